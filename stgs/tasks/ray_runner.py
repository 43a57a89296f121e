"""The Ray runner: each task a Ray task with a core request, retried when its worker dies, never when it fails for
a user error (stgs.tasks.runner). Imported only when a run asks for Ray; Ray is the optional `ray` extra.

Ray's own protocol pickles what it sends between driver and workers, so a Ray cluster must only ever be reachable
from trusted machines (docs/SCALING.md); our tasks pass plain data and exchange bulk data as files in our formats.
"""

from __future__ import annotations

import logging
import os
import socket
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from stgs.errors import StgsError
from stgs.tasks.runner import Task, TaskFailedError, check_order, execute, write_shared_token

try:
    import ray
    from ray.exceptions import RayTaskError
except ImportError as e:  # pragma: no cover - exercised only where the extra is missing
    raise StgsError("Ray is not installed: install the optional extra (pip install 'streamstgs[ray]')") from e


def check_reachable(address: str, timeout: float = 5.0) -> None:
    """A HOST:PORT (or ray://HOST:PORT) address that answers a TCP connect; Ray itself would retry an unreachable
    head for minutes."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not (host and port.isdigit() and 0 < int(port) < 65536):
        raise StgsError(f"a Ray address is local, auto, HOST:PORT or ray://HOST:PORT, got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        raise StgsError(f"cannot reach the Ray cluster at {address!r}: {e.strerror or e}") from None


class RayRunner:
    """Tasks on the Ray cluster this process is connected to; one progress bar over all of them."""

    def __init__(self, retries: int, progress: bool):
        self.retries, self.progress = retries, progress

    @classmethod
    def connect(cls, address: str, retries: int = 3, progress: bool = True) -> RayRunner:
        if retries < 0:
            raise StgsError(f"retries must be >= 0, got {retries}")
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        options: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING, "configure_logging": True}
        if address == "local":
            options |= {"num_cpus": os.cpu_count() or 1, "include_dashboard": False}
        else:
            if address != "auto":
                check_reachable(address)
            options["address"] = address
        try:
            ray.init(**options)
        except (ConnectionError, RuntimeError, ValueError) as e:
            where = "a new local Ray instance" if address == "local" else f"the Ray cluster at {address!r}"
            raise StgsError(f"cannot start or reach {where}: {str(e).splitlines()[0]}") from None
        return cls(retries, progress)

    def run(self, tasks: list[Task], log_dir: Path, desc: str,
            on_result: Callable[[str, dict], None] | None = None) -> dict[str, dict]:
        check_order(tasks)
        token = write_shared_token(log_dir)
        shared_worker, own_worker = ray.remote(execute), ray.remote(max_calls=1)(execute)
        refs: dict[str, ray.ObjectRef] = {}
        names: dict[ray.ObjectRef, str] = {}
        for task in tasks:
            remote = own_worker if task.fresh_process else shared_worker
            options = remote.options(num_cpus=task.cpus, max_retries=self.retries, retry_exceptions=False,
                                     name=task.name)
            ref = options.remote(task.name, task.fn, task.args, token, str(log_dir), True,
                                 *(refs[a] for a in task.after))
            refs[task.name] = ref
            names[ref] = task.name
        results: dict[str, dict] = {}
        pending = list(refs.values())
        with tqdm(total=len(tasks), desc=desc, unit="task", disable=not self.progress) as bar:
            try:
                while pending:
                    ready, pending = ray.wait(pending, num_returns=1)
                    name = names[ready[0]]
                    outcome = self._get(ready[0], name)
                    if "error" in outcome:
                        raise TaskFailedError(outcome["error"])
                    results[name] = outcome["result"]
                    if on_result is not None:
                        on_result(name, outcome["result"])
                    bar.update(1)
            except BaseException:
                for ref in pending:
                    ray.cancel(ref, force=True)
                raise
        return results

    def _get(self, ref: ray.ObjectRef, name: str) -> dict:
        try:
            return ray.get(ref)
        except RayTaskError as e:
            cause = e.cause if e.cause is not None else e
            last = "".join(traceback.format_exception_only(cause)).strip().splitlines()[-1]
            raise TaskFailedError(f"task {name} raised {last} (its traceback is in the task's log)") from None
        except ray.exceptions.RayError as e:
            raise TaskFailedError(f"task {name} did not finish after {self.retries + 1} attempt(s): "
                                  f"{str(e).splitlines()[0]}") from None

    def close(self) -> None:
        if ray.is_initialized():
            ray.shutdown()
