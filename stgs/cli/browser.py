"""The web player from Python: `stgs serve` in a child process on a free loopback port, and Debian's Chromium
driven through web/tools/browse.mjs (playwright-core on the system binary; never a downloaded browser). Used by
`stgs demo` (its screenshot), the web benchmark and the browser tests."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

from stgs.errors import StgsError

WEB = Path(__file__).resolve().parents[2] / "web"
"""The web player's sources; its build is WEB / "dist"."""


def missing_browser() -> str | None:
    """Why the player cannot be driven here (no build, Node or Chromium), or None when it can."""
    if shutil.which("node") is None:
        return "Node.js is not installed"
    if not (WEB / "dist" / "index.html").is_file():
        return "the web player is not built (./bin/stgs builds it when Node is installed)"
    if shutil.which("chromium") is None:
        return "Debian's chromium is not installed"
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def served(root: Path, startup_s: float = 30.0, player_dir: Path | None = None) -> Iterator[str]:
    """`stgs serve ROOT` on a free loopback port (offering `player_dir` at /player/ when given); yields its base
    URL (ends in /)."""
    port = free_port()
    extra = ["--player-dir", str(player_dir)] if player_dir else []
    proc = subprocess.Popen([sys.executable, "-m", "stgs.cli", "serve", str(root), "--port", str(port), "--quiet",
                             *extra], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    base = f"http://127.0.0.1:{port}/"
    try:
        deadline = time.monotonic() + startup_s
        while True:
            try:
                urllib.request.urlopen(base + "healthz", timeout=1).read()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    said = proc.stderr.read().decode() if proc.stderr is not None else ""
                    raise StgsError(f"stgs serve did not start: {said[-300:]}") from None
                time.sleep(0.1)
        yield base
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=15)


@contextlib.contextmanager
def served_trees(trees: list[Path], player_dir: Path | None = None) -> Iterator[str]:
    """`served` over a temporary ROOT holding a copy of each packaged tree, under its folder's name (the server
    follows no symlink out of its root); yields the base URL."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for tree in trees:
            shutil.copytree(tree, root / tree.resolve().name)
        with served(root, player_dir=player_dir) as base:
            yield base


def browse(plan: dict, timeout: float = 600) -> tuple[dict, str | None]:
    """Run a plan of browser steps (web/tools/browse.mjs); returns what it gathered and the failure (None: ok)."""
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        json.dump(plan, f)
    proc = subprocess.Popen(["node", str(WEB / "tools" / "browse.mjs"), f.name, shutil.which("chromium") or ""],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        # SIGTERM first: Playwright closes the browser it started (its own process group) on it; then whatever is
        # left of node's group goes.
        proc.terminate()
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
        return {}, f"the browser plan did not finish in {timeout:g} s"
    finally:
        os.unlink(f.name)
    out = json.loads(stdout) if stdout.strip() else {}
    return out, (stderr.strip() or "browse failed") if proc.returncode else None
