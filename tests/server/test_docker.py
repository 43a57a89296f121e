"""docker/: the Dockerfiles and the compose file have the pieces a deployment needs.

No Docker engine runs here, so the images are not built; this checks the files
and that the server's entry point really needs none of the heavy packages the
server image leaves out.
"""

from __future__ import annotations

import re
import subprocess
import sys
from importlib.metadata import requires
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
LOCK = ROOT / "requirements.lock"


def instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_server_image():
    ins = instructions(DOCKER / "server.Dockerfile")
    kinds = [k for k, _ in ins]
    final = [a for k, a in ins if k == "FROM"][-1]
    assert final.startswith("python:") and "slim" in final
    user = [a for k, a in ins if k == "USER"]
    assert user and user[-1] not in ("root", "0")
    assert any(k == "HEALTHCHECK" and "/healthz" in a for k, a in ins)
    assert any(k == "VOLUME" and "/data" in a for k, a in ins)
    assert "EXPOSE" in kinds and "ENTRYPOINT" in kinds
    assert any(k == "RUN" and "requirements.lock" in a for k, a in ins)


def test_server_image_serves_the_web_player():
    """A Node stage builds web/dist from the lockfile; only the build reaches the final image, and the server is
    pointed at it (else /player/ answers 503)."""
    path = DOCKER / "server.Dockerfile"
    web_stage = stage(path, "web")
    assert web_stage[0][1].startswith("node:20") and "slim" in web_stage[0][1]
    runs = [a for k, a in web_stage if k == "RUN"]
    assert any(a.startswith("npm ci") for a in runs) and "node build.mjs" in runs
    copies = [a for k, a in web_stage if k == "COPY"]
    assert any("package-lock.json" in a for a in copies)
    for needed in ("web/build.mjs", "web/tsconfig.json", "web/src"):  # what build.mjs reads
        assert any(needed in a for a in copies), needed
    final = instructions(path)
    assert ("COPY", "--from=web /web/dist ./web/dist") in final
    cmd = next(a for k, a in reversed(final) if k == "CMD")
    assert '"--player-dir", "/app/web/dist"' in cmd
    workdir = [a for k, a in final if k == "WORKDIR"][-1]
    assert workdir == "/app"


def server_slice_pattern() -> re.Pattern:
    run = next(a for k, a in instructions(DOCKER / "server.Dockerfile") if k == "RUN" and "grep" in a)
    return re.compile(re.search(r"'(\^\(.*?\)==)'", run).group(1))


def closure(package: str) -> set[str]:
    """The package and everything it requires on this Python (no extras), as normalised names."""
    todo, seen = [package], set()
    while todo:
        name = re.sub(r"[-_.]+", "_", todo.pop()).lower()
        if name in seen:
            continue
        seen.add(name)
        for text in requires(name) or []:
            req = Requirement(text)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                todo.append(req.name)
    return seen


def test_server_slice_covers_what_the_server_imports():
    pattern = server_slice_pattern()
    pinned = {re.sub(r"[-_.]+", "_", line.split("==")[0]).lower() for line in LOCK.read_text().splitlines()
              if pattern.match(line)}
    needed = set().union(*(closure(p) for p in ("aiohttp", "lxml", "prometheus_client")))
    assert needed <= pinned, f"missing from the server image: {sorted(needed - pinned)}"


