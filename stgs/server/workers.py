"""Running the app: SceneRunner (the fast path in front of the app), one process or several on one port
(SO_REUSEPORT), graceful shutdown on SIGINT/SIGTERM.

Why our own processes rather than gunicorn's aiohttp worker: gunicorn runs the app through aiohttp's router,
without the fast path, which serves fewer requests for more CPU per request (`bench/serving/serve_floor.py
--gunicorn`; docs/BENCHMARKS.md, "Server"), besides adding a dependency."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import dataclasses
import logging
import multiprocessing
import multiprocessing.synchronize
import os
import signal
import socket
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from aiohttp import web
from prometheus_client import multiprocess

from stgs.server.app import SceneRunner, build_app
from stgs.server.config import ServeConfig
from stgs.server.metrics import MULTIPROCESS_ENV, JsonAccessLogger
from stgs.server.slots import reserve_descriptors


def run(cfg: ServeConfig) -> None:
    """Serve until SIGINT/SIGTERM; in-flight transfers get cfg.shutdown_timeout seconds to finish."""
    reserve_descriptors(cfg.max_transfers, cfg.max_waiting_transfers)  # before a port is taken; workers inherit it
    if cfg.workers == 1:
        serve_process(cfg)
    else:
        run_workers(cfg)


@contextlib.contextmanager
def reserved_port(host: str, port: int) -> Iterator[int]:
    """Hold (host, port) with SO_REUSEPORT so that port 0 becomes one port every worker then binds too."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
        yield sock.getsockname()[1]  # bound but never listening: the kernel hands it no connections


def run_workers(cfg: ServeConfig) -> None:
    """cfg.workers processes on one port; SIGTERM/SIGINT reach each, which shuts down as a single server does."""
    with tempfile.TemporaryDirectory(prefix="stgs-metrics-") as metrics_dir, \
            reserved_port(cfg.host, cfg.port) as port:
        os.environ[MULTIPROCESS_ENV] = metrics_dir  # inherited by the workers, which import prometheus afresh
        spawn = multiprocessing.get_context("spawn")
        listening = [spawn.Event() for _ in range(cfg.workers)]
        procs = [spawn.Process(target=serve_process, args=(dataclasses.replace(cfg, port=port), event),
                               name=f"stgs-serve-{i}") for i, event in enumerate(listening)]
        stopping = []

        def stop(signum: int, frame: object) -> None:
            stopping.append(signum)
            for proc in procs:
                if proc.pid is not None and proc.is_alive():
                    os.kill(proc.pid, signal.SIGTERM)

        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
        for proc in procs:
            if not stopping:
                proc.start()
        procs = [proc for proc in procs if proc.pid is not None]
        for proc, event in zip(procs, listening, strict=False):
            while not event.wait(0.1) and proc.is_alive():
                pass
        if all(event.is_set() for event in listening):  # announced once every worker takes connections
            print(f"stgs serve: ======== Running on http://{cfg.host}:{port} ({cfg.workers} workers) ========\n"
                  "(Press CTRL+C to quit)", flush=True)
        for proc in procs:
            proc.join()
            multiprocess.mark_process_dead(proc.pid)
        failed = [proc.exitcode for proc in procs if proc.exitcode]
        if failed:
            raise SystemExit(f"stgs serve: {len(failed)} of {len(procs)} workers failed (exit {failed[0]})")


def leave_signals_to_parent() -> None:
    """A worker takes signals from the parent only: its own process group (a terminal's Ctrl-C or a group kill
    would otherwise arrive twice, and a second SIGTERM cuts the graceful shutdown), and SIGTERM if the parent dies."""
    os.setpgid(0, 0)
    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGTERM)
    parent = multiprocessing.parent_process()
    if parent is not None and os.getppid() != parent.pid:  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


def serve_process(cfg: ServeConfig, listening: multiprocessing.synchronize.Event | None = None) -> None:
    """One server process; a worker of several sets `listening` instead of printing where it listens."""
    if listening is not None:
        leave_signals_to_parent()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    access = logging.getLogger("stgs.access")
    access.setLevel(logging.INFO if cfg.access_log else logging.WARNING)
    if listening is None:
        def announce(msg: str) -> None:
            print(f"stgs serve: {msg}", flush=True)
    else:
        def announce(msg: str) -> None:
            listening.set()
    asyncio.run(serve_until_signalled(cfg, access, announce))


async def serve_until_signalled(cfg: ServeConfig, access: logging.Logger, announce: Callable[[str], None]) -> None:
    """Serve cfg on its address until SIGINT/SIGTERM, then stop listening and give in-flight transfers
    cfg.shutdown_timeout seconds (aiohttp's graceful shutdown, as web.run_app does it)."""
    runner = SceneRunner(build_app(cfg), shutdown_timeout=cfg.shutdown_timeout, keepalive_timeout=cfg.keepalive_timeout,
                         access_log_class=JsonAccessLogger, access_log=access, max_line_size=cfg.max_header_bytes,
                         max_field_size=cfg.max_header_bytes, max_headers=cfg.max_headers)
    await runner.setup()
    try:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, stop.set)
        site = web.TCPSite(runner, cfg.host, cfg.port, reuse_port=cfg.workers > 1 or None)
        await site.start()
        announce(f"======== Running on {site.name} ========\n(Press CTRL+C to quit)")
        await stop.wait()
    finally:
        await runner.cleanup()


def child_pids(pid: int) -> list[int]:
    """The child processes of process `pid` (Linux: /proc)."""
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def worker_pids(pid: int) -> list[int]:
    """The worker processes of a `stgs serve --workers N` parent (its multiprocessing spawn children; Linux)."""
    return [c for c in child_pids(pid) if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
