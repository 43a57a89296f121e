"""One interface for running a stage's tasks: in this process (`LocalRunner`) or on a Ray cluster
(`stgs.tasks.ray_runner`, imported only when asked for).

A task is a module-level function of plain data (paths, numbers, dicts) that reads its inputs from storage every
worker sees, writes its outputs there atomically and returns a small dict. Nothing but those arguments and that
dict crosses between the driver and a worker. Each task appends its events to its own log file
(`<log_dir>/<task>.log`, JSON lines: start with host, pid and time; done with seconds; error with its message),
so a task's history outlives the process that ran it.

A task fails in one of two ways. A user error (`StgsError`: bad input, bad settings) comes back as a result and
fails the run with that one message, never retried. A worker that dies is a system failure, which the Ray runner
retries (`retries` times) from the task's own checkpoints.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from stgs.errors import StgsError
from stgs.fsio import atomic_write_bytes

SHARED_TOKEN = "shared-token"
"""The file a driver writes in its log folder and every task reads back before it starts."""


@dataclass(frozen=True)
class Task:
    """One unit of work: `fn(*args)` run once, after the tasks named in `after`."""

    name: str
    """Unique within a run; names the task's log file."""
    fn: Callable[..., dict]
    """A module-level function (workers import it by name)."""
    args: tuple = ()
    """Plain data only."""
    after: tuple[str, ...] = ()
    """Tasks that must have finished first (earlier in the same list)."""
    cpus: int = 1
    """Cores the task uses (a Ray resource request; the function sets its own thread count)."""
    fresh_process: bool = False
    """On Ray, run in a worker process of its own (minutes-long tasks: see docs/SCALING.md)."""


class TaskFailedError(StgsError):
    """A task failed for a user error, or its worker kept dying; the run stops with this message."""


class Runner(Protocol):
    def run(self, tasks: list[Task], log_dir: Path, desc: str,
            on_result: Callable[[str, dict], None] | None = None) -> dict[str, dict]:
        """Run every task (each after its `after`), calling `on_result(name, result)` on the driver as each
        finishes; the results by task name. Raises TaskFailedError on the first failure, cancelling the rest."""
        ...

    def close(self) -> None: ...


def log_event(log_dir: Path, name: str, event: dict) -> None:
    """Append one JSON line to the task's log file."""
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / f"{name}.log", "a") as f:
        f.write(json.dumps({"time": round(time.time(), 3), **event}) + "\n")


def read_log(log_dir: Path, name: str) -> list[dict]:
    """A task's logged events, oldest first (an empty list before it started)."""
    path = Path(log_dir) / f"{name}.log"
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def write_shared_token(log_dir: Path) -> str:
    """Mark the run's log folder (inside its output, on the shared storage) with a fresh token before any task
    starts; returns it. A task that cannot read it back runs where the output is not shared."""
    token = secrets.token_hex(16)
    atomic_write_bytes(Path(log_dir) / SHARED_TOKEN, token.encode())
    return token


def execute(name: str, fn: Callable[..., dict], args: tuple, token: str, log_dir: str, catch: bool,
            *after: object) -> dict:
    """Run one task where it was scheduled: {"result": ...}, or {"error": message} for a user error when `catch`
    (else the error propagates as raised). `after` holds the results of the tasks it waited for (Ray passes them
    so that it schedules this task after them); if one of them failed, this task does not run."""
    try:
        seen = (Path(log_dir) / SHARED_TOKEN).read_text()
    except OSError:
        seen = None
    if seen != token:
        return {"error": f"the worker on {socket.gethostname()} does not see {log_dir} as the driver wrote it; every "
                         "worker must mount the input and output folders at the same paths as the driver"}
    if failed := next((r["error"] for r in after if isinstance(r, dict) and "error" in r), None):
        return {"error": failed}  # a task it depends on failed: that error stops the run, this one never starts
    logs = Path(log_dir)
    log_event(logs, name, {"event": "start", "host": socket.gethostname(), "pid": os.getpid()})
    start = time.perf_counter()
    try:
        result = fn(*args)
    except StgsError as e:
        log_event(logs, name, {"event": "error", "message": str(e)})
        if not catch:
            raise
        return {"error": str(e)}
    except BaseException as e:
        log_event(logs, name, {"event": "crash", "message": f"{type(e).__name__}: {e}",
                               "traceback": traceback.format_exc()})
        raise
    log_event(logs, name, {"event": "done", "seconds": round(time.perf_counter() - start, 3)})
    return {"result": result}


def check_order(tasks: list[Task]) -> None:
    seen: set[str] = set()
    for task in tasks:
        if task.name in seen:
            raise ValueError(f"task {task.name!r} appears twice")
        missing = [a for a in task.after if a not in seen]
        if missing:
            raise ValueError(f"task {task.name!r} runs after {missing}, which do not come before it")
        seen.add(task.name)


class LocalRunner:
    """Every task in this process, one after another, in list order; a user error raises as itself."""

    def run(self, tasks: list[Task], log_dir: Path, desc: str,
            on_result: Callable[[str, dict], None] | None = None) -> dict[str, dict]:
        check_order(tasks)
        token = write_shared_token(log_dir)
        results = {}
        for task in tasks:
            outcome = execute(task.name, task.fn, task.args, token, str(log_dir), False)
            if "error" in outcome:  # the shared-folder check (a user error raises as itself)
                raise TaskFailedError(outcome["error"])
            results[task.name] = outcome["result"]
            if on_result is not None:
                on_result(task.name, outcome["result"])
        return results

    def close(self) -> None:
        pass
