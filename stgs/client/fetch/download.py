"""HTTP downloads for the player: one keep-alive aiohttp session, timeouts, retries, throughput samples.

Every request is size-capped before its body is read (Content-Length) and
while it is read (the cap the manifest implies), retried with exponential
backoff on connection errors, timeouts, truncated bodies and 5xx/429 within
one deadline for the request and its retries, and recorded as a throughput
sample (bytes, seconds, time to first byte) for the ABR. A progress callback
can abandon a transfer mid-way. Every URL, redirects included, passes the
playback's URL policy (stgs.client.urlpolicy) before it is fetched.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urljoin

import aiohttp

from stgs.client.urlpolicy import PolicyResolver, RefusedAddressError, RefusedUrlError, UrlPolicy, UrlPolicySettings

CHUNK = 1 << 16
RETRY_STATUS = frozenset({408, 429, 500, 502, 503, 504})
REDIRECT_STATUS = frozenset({301, 302, 303, 307, 308})
MAX_REDIRECTS = 5


@dataclass
class DownloadSettings:
    """Network behaviour of the player's downloader."""

    connect_timeout_s: float = 5.0
    """Seconds to open a connection."""
    read_timeout_s: float = 10.0
    """Seconds without any byte arriving before a request fails."""
    total_timeout_s: float = 120.0
    """Seconds one request may take in all, its retries included (a server that drips bytes is cut here)."""
    retries: int = 3
    """Retries after the first attempt (connection errors, timeouts, 5xx, truncated bodies)."""
    backoff_s: float = 0.25
    """First retry delay; doubles per retry."""
    max_backoff_s: float = 4.0
    """Longest retry delay."""
    connections: int = 4
    """Keep-alive connections to the server."""
    concurrent: bool = True
    """Request a GOP's keyframe and features at once (one round trip per GOP instead of two)."""

    def backoff(self, attempt: int) -> float:
        """Seconds to wait before retry number `attempt` (1, 2, ...)."""
        return min(self.max_backoff_s, self.backoff_s * 2 ** (attempt - 1))


@dataclass
class Sample:
    """One finished (or abandoned) HTTP transfer."""

    url: str
    kind: str
    """keyframe, init, media or document."""
    bytes: int
    seconds: float
    """Request start to last byte."""
    ttfb: float
    """Request start to response headers."""
    status: int
    attempts: int = 1
    abandoned: bool = False

    @property
    def kbps(self) -> float:
        return self.bytes * 8 / 1e3 / max(self.seconds, 1e-6)


class FetchError(Exception):
    """A download that failed for good (after retries where retrying makes sense)."""

    def __init__(self, url: str, reason: str, attempts: int = 1):
        super().__init__(f"{url}: {reason}" + (f" (after {attempts} attempts)" if attempts > 1 else ""))
        self.url, self.reason, self.attempts = url, reason, attempts


class AbandonError(Exception):
    """The progress callback asked to drop this transfer; `sample` counts the wasted bytes."""

    def __init__(self, sample: Sample):
        super().__init__(f"abandoned {sample.url} after {sample.bytes} bytes")
        self.sample = sample


class TransientError(Exception):
    """A failure worth retrying: connection error, timeout, truncated body, HTTP 408/429/5xx."""


Progress = Callable[[int, int | None, float, float], bool]
"""(bytes so far, Content-Length or None, seconds since the request started, seconds to the response headers)
-> abandon?"""


