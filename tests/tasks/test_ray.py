"""stgs train/pack --ray on a real local Ray cluster (a head and two one-core workers on 127.0.0.1, started and shut
down here): the same bytes as a local run, a worker killed mid-task, a bad input, a driver killed and resumed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stgs.synth import SynthConfig, synthesize
from stgs.tasks.runner import read_log
from stgs.train import budget, train
from stgs.tree import STATIC_EXTENSION, STATS
from tests.conftest import run_stgs as stgs

ray_cluster_utils = pytest.importorskip("ray.cluster_utils")

SCENE = SynthConfig(grid_side=16, num_gops=2, gop_size=6, width=96, height=72, num_cameras=8, fit_steps=30)
FLAGS = ("--gop-size", "6", "--grid-side", "16", "--coarse-iterations", "30", "--iterations", "120",
         "--threads", "1", "--quiet")
CONFIG = {"gop_size": 6, "grid_side": 16, "coarse_iterations": 30, "iterations": 120, "threads": 1}
REPORT_TIMES = {"seconds", "coarse_seconds", "static_seconds", "curve", "peak_rss_mb"}
"""Fields of train_report.json that measure the run (wall times, peak memory): they differ between any two runs."""


@pytest.fixture(scope="module")
def cluster():
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    c = ray_cluster_utils.Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    for _ in range(2):
        c.add_node(num_cpus=1)
    c.wait_for_nodes(timeout=60)
    yield c.address
    c.shutdown()


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ray") / "scene"
    synthesize(SCENE, out, progress=False)
    return out


@pytest.fixture(scope="module")
def local_model(scene, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ray") / "local"
    train(scene, out, budget("quick", **CONFIG), progress=False)
    return out


def without_times(doc):
    if isinstance(doc, dict):
        return {k: without_times(v) for k, v in doc.items() if k not in REPORT_TIMES}
    if isinstance(doc, list):
        return [without_times(v) for v in doc]
    return doc


def assert_same_model(a: Path, b: Path) -> None:
    names = sorted(p.name for p in a.iterdir() if p.is_file())
    assert names == sorted(p.name for p in b.iterdir() if p.is_file())
    for name in names:
        if name == "train_report.json":
            docs = [without_times(json.loads((d / name).read_text())) for d in (a, b)]
            assert docs[0] == docs[1]
        else:
            assert (a / name).read_bytes() == (b / name).read_bytes(), name


def tree_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and ".pack-logs" not in p.parts}


def starts(model: Path, task: str) -> list[dict]:
    return [e for e in read_log(model / ".train" / "logs", task) if e["event"] == "start"]


def test_train_and_pack_on_ray_give_the_bytes_of_a_local_run(cluster, scene, local_model, tmp_path):
    result = stgs("train", str(scene), str(tmp_path / "model"), *FLAGS, "--ray", cluster)
    assert result.returncode == 0, result.stderr
    assert_same_model(local_model, tmp_path / "model")
    for task in ("base", "gop_0000", "gop_0001"):
        assert [e["event"] for e in read_log(tmp_path / "model" / ".train" / "logs", task)] == ["start", "done"]

    local = stgs("pack", str(local_model), str(tmp_path / "dash-local"), "--qps", "20,32", "--av1-qps", "27",
                 "--quiet")
    assert local.returncode == 0, local.stderr
    distributed = stgs("pack", str(local_model), str(tmp_path / "dash-ray"), "--qps", "20,32", "--av1-qps", "27",
                       "--quiet", "--ray", cluster)
    assert distributed.returncode == 0, distributed.stderr
    assert tree_files(tmp_path / "dash-local") == tree_files(tmp_path / "dash-ray")
    logs = sorted(p.stem for p in (tmp_path / "dash-ray" / ".pack-logs").glob("*.log"))
    assert logs == ["gop0-av1q27", "gop0-prepare", "gop0-qp20", "gop0-qp32",
                    "gop1-av1q27", "gop1-prepare", "gop1-qp20", "gop1-qp32"]
    assert not (tmp_path / "dash-ray" / ".pack-work").exists()


def test_a_layered_scene_packs_on_ray_to_the_bytes_of_a_local_run(cluster, tmp_path):
    layered = SynthConfig(grid_side=8, num_gops=2, gop_size=4, width=48, height=36, num_cameras=2, fit_steps=10,
                          effects=("rigid", "static_background"), static_grid_side=8)
    synthesize(layered, tmp_path / "model", progress=False)
    local = stgs("pack", str(tmp_path / "model"), str(tmp_path / "dash-local"), "--qps", "24", "--quiet")
    assert local.returncode == 0, local.stderr
    distributed = stgs("pack", str(tmp_path / "model"), str(tmp_path / "dash-ray"), "--qps", "24", "--quiet",
                       "--ray", cluster)
    assert distributed.returncode == 0, distributed.stderr
    files = tree_files(tmp_path / "dash-ray")
    assert files == tree_files(tmp_path / "dash-local")
    assert [name for name in files if name.endswith(STATIC_EXTENSION)] != []  # the static layer is in both trees
    assert json.loads(files[STATS])["static"]["capacity"] == 64


def popen_train(scene: Path, out: Path, cluster: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "stgs.cli", "train", str(scene), str(out), *FLAGS, "--ray",
                             cluster, *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(condition, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.2)


def test_a_worker_killed_mid_task_is_retried_and_the_model_is_the_same(cluster, scene, local_model, tmp_path):
    out = tmp_path / "model"
    driver = popen_train(scene, out, cluster)
    wait_for(lambda: len(starts(out, "gop_0001")) == 1, 120, "GOP 1 to start")
    victim = starts(out, "gop_0001")[0]["pid"]
    # frozen at once, then killed: mid-task however late this process gets the CPU (a GOP task here takes about
    # two seconds, and two of them share the two cores with Ray)
    os.kill(victim, signal.SIGSTOP)
    assert [e["event"] for e in read_log(out / ".train" / "logs", "gop_0001")] == ["start"], "GOP 1 ended first"
    os.kill(victim, signal.SIGKILL)
    _, stderr = driver.communicate(timeout=300)
    assert driver.returncode == 0, stderr
    attempts = starts(out, "gop_0001")
    assert len(attempts) == 2 and attempts[1]["pid"] != victim  # retried in a new worker process
    assert_same_model(local_model, out)


def test_a_bad_input_fails_the_run_once_with_its_clear_error(cluster, scene, tmp_path):
    broken = tmp_path / "scene"
    subprocess.run(["cp", "-r", str(scene), str(broken)], check=True)
    image = next(p for p in sorted((broken / "gt").rglob("*.png")) if "masks" not in p.parts)
    image.write_bytes(image.read_bytes()[:60])  # its header intact (the driver's up-front check passes), no pixels
    result = stgs("train", str(broken), str(tmp_path / "model"), *FLAGS, "--ray", cluster)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stgs: ") and image.name in lines[0], result.stderr
    failed = [e for e in read_log(tmp_path / "model" / ".train" / "logs", "base")]
    assert [e["event"] for e in failed] == ["start", "error"]  # not retried
    assert read_log(tmp_path / "model" / ".train" / "logs", "gop_0000") == []  # what depends on it never starts
    assert not (tmp_path / "model" / "model.json").exists()


def test_a_bad_model_file_fails_the_pack_once_with_its_clear_error(cluster, local_model, tmp_path):
    model = tmp_path / "model"
    subprocess.run(["cp", "-r", str(local_model), str(model)], check=True)
    gop = model / "gop_0001.safetensors"
    gop.write_bytes(gop.read_bytes()[:100])  # truncated
    result = stgs("pack", str(model), str(tmp_path / "dash"), "--qps", "20", "--quiet", "--ray", cluster)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stgs: ") and "gop_0001" in lines[0], result.stderr
    logs = tmp_path / "dash" / ".pack-logs"
    for task in ("gop0-prepare", "gop0-qp20", "gop1-prepare", "gop1-qp20"):
        assert len([e for e in read_log(logs, task) if e["event"] == "start"]) <= 1, task  # never retried
    assert not (tmp_path / "dash" / "manifest.mpd").exists()


def test_a_killed_driver_resumes_without_retraining_finished_gops(cluster, scene, local_model, tmp_path):
    out = tmp_path / "model"
    driver = popen_train(scene, out, cluster)
    wait_for(lambda: all(starts(out, f"gop_{k:04d}") for k in (0, 1)), 180, "both GOPs to start")
    # Frozen while its GOPs run on the workers, the driver cannot write the model dir: GOP 1 may finish between
    # two polls of GOP 0's report (the workers run them side by side), and a driver still running would then
    # finish the run before the kill.
    driver.send_signal(signal.SIGSTOP)
    wait_for(lambda: (out / ".train" / "gop_0000.report.json").is_file(), 180, "GOP 0 to finish")
    driver.send_signal(signal.SIGKILL)
    driver.wait(timeout=30)
    assert not (out / "model.json").exists()
    result = stgs("train", str(scene), str(out), *FLAGS, "--ray", cluster, "--resume")
    assert result.returncode == 0, result.stderr
    assert len(starts(out, "base")) == 1 and len(starts(out, "gop_0000")) == 1  # finished: skipped
    assert_same_model(local_model, out)


def test_a_retried_gop_task_whose_first_attempt_finished_returns_its_result(scene, local_model, tmp_path):
    """A worker killed after its GOP task finished, before the driver took the result: the retry finds the saved
    GOP (which shares its name with the GOP's checkpoint) and returns its report instead of loading it as a
    checkpoint (a KeyError) or training over it."""
    import dataclasses
    import hashlib

    from stgs.train.run import TrainJob, gop_task

    out = tmp_path / "model"
    subprocess.run(["cp", "-r", str(local_model), str(out)], check=True)
    saved = out / ".train" / "gop_0001.safetensors"
    before = hashlib.sha256(saved.read_bytes()).hexdigest()
    job = TrainJob(str(scene.resolve()), str(out.resolve()), dataclasses.asdict(budget("quick", **CONFIG)), "auto",
                   False)
    result = gop_task(job, 1)
    report = json.loads((out / ".train" / "gop_0001.report.json").read_text())
    assert result == {"gop": 1, "seconds": report["seconds"], "val_psnr": report["val_psnr"]}
    assert hashlib.sha256(saved.read_bytes()).hexdigest() == before
