#!/usr/bin/env python3
"""How close `stgs serve` is to the cheapest aiohttp file server, and both to nginx (CPU per request under wrk).

Three servers take turns on the same packaged scene, 2 processes each (SO_REUSEPORT for the Python ones),
the order rotating by round: `stgs serve --workers 2 --quiet`; the floor, an aiohttp low-level server
(aiohttp.web.Server, no application, router, middleware, metrics or path checks) whose handler looks the URL
up in a dict of the scene's files and sends the file as `stgs serve` does (one os.sendfile on the socket); and
nginx (sendfile, access log off). Each run: wrk (one thread, keep-alive, round-robin over every segment) at
`--clients`, and the servers' CPU time (utime + stime of /proc/PID/stat) before and after. The floor bounds
what any aiohttp server can reach on this machine; the gap between it and `stgs serve` is what our own
Python costs.

`--gunicorn` adds a fourth: the same app under gunicorn's aiohttp worker (2 workers), the measurement behind
running our own worker processes (stgs/server/workers.py). gunicorn is not a dependency of the project; install it
in the venv for this (`.venv/bin/pip install gunicorn`).

Usage: .venv/bin/python -m bench.serving.serve_floor DASH_DIR [--rounds 4] [--clients 64] [--seconds 6] [--gunicorn]
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.serving.serve import (
    NGINX_CONF,
    WRK_SCRIPT,
    check_serves,
    cpu_per_request,
    free_port,
    wait_for,
)
from stgs.server.workers import child_pids, worker_pids
from stgs.tree import SEGMENT_SUFFIXES

SERVERS = ("stgs serve", "aiohttp floor", "nginx")
GUNICORN = "gunicorn aiohttp worker"
CHECKOUT = Path(__file__).resolve().parents[1]
"""Where `python -m bench.serving.serve_floor` finds the bench package (benchmarks are not installed)."""


def gunicorn_app():
    """The factory gunicorn calls: the app `stgs serve` builds, for the folder in $STGS_BENCH_ROOT."""
    from stgs.server.app import build_app
    from stgs.server.config import ServeConfig

    return build_app(ServeConfig(root=Path(os.environ["STGS_BENCH_ROOT"]), access_log=False))


def floor_server(root: Path, port: int) -> None:
    """The cheapest aiohttp server of the scene's files: a dict lookup, then the body as `stgs serve` sends it."""
    from aiohttp import web

    from stgs.server.files import open_and_stat
    from stgs.server.sending import Sender, send_file_body

    files = {f"/{p.relative_to(root)}": str(p) for p in root.rglob("*") if p.is_file()}

    async def handle(request: web.BaseRequest) -> web.StreamResponse:
        path = files.get(request.path)
        if path is None:
            raise web.HTTPNotFound()
        fd, st = open_and_stat(path)
        try:
            response = web.StreamResponse(headers={"Content-Type": "video/iso.segment",
                                                   "Content-Length": str(st.st_size)})
            await response.prepare(request)
            await send_file_body(request, fd, 0, st.st_size, [0], 30.0, Sender())
            await response.write_eof()
            return response
        finally:
            os.close(fd)

    async def serve() -> None:
        runner = web.ServerRunner(web.Server(handle, access_log=None))
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", port, reuse_port=True).start()
        await asyncio.Event().wait()

    asyncio.run(serve())


