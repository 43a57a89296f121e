"""Accounting: Prometheus metrics (one path: every answered request goes through `Metrics.answered`) and the
JSON access log."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import os
import time
from collections.abc import AsyncIterator

from aiohttp import web
from aiohttp.abc import AbstractAccessLogger
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest, multiprocess

from stgs.server.config import METRICS_KEY
from stgs.server.responses import body_bytes, is_file_response
from stgs.server.slots import TransferSlots

MULTIPROCESS_ENV = "PROMETHEUS_MULTIPROC_DIR"
"""Set (to a folder shared by the workers) when several processes serve: prometheus_client then keeps every
value in a file there, and /metrics reads them all."""


class Metrics:
    """Prometheus metrics of one app (own registry, so tests can run several apps).

    Each update of a prometheus_client metric takes a lock (and, with several workers, writes an mmap'ed
    file): ~13 µs per request for the five a request made. Requests therefore count into plain integers,
    folded into the Prometheus metrics by `flush` — before every /metrics answer and every FLUSH_SECONDS
    (so with several workers the others' figures lag by at most that). The latency histogram is observed
    per request: prometheus_client has no bulk update for it.
    """

    FLUSH_SECONDS = 1.0

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("stgs_http_requests", "HTTP requests", ["method", "status"],
                                registry=self.registry)
        self.bytes = Counter("stgs_http_sent_bytes", "Body bytes sent", registry=self.registry)
        self.in_flight = Gauge("stgs_http_in_flight", "Requests being handled", registry=self.registry,
                               multiprocess_mode="livesum")
        self.latency = Histogram("stgs_http_request_seconds", "Request handling time including the transfer",
                                 buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
                                 registry=self.registry)
        self.parked = Gauge("stgs_transfers_waiting", "Transfers parked on a client that takes no bytes",
                            registry=self.registry, multiprocess_mode="livesum")
        self.shed = Counter("stgs_transfers_shed", "Waiting transfers reset to make room for another",
                            registry=self.registry)
        self.slots: TransferSlots | None = None
        """The app's TransferSlots, once it has started (their counts are folded in at each flush)."""
        self._shed_seen = 0
        self.handling = 0
        """Requests being handled now (the gauge gets it at each flush)."""
        self._answered: collections.Counter[tuple[str, int]] = collections.Counter()
        self._sent = 0

    def answered(self, method: str, status: int, seconds: float, body_bytes: int) -> None:
        """One request answered: its status, handling time (the transfer included) and body bytes."""
        self._answered[(method, status)] += 1
        self.latency.observe(seconds)
        self._sent += body_bytes

    def flush(self) -> None:
        """Fold the counts kept since the last flush into the Prometheus metrics."""
        answered, self._answered = self._answered, collections.Counter()
        for (method, status), count in answered.items():
            self.requests.labels(method, str(status)).inc(count)
        sent, self._sent = self._sent, 0
        if sent:
            self.bytes.inc(sent)
        self.in_flight.set(self.handling)
        if self.slots is not None:
            self.parked.set(self.slots.parked)
            if self.slots.shed > self._shed_seen:
                self.shed.inc(self.slots.shed - self._shed_seen)
                self._shed_seen = self.slots.shed

    def exposition(self) -> bytes:
        """The text format: this process's values, or with several workers the sum over all of them."""
        self.flush()
        if MULTIPROCESS_ENV not in os.environ:
            return generate_latest(self.registry)
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry)


async def flush_metrics(app: web.Application) -> AsyncIterator[None]:
    """Cleanup context: flushes the app's metrics every Metrics.FLUSH_SECONDS and once more at shutdown."""
    metrics: Metrics = app[METRICS_KEY]

    async def periodically() -> None:
        while True:
            await asyncio.sleep(metrics.FLUSH_SECONDS)
            metrics.flush()

    task = asyncio.create_task(periodically())
    yield
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    metrics.flush()


class JsonAccessLogger(AbstractAccessLogger):
    """One JSON object per request: time, peer address (and the forwarded client behind a trusted proxy), method,
    path, range, status, body bytes, seconds."""

    @property
    def enabled(self) -> bool:
        return self.logger.isEnabledFor(logging.INFO)

    def log(self, request: web.BaseRequest, response: web.StreamResponse, time_s: float) -> None:
        line = {"ts": round(time.time(), 3), "remote": request.remote, "method": request.method,
                "path": request.path, "range": request.headers.get("Range"), "status": response.status,
                "bytes": body_bytes(request, response), "seconds": round(time_s, 6)}
        client = getattr(response, "client", "")
        if client and client != request.remote:  # a trusted proxy's forwarded client (stgs.server.clients)
            line["client"] = client
        self.logger.info(json.dumps(line))


@web.middleware
async def observe(request: web.Request, handler) -> web.StreamResponse:
    """Count requests by status; file responses report themselves once their transfer ends (it happens later)."""
    m: Metrics = request.app[METRICS_KEY]
    start = time.perf_counter()
    m.handling += 1
    status = 500
    response = None
    try:
        response = await handler(request)
        status = response.status
        return response
    except web.HTTPException as exc:
        status = exc.status
        raise
    finally:
        m.handling -= 1
        if not is_file_response(response):
            m.answered(request.method, status, time.perf_counter() - start,
                       body_bytes(request, response) if response is not None else 0)
