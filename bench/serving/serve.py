"""Server benchmark: `stgs serve` vs nginx on the same files, same machine (`stgs bench serve`).

Both servers run on loopback; wrk (one thread, keep-alive, round-robin over
every segment of a packaged scene) measures throughput and latency
percentiles at each client count. Report the ratio to nginx measured in the
same run. Only loopback addresses are used; every run is bounded in time.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from stgs.errors import StgsError
from stgs.tree import SEGMENT_SUFFIXES

WRK_SCRIPT = """
paths = {{{paths}}}
i = 0
request = function()
  i = (i % #paths) + 1
  return wrk.format("GET", paths[i])
end
"""

NGINX_CONF = """
worker_processes {workers};
pid {tmp}/nginx.pid;
error_log {tmp}/error.log;
events {{ worker_connections 4096; }}
http {{
  access_log off;
  sendfile on;
  tcp_nopush on;
  keepalive_requests 1000000;
  client_body_temp_path {tmp}/body;
  proxy_temp_path {tmp}/proxy;
  fastcgi_temp_path {tmp}/fastcgi;
  uwsgi_temp_path {tmp}/uwsgi;
  scgi_temp_path {tmp}/scgi;
  types {{ application/dash+xml mpd; video/mp4 mp4; video/iso.segment m4s; }}
  server {{
    listen 127.0.0.1:{port};
    root {root};
  }}
}}
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"server on port {port} did not start")


def check_serves(port: int, path: str) -> None:
    """Fail loudly unless the server answers 200 for a segment (a benchmark of 403s measures nothing)."""
    import urllib.request

    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/{path}", timeout=5) as resp:
            status = resp.status
    except OSError as exc:
        raise RuntimeError(f"server on port {port} does not serve /{path}: {exc}") from exc
    if status != 200:
        raise RuntimeError(f"server on port {port} answered {status} for /{path}")


