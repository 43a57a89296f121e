"""stgs.tasks without Ray: ordering, per-task logs, user errors, the shared-storage check."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from stgs.errors import StgsError
from stgs.tasks import LocalRunner, Task, TaskFailedError
from stgs.tasks.runner import SHARED_TOKEN, execute, read_log, write_shared_token

ROOT = Path(__file__).resolve().parents[2]


def double(x: int) -> dict:
    return {"value": 2 * x}


def refuse(x: int) -> dict:
    raise StgsError(f"input {x} is bad")


def test_local_runner_runs_in_order_logs_each_task_and_reports_results(tmp_path):
    seen = []
    tasks = [Task("a", double, (1,)), Task("b", double, (2,), after=("a",))]
    results = LocalRunner().run(tasks, tmp_path / "logs", "test", lambda name, r: seen.append((name, r)))
    assert results == {"a": {"value": 2}, "b": {"value": 4}} and seen == [("a", {"value": 2}), ("b", {"value": 4})]
    events = read_log(tmp_path / "logs", "b")
    assert [e["event"] for e in events] == ["start", "done"] and events[0]["pid"] > 0
    assert events[1]["seconds"] >= 0


def test_a_user_error_raises_as_itself_locally_and_comes_back_as_data_for_ray(tmp_path):
    with pytest.raises(StgsError, match="input 3 is bad"):
        LocalRunner().run([Task("x", refuse, (3,))], tmp_path, "test")
    assert [e["event"] for e in read_log(tmp_path, "x")] == ["start", "error"]
    token = write_shared_token(tmp_path)
    assert execute("y", refuse, (4,), token, str(tmp_path), True) == {"error": "input 4 is bad"}


def test_a_task_that_does_not_see_the_drivers_folder_fails_with_a_clear_error(tmp_path):
    write_shared_token(tmp_path)
    outcome = execute("z", double, (1,), "another-token", str(tmp_path), True)
    assert "does not see" in outcome["error"] and "same paths" in outcome["error"]
    (tmp_path / SHARED_TOKEN).unlink()
    assert "does not see" in execute("z", double, (1,), "t", str(tmp_path), True)["error"]
    assert read_log(tmp_path, "z") == []  # it never started


def test_tasks_out_of_order_or_twice_are_a_programming_error(tmp_path):
    with pytest.raises(ValueError, match="do not come before it"):
        LocalRunner().run([Task("b", double, (1,), after=("a",)), Task("a", double, (1,))], tmp_path, "t")
    with pytest.raises(ValueError, match="appears twice"):
        LocalRunner().run([Task("a", double, (1,)), Task("a", double, (2,))], tmp_path, "t")
    assert issubclass(TaskFailedError, StgsError)


def test_a_task_whose_dependency_failed_never_starts(tmp_path):
    token = write_shared_token(tmp_path)
    outcome = execute("after", double, (1,), token, str(tmp_path), True, {"error": "input 3 is bad"})
    assert outcome == {"error": "input 3 is bad"} and read_log(tmp_path, "after") == []
    assert execute("ok", double, (1,), token, str(tmp_path), True, {"result": {}}) == {"result": {"value": 2}}


def test_without_ray_nothing_of_ray_is_imported(tmp_path):
    """A local run's whole import graph (the CLI, training, packing, the task runner) leaves Ray alone."""
    code = ("import sys; import stgs.cli.commands, stgs.train.run, stgs.packager.packer, stgs.packager.tasks, "
            "stgs.tasks; from stgs.tasks import open_runner; open_runner(None); "
            "sys.exit(1 if any(m == 'ray' or m.startswith('ray.') for m in sys.modules) else 0)")
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0


def test_an_unreachable_or_malformed_ray_address_is_one_clear_error_at_once():
    ray_runner = pytest.importorskip("stgs.tasks.ray_runner")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    with pytest.raises(StgsError, match=f"cannot reach the Ray cluster at '127.0.0.1:{port}'"):
        ray_runner.check_reachable(f"127.0.0.1:{port}")
    for bad in ("nohost", "host:port", "host:0", ":6379"):
        with pytest.raises(StgsError, match="a Ray address is local, auto, HOST:PORT"):
            ray_runner.check_reachable(bad)