@dataclass
class Downloader:
    """The player's HTTP client; use as `async with Downloader(settings) as d`."""

    settings: DownloadSettings = field(default_factory=DownloadSettings)
    policy: UrlPolicy = field(default_factory=lambda: UrlPolicy("", UrlPolicySettings(any_host=True, loopback=True)))
    """What may be fetched (default: any http(s) host, never a link-local address)."""
    samples: list[Sample] = field(default_factory=list)
    """Every transfer so far, in completion order."""
    retries: int = 0
    """Retries made so far (all requests)."""

    async def __aenter__(self) -> Downloader:
        s = self.settings
        timeout = aiohttp.ClientTimeout(total=s.total_timeout_s, sock_connect=s.connect_timeout_s,
                                        sock_read=s.read_timeout_s)
        connector = aiohttp.TCPConnector(limit=s.connections, resolver=PolicyResolver(self.policy))
        self._session = aiohttp.ClientSession(timeout=timeout, connector=connector, auto_decompress=False)
        return self

    async def __aexit__(self, *exc) -> None:
        await self._session.close()

    async def fetch(self, url: str, kind: str, max_bytes: int, progress: Progress | None = None) -> bytes:
        """The body of `url` (200 only), at most max_bytes; raises FetchError or AbandonError."""
        settings = self.settings
        attempts = settings.retries + 1
        deadline = time.perf_counter() + settings.total_timeout_s
        last = "no attempt"
        for attempt in range(1, attempts + 1):
            left = deadline - time.perf_counter()
            if left <= 0:
                raise FetchError(url, f"{last}; no answer within {settings.total_timeout_s:g} s", attempt - 1)
            try:
                data, sample = await self.fetch_once(url, kind, max_bytes, progress, left)
            except TransientError as exc:
                last = str(exc)
                if attempt < attempts:
                    self.retries += 1
                    await asyncio.sleep(min(settings.backoff(attempt), max(0.0, deadline - time.perf_counter())))
                continue
            sample.attempts = attempt
            return data
        raise FetchError(url, last, attempts)

    async def fetch_once(self, url: str, kind: str, max_bytes: int, progress: Progress | None = None,
                         time_left: float | None = None) -> tuple[bytes, Sample]:
        """One attempt at `url` (no retry; redirects followed, each checked by the policy) within `time_left`
        seconds (None: the settings' total): its body and sample; raises TransientError, FetchError or
        AbandonError. Every finished transfer is appended to `samples`."""
        start = time.perf_counter()
        s = self.settings
        total = s.total_timeout_s if time_left is None else max(1e-3, min(time_left, s.total_timeout_s))
        timeout = aiohttp.ClientTimeout(total=total, sock_connect=s.connect_timeout_s, sock_read=s.read_timeout_s)
        where = url
        try:
            for _ in range(MAX_REDIRECTS + 1):
                self.policy.check(where)
                async with self._session.get(where, allow_redirects=False, timeout=timeout) as resp:
                    if resp.status in REDIRECT_STATUS:
                        location = resp.headers.get("Location")
                        if not location:
                            raise FetchError(url, f"HTTP {resp.status} without a Location")
                        where = urljoin(str(resp.url), location)
                        continue
                    return await self._read(resp, url, kind, max_bytes, progress, start)
            raise FetchError(url, f"more than {MAX_REDIRECTS} redirects")
        except RefusedUrlError as exc:
            raise FetchError(url, f"refused by the URL policy: {exc}") from None
        except aiohttp.ClientConnectorError as exc:
            if isinstance(exc.os_error, RefusedAddressError):
                raise FetchError(url, f"refused by the URL policy: {exc.os_error}") from None
            raise TransientError(f"{type(exc).__name__}: {exc}".rstrip(": ")) from exc
        except (TimeoutError, aiohttp.ClientError, ConnectionError) as exc:
            raise TransientError(f"{type(exc).__name__}: {exc}".rstrip(": ")) from exc

    async def _read(self, resp: aiohttp.ClientResponse, url: str, kind: str, max_bytes: int,
                    progress: Progress | None, start: float) -> tuple[bytes, Sample]:
        ttfb = time.perf_counter() - start
        if resp.status in RETRY_STATUS:
            raise TransientError(f"HTTP {resp.status}")
        if resp.status != 200:
            raise FetchError(url, f"HTTP {resp.status} {resp.reason or ''}".rstrip())
        length = resp.content_length
        if length is not None and length > max_bytes:
            raise FetchError(url, f"{length} bytes announced, over the {max_bytes}-byte limit")
        body = bytearray()
        async for chunk in resp.content.iter_chunked(CHUNK):
            body += chunk
            if len(body) > max_bytes:
                raise FetchError(url, f"body exceeds the {max_bytes}-byte limit")
            if progress is not None and progress(len(body), length, time.perf_counter() - start, ttfb):
                resp.close()
                raise AbandonError(Sample(url, kind, len(body), time.perf_counter() - start, ttfb,
                                          resp.status, abandoned=True))
        if length is not None and len(body) != length:
            raise TransientError(f"truncated body ({len(body)} of {length} bytes)")
        sample = Sample(url, kind, len(body), time.perf_counter() - start, ttfb, resp.status)
        self.samples.append(sample)
        return bytes(body), sample