def test_stgs_serve_runs_with_torch_and_numpy_unimportable(tmp_path):
    """The `stgs serve` command line as the console script runs it, in a process where importing torch, numpy or
    OpenCV fails: it gets as far as checking its ROOT (the server itself is imported at run time)."""
    code = ("import sys; sys.modules.update(torch=None, numpy=None, cv2=None); from stgs.cli import main; "
            "import stgs.server.app, stgs.server.workers, stgs.server.catalogue; "
            f"sys.exit(main(['serve', {str(tmp_path / 'missing')!r}]))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert result.returncode == 2 and result.stderr.strip() == f"stgs: {tmp_path / 'missing'}: not a folder", \
        result.stderr


def test_server_entry_point_needs_no_torch():
    code = ("import sys; from stgs.cli import build_parser; build_parser(('serve',)); import stgs.server.workers; "
            "sys.exit(1 if {'torch', 'numpy', 'cv2'} & set(sys.modules) else 0)")
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_packager_image():
    ins = instructions(DOCKER / "packager.Dockerfile")
    assert ins[0][0] == "FROM" and "slim" in ins[0][1]
    assert any(k == "RUN" and "g++" in a and "apt-get" in a for k, a in ins)  # the native kernels' compiler
    assert not any(k == "RUN" and "ffmpeg" in a for k, a in ins)  # video goes through PyAV's own FFmpeg
    assert re.search(r"^av==", LOCK.read_text(), re.M)
    assert any(k == "RUN" and "-r requirements.lock" in a for k, a in ins)
    user = [a for k, a in ins if k == "USER"]
    assert user and user[-1] not in ("root", "0")


def test_compose_puts_a_caching_proxy_in_front():
    compose = (DOCKER / "compose.yaml").read_text()
    assert re.search(r"^  server:", compose, re.M) and re.search(r"^  cache:", compose, re.M)
    assert "image: nginx" in compose and "server.Dockerfile" in compose
    conf = (DOCKER / "nginx-cache.conf").read_text()
    assert "proxy_cache_path" in conf and "proxy_pass http://server:8080" in conf
    assert "proxy_cache stgs;" in conf
    # the server's connections all come from the proxy: connections per client are the proxy's to limit
    server_section = compose.split("  cache:")[0]
    assert '"--max-connections-per-client", "0"' in server_section
    assert re.search(r"limit_conn \w+ \d+;", conf) and "limit_conn_zone $binary_remote_addr" in conf
    # the transfer limits key on the client the proxy forwards (overwritten, so a client cannot choose it)
    assert "proxy_set_header X-Forwarded-For $remote_addr;" in conf


def test_compose_server_command_is_a_valid_configuration(tmp_path):
    """The compose file's `stgs serve` flags parse and make a ServeConfig (its checks run at start-up), which
    trusts X-Forwarded-For from the compose networks' private ranges only."""
    import ipaddress

    import yaml

    from stgs.cli import build_parser
    from stgs.cli.stream import serve_config

    command = yaml.safe_load((DOCKER / "compose.yaml").read_text())["services"]["server"]["command"]
    args = build_parser(("serve",)).parse_args(["serve", *command])
    cfg = serve_config(args)
    assert cfg.max_connections_per_client == 0 and cfg.player_dir == Path("/app/web/dist")
    assert cfg.trusted and all(net.is_private for net in cfg.trusted)
    assert not any(ipaddress.ip_address("203.0.113.9") in net for net in cfg.trusted)


def stage(path: Path, name: str) -> list[tuple[str, str]]:
    """The instructions of one named stage of a multi-stage Dockerfile."""
    ins, out, current = instructions(path), [], None
    for kind, args in ins:
        if kind == "FROM":
            current = args.split(" AS ")[-1].strip() if " AS " in args else None
        if current == name:
            out.append((kind, args))
    return out


def test_ray_worker_image_is_the_packager_image_plus_ray():
    path = DOCKER / "packager.Dockerfile"
    ins = instructions(path)
    assert ins[-1] == ("FROM", "packager")  # a plain `docker build` still gives the packager image
    worker = stage(path, "ray-worker")
    assert worker[0] == ("FROM", "packager AS ray-worker")
    assert any(k == "RUN" and "-r requirements-ray.lock" in a for k, a in worker)
    assert ("ENTRYPOINT", '["ray"]') in worker
    user = [a for k, a in worker if k == "USER"]
    assert user and user[-1] not in ("root", "0")
    pins = dict(line.split("==") for line in (ROOT / "requirements-ray.lock").read_text().splitlines()
                if "==" in line and not line.startswith("#"))
    assert pins["ray"] == "2.60.0"
    assert re.search(r'^ray = \["ray==2\.60\.0"\]', (ROOT / "pyproject.toml").read_text(), re.M)
    assert not re.search(r"^ray==", LOCK.read_text(), re.M)  # the packager image does not carry Ray


def test_ray_compose_runs_a_head_and_workers_on_one_shared_volume():
    import yaml

    doc = yaml.safe_load((DOCKER / "ray-compose.yaml").read_text())
    head, worker = doc["services"]["ray-head"], doc["services"]["ray-worker"]
    for service in (head, worker):
        assert service["build"] == {"context": "..", "dockerfile": "docker/packager.Dockerfile",
                                    "target": "ray-worker"}
        assert service["volumes"] == ["${WORK:-./work}:/work"]  # every task sees the same paths
        assert service["command"][0] == "start" and "--block" in service["command"]
    assert "--head" in head["command"] and "--port=6379" in head["command"] and "--num-cpus=0" in head["command"]
    assert "--address=ray-head:6379" in worker["command"] and worker["depends_on"] == ["ray-head"]
    assert worker["deploy"]["replicas"] == "${WORKERS:-2}"
    assert "ports" not in head  # Ray's port stays on the compose network
    text = (DOCKER / "ray-compose.yaml").read_text()
    assert "stgs train /work/" in text and "--ray auto" in text