def start(name: str, dash: Path, port: int, tmp: Path) -> tuple[list[subprocess.Popen], list[int]]:
    """The server's processes (to stop) and the pids that do its work (to measure)."""
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    if name == "stgs serve":
        proc = subprocess.Popen([sys.executable, "-m", "stgs.cli", "serve", str(dash), "--port", str(port),
                                 "--workers", "2", "--quiet"], **quiet)
        wait_for(port)
        return [proc], worker_pids(proc.pid)
    if name == "aiohttp floor":
        command = [sys.executable, "-m", "bench.serving.serve_floor", str(dash), "--floor-server", str(port)]
        procs = [subprocess.Popen(command, cwd=CHECKOUT, **quiet) for _ in range(2)]
        wait_for(port)
        return procs, [proc.pid for proc in procs]
    if name == GUNICORN:
        proc = subprocess.Popen([sys.executable, "-m", "gunicorn", "bench.serving.serve_floor:gunicorn_app()",
                                 "--worker-class", "aiohttp.GunicornWebWorker", "--workers", "2",
                                 "--bind", f"127.0.0.1:{port}"], cwd=CHECKOUT,
                                env=dict(os.environ, STGS_BENCH_ROOT=str(dash)), **quiet)
        wait_for(port)
        return [proc], child_pids(proc.pid)
    conf = tmp / "nginx.conf"
    conf.write_text(NGINX_CONF.format(tmp=tmp, port=port, root=dash, workers=2))
    proc = subprocess.Popen([shutil.which("nginx") or "/usr/sbin/nginx", "-c", str(conf), "-g", "daemon off;"], **quiet)
    wait_for(port)
    return [proc], child_pids(proc.pid)


def measure(name: str, dash: Path, script: Path, first: str, tmp: Path, clients: int, seconds: int
            ) -> tuple[float, float]:
    """(server CPU µs per request, requests per second) of one run."""
    port = free_port()
    procs, pids = start(name, dash, port, tmp)
    try:
        check_serves(port, first)
        us, rps, out = cpu_per_request(pids, port, script, clients, seconds)
    finally:
        for proc in procs:
            proc.terminate()  # nginx's master takes its workers along; stgs serve's parent its workers
        for proc in procs:
            proc.wait(timeout=30)
    if "Non-2xx" in out:
        raise RuntimeError(f"{name}: errors under load:\n{out}")
    return us, rps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dash", type=Path, help="a packaged scene (stgs pack output)")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--clients", type=int, default=64)
    parser.add_argument("--seconds", type=int, default=6)
    parser.add_argument("--gunicorn", action="store_true", help="also gunicorn's aiohttp worker")
    parser.add_argument("--floor-server", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = parser.parse_args()
    dash = args.dash.resolve()
    if args.floor_server is not None:
        floor_server(dash, args.floor_server)
        return 0
    paths = sorted(str(p.relative_to(dash)) for p in dash.rglob("*") if p.suffix in SEGMENT_SUFFIXES)
    if not paths:
        raise SystemExit(f"{dash}: no segments (expected a folder written by stgs pack)")
    servers = (*SERVERS, GUNICORN) if args.gunicorn else SERVERS
    if args.gunicorn and importlib.util.find_spec("gunicorn") is None:
        raise SystemExit("gunicorn is not installed (.venv/bin/pip install gunicorn)")
    results: dict[str, list[tuple[float, float]]] = {name: [] for name in servers}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        tmp.chmod(0o755)  # nginx's workers run as another user
        script = tmp / "paths.lua"
        script.write_text(WRK_SCRIPT.format(paths=", ".join(f'"/{p}"' for p in paths)))
        for r in range(args.rounds):
            for name in servers[r % len(servers):] + servers[:r % len(servers)]:
                results[name].append(measure(name, dash, script, paths[0], tmp, args.clients, args.seconds))
                us, rps = results[name][-1]
                print(f"round {r + 1} {name}: {us:.0f} us CPU per request, {rps:.0f} requests/s", flush=True)
    nginx_rps = statistics.median(r for _, r in results["nginx"])
    print(f"\n| server ({args.clients} clients) | server CPU µs per request (median) | requests/s (median) "
          "| requests/s ratio to nginx |")
    print("|---|---|---|---|")
    for name, runs in results.items():
        rps = statistics.median(r for _, r in runs)
        print(f"| {name} | {statistics.median(u for u, _ in runs):.0f} | {rps:.0f} | {rps / nginx_rps:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
