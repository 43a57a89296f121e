"""Training and packaging as tasks: the local loop against Ray with 1 and 2 one-core workers, in one run.

    python -m bench.training.scaling --dataset synth --out /tmp/scaling-synth
    python -m bench.training.scaling --dataset ../shared/data/panoptic-basketball --out /tmp/scaling-panoptic \
        --train "--budget cpu --holdout 1,14,27 --gops 1 --coarse-iterations 150 --iterations 300" --qps 16,24,32

Per mode (local: `stgs train --threads 1` and `stgs pack --jobs 1`; ray-W: a Ray cluster started here on
127.0.0.1, a head that runs no tasks and W workers of one core, the same commands with `--ray`), the wall time of
each command as a user runs it (a subprocess, Ray's connection included) and the task seconds from the task logs;
every Ray run's model dir and tree are checked byte-identical to the local run's (train_report.json's times and
the task logs aside). `--dataset synth` makes the small synthetic scene (4 GOPs of 6 frames, 256 Gaussians).
Prints a Markdown table and writes OUT/scaling.json. Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from stgs.synth import SynthConfig, synthesize
from stgs.tasks.runner import read_log

SYNTH = SynthConfig(grid_side=16, num_gops=4, gop_size=6, width=96, height=72, num_cameras=8, fit_steps=30)
SYNTH_TRAIN = "--gop-size 6 --grid-side 16 --coarse-iterations 300 --iterations 600"


def stgs(*args: str) -> float:
    start = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "stgs.cli", *args, "--quiet"], capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(f"stgs {' '.join(args)} failed: {result.stderr.strip()}")
    return time.perf_counter() - start


def task_seconds(log_dir: Path) -> dict[str, float]:
    out = {}
    for path in sorted(log_dir.glob("*.log")):
        done = [e for e in read_log(log_dir, path.stem) if e["event"] == "done"]
        if done:
            out[path.stem] = done[-1]["seconds"]
    return out


def files(root: Path, skip: set[str]) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not (skip & set(p.relative_to(root).parts))}


def run_mode(name: str, address: str | None, dataset: Path, out: Path, train_args: list[str], qps: str) -> dict:
    model, dash = out / f"model-{name}", out / f"dash-{name}"
    shutil.rmtree(model, ignore_errors=True)
    shutil.rmtree(dash, ignore_errors=True)
    ray = ["--ray", address] if address else []
    train_s = stgs("train", str(dataset), str(model), *train_args, "--threads", "1", *ray)
    pack_s = stgs("pack", str(model), str(dash), "--qps", qps, *(ray or ["--jobs", "1"]))
    return {"mode": name, "train_s": train_s, "pack_s": pack_s, "train_tasks": task_seconds(model / ".train" / "logs"),
            "pack_tasks": task_seconds(dash / ".pack-logs"), "model": str(model), "dash": str(dash)}


def same_outputs(a: dict, b: dict) -> bool:
    ma, mb = files(Path(a["model"]), {".train", "train_report.json"}), files(Path(b["model"]), {".train",
                                                                                                  "train_report.json"})
    return ma == mb and files(Path(a["dash"]), {".pack-logs"}) == files(Path(b["dash"]), {".pack-logs"})


def costs(doc: dict, gop_iterations: int, base_iterations: int) -> dict:
    """Per-task costs on one core from a run of this benchmark, scaled to a budget's iterations: the base stage
    and a GOP at their measured seconds per iteration (the GOP's from its training curve, its setup apart), a
    GOP's pack tasks as measured, and Ray's overhead per task (wall time not spent in tasks, per task)."""
    local = next(r for r in doc["rows"] if r["mode"] == "local")
    ray = next(r for r in doc["rows"] if r["mode"] == "ray-1")
    report = json.loads((Path(local["model"]) / "train_report.json").read_text())
    gop = report["gops"][0]
    curve = gop["curve"]
    per_it = (curve[-1]["seconds"] - curve[0]["seconds"]) / (curve[-1]["iteration"] - curve[0]["iteration"]) \
        if len(curve) > 1 else gop["seconds"] / gop["iterations"]
    setup = local["train_tasks"]["gop_0000"] - gop["iterations"] * per_it
    config = json.loads((Path(local["model"]) / "model.json").read_text())["extra"]["config"]
    base_per_it = report["coarse_seconds"] / max(1, config["coarse_iterations"])
    n_gops = len(report["gops"])
    n_tasks = len(ray["train_tasks"]) + len(ray["pack_tasks"])
    overhead = (ray["train_s"] + ray["pack_s"] - sum(ray["train_tasks"].values())
                - sum(ray["pack_tasks"].values())) / n_tasks
    return {"t_b": base_per_it * base_iterations, "t_g": setup + per_it * gop_iterations,
            "t_p": sum(ray["pack_tasks"].values()) / n_gops, "o": overhead, "gop_setup_s": setup,
            "gop_s_per_it": per_it, "q": len(doc["qps"].split(","))}


def predict(c: dict, gops: int, workers: int) -> dict:
    """The wall time and core-hours of `gops` GOPs on `workers` one-core workers (docs/SCALING.md's model)."""
    q = c["q"]
    wall = (c["t_b"] + math.ceil(gops / workers) * (c["t_g"] + c["o"])
            + math.ceil(gops * (1 + q) / workers) * (c["t_p"] / (1 + q) + c["o"]))
    core_s = gops * (c["t_g"] + c["t_p"]) + workers * c["t_b"]
    return {"gops": gops, "workers": workers, "wall_h": wall / 3600, "core_h": core_s / 3600}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", help="a dataset folder, or 'synth' for the small synthetic scene")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--train", default=SYNTH_TRAIN, help="stgs train flags (quoted)")
    ap.add_argument("--qps", default="20,32")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--predict", type=Path, metavar="SCALING_JSON",
                    help="no runs: the model's wall time and core-hours from an earlier run's scaling.json")
    ap.add_argument("--gop-iterations", type=int, default=3000, help="with --predict: a GOP's iterations")
    ap.add_argument("--base-iterations", type=int, default=1500, help="with --predict: the base stage's")
    ap.add_argument("--fleet", default="300x1,300x50,1800x50,1800x200",
                    help="with --predict: GOPSxWORKERS cases")
    args = ap.parse_args()
    if args.predict:
        c = costs(json.loads(args.predict.read_text()), args.gop_iterations, args.base_iterations)
        print(f"per task on one core: base {c['t_b']:.0f} s, GOP {c['t_g']:.0f} s ({c['gop_setup_s']:.0f} s setup + "
              f"{c['gop_s_per_it']:.3f} s/it), pack {c['t_p']:.1f} s per GOP, overhead {c['o']:.1f} s per task")
        print("| GOPs | workers | wall h (s) | core-hours |")
        print("|---|---|---|---|")
        for case in args.fleet.split(","):
            p = predict(c, *map(int, case.split("x")))
            print(f"| {p['gops']:,} | {p['workers']} | {p['wall_h']:.2f} ({p['wall_h'] * 3600:,.0f} s) | "
                  f"{p['core_h']:,.1f} |")
        return
    if not (args.dataset and args.out):
        ap.error("--dataset and --out are required (or --predict)")
    args.out.mkdir(parents=True, exist_ok=True)
    dataset = args.out / "scene" if args.dataset == "synth" else Path(args.dataset)
    if args.dataset == "synth" and not dataset.exists():
        synthesize(SYNTH, dataset, progress=False)
    from ray.cluster_utils import Cluster

    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    train_args = shlex.split(args.train)
    rows = [run_mode("local", None, dataset, args.out, train_args, args.qps)]
    for workers in map(int, args.workers.split(",")):
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
        for _ in range(workers):
            cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes(timeout=60)
        try:
            rows.append(run_mode(f"ray-{workers}", cluster.address, dataset, args.out, train_args, args.qps))
        finally:
            cluster.shutdown()
        rows[-1]["identical"] = same_outputs(rows[0], rows[-1])
    local = rows[0]
    print("| mode | train wall s | Σ train task s | pack wall s | Σ pack task s | train × local | pack × local "
          "| bytes = local |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['mode']} | {r['train_s']:.1f} | {sum(r['train_tasks'].values()):.1f} | {r['pack_s']:.1f} | "
              f"{sum(r['pack_tasks'].values()):.1f} | {local['train_s'] / r['train_s']:.2f} | "
              f"{local['pack_s'] / r['pack_s']:.2f} | {r.get('identical', '—')} |")
    (args.out / "scaling.json").write_text(json.dumps({"dataset": args.dataset, "train": args.train,
                                                       "qps": args.qps, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