def parse_wrk(text: str) -> dict:
    def seconds(value: str) -> float:
        number, unit = re.match(r"([\d.]+)(us|ms|s|m)", value).groups()
        return float(number) * {"us": 1e-6, "ms": 1e-3, "s": 1.0, "m": 60.0}[unit]

    def size(value: str) -> float:
        number, unit = re.match(r"([\d.]+)([KMG]?B)", value).groups()
        return float(number) * {"B": 1, "KB": 1024, "MB": 1024 ** 2, "GB": 1024 ** 3}[unit]

    pct = dict(re.findall(r"^\s+(50|99)(?:\.000)?%\s+(\S+)", text, re.M))
    return {"rps": float(re.search(r"Requests/sec:\s+([\d.]+)", text).group(1)),
            "mbps": size(re.search(r"Transfer/sec:\s+(\S+)", text).group(1)) / 1024 ** 2,
            "p50_ms": seconds(pct["50"]) * 1e3, "p99_ms": seconds(pct["99"]) * 1e3,
            "errors": int(m.group(1)) if (m := re.search(r"Non-2xx or 3xx responses:\s+(\d+)", text)) else 0}


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU time the processes have used so far (utime + stime of /proc/PID/stat)."""
    ticks = 0
    for pid in pids:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        ticks += int(fields[11]) + int(fields[12])
    return ticks / os.sysconf("SC_CLK_TCK")


def cpu_per_request(pids: list[int], port: int, script: Path, clients: int, seconds: int) -> tuple[float, float, str]:
    """One wrk run (one thread, keep-alive) against the server on port: (CPU µs the processes `pids` spent per
    request, requests per second, wrk's output)."""
    before = cpu_seconds(pids)
    out = wrk_output(port, script, clients, seconds)
    used = cpu_seconds(pids) - before
    requests = int(re.search(r"(\d+) requests in", out).group(1))
    return used / requests * 1e6, requests / seconds, out


def wrk_output(port: int, script: Path, clients: int, seconds: int, *flags: str) -> str:
    """wrk's report of one run (one thread, `clients` keep-alive connections) against the server on port."""
    cmd = ["wrk", "-t", "1", "-c", str(clients), "-d", f"{seconds}s", *flags, "-s", str(script),
           f"http://127.0.0.1:{port}/"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 30, check=True).stdout


def run_wrk(port: int, script: Path, clients: int, seconds: int) -> dict:
    return parse_wrk(wrk_output(port, script, clients, seconds, "--latency"))


def main(scene_dir: Path | None, clients: list[int], seconds: int) -> int:
    for tool in ("nginx", "wrk"):
        if shutil.which(tool) is None and not Path(f"/usr/sbin/{tool}").exists():
            raise StgsError(f"{tool} is required for this benchmark (Debian: apt-get install nginx wrk)")
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        tmp.chmod(0o755)  # nginx's workers run as another user and must reach the files
        if scene_dir is None:
            from stgs.packager import PackConfig, pack
            from stgs.synth import PRESETS, synthesize

            # Serving does not care how well the scene is fitted: a short fit is enough.
            synthesize(dataclasses.replace(PRESETS["demo"], fit_steps=20), tmp / "model", progress=False)
            scene_dir = tmp / "dash"
            pack(tmp / "model", scene_dir, PackConfig(ladder="fixed"), progress=False)
        scene_dir = Path(scene_dir).resolve()
        paths = sorted(str(p.relative_to(scene_dir)) for p in scene_dir.rglob("*")
                       if p.suffix in SEGMENT_SUFFIXES)
        sizes = [(scene_dir / p).stat().st_size for p in paths]
        script = tmp / "paths.lua"
        script.write_text(WRK_SCRIPT.format(paths=", ".join(f'"/{p}"' for p in paths)))
        stgs_port, nginx_port = free_port(), free_port()
        conf = tmp / "nginx.conf"
        workers = os.cpu_count() or 1
        conf.write_text(NGINX_CONF.format(tmp=tmp, port=nginx_port, root=scene_dir, workers=workers))
        nginx_bin = shutil.which("nginx") or "/usr/sbin/nginx"
        servers = [subprocess.Popen([sys.executable, "-m", "stgs.cli", "serve", str(scene_dir), "--port",
                                     str(stgs_port), "--workers", str(workers), "--quiet"], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL),
                   subprocess.Popen([nginx_bin, "-c", str(conf), "-g", "daemon off;"], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)]
        try:
            wait_for(stgs_port)
            wait_for(nginx_port)
            for port in (stgs_port, nginx_port):
                check_serves(port, paths[0])
            print(f"<!-- stgs bench serve: {len(paths)} segments, mean {sum(sizes) / len(sizes) / 1024:.0f} KB, "
                  f"wrk -t1 -d{seconds}s per cell, stgs serve and nginx with {workers} workers each on one "
                  f"{os.cpu_count()}-core machine -->")
            print("| clients | stgs MB/s | nginx MB/s | throughput ratio | stgs p50 ms | nginx p50 ms "
                  "| stgs p99 ms | nginx p99 ms | p99 ratio | errors (stgs/nginx) |")
            print("|---|---|---|---|---|---|---|---|---|---|")
            for n in clients:
                ours = run_wrk(stgs_port, script, n, seconds)
                theirs = run_wrk(nginx_port, script, n, seconds)
                print(f"| {n} | {ours['mbps']:.0f} | {theirs['mbps']:.0f} | {ours['mbps'] / theirs['mbps']:.2f} "
                      f"| {ours['p50_ms']:.2f} | {theirs['p50_ms']:.2f} | {ours['p99_ms']:.2f} "
                      f"| {theirs['p99_ms']:.2f} | {ours['p99_ms'] / theirs['p99_ms']:.2f} "
                      f"| {ours['errors']}/{theirs['errors']} |", flush=True)
        finally:
            for proc in servers:
                proc.terminate()
                try:
                    proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    proc.kill()
    return 0
