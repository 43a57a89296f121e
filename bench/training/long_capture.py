"""Peak memory and wall time of training against the capture's length, and a long capture end to end
(`python -m bench.training.long_capture [--frames 60,150,600,1800] [--max-memory 256M] [--play 1800]`; prints Markdown
rows for docs/BENCHMARKS.md, "Long captures").

Each capture is `stgs synth --seconds` of a small layered scene (160x120, 5 cameras, the static backdrop), the
same scene at every length. It trains with the quick budget in 60-frame GOPs under one --max-memory; the table
gives each step's own peak memory (the process's high-water mark, as the kernel counts it for that child: the
training report's VmHWM for train, wait4's ru_maxrss for pack) and its wall time. With --play N, the N-frame
capture is also packed, served by `stgs serve` on loopback and played to its end by `stgs play`, whose log
gives its peak memory and the frames it rendered.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from stgs.cli.browser import served
from stgs.tree import MANIFEST

SCENE = ["--width", "160", "--height", "120", "--cameras", "5", "--grid-side", "16", "--static-grid-side", "16",
         "--fit-steps", "10", "--gop-size", "60", "--effects", "rigid,nonrigid,appear,color,static_background"]
FPS = 30.0


def stgs_step(*args: str) -> tuple[float, float]:
    """Run `stgs ARGS` as a child; (its wall seconds, its own peak resident memory in MB from wait4)."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "stgs.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"stgs {args[0]} failed: {proc.stderr.read().decode()[-400:]}")
    proc.returncode = 0  # reaped by wait4
    return seconds, usage.ru_maxrss / 1024


def row(frames: int, work: Path, max_memory: str, play: bool) -> str:
    scene, model, dash = work / f"scene{frames}", work / f"model{frames}", work / f"dash{frames}"
    stgs_step("synth", str(scene), "--seconds", f"{frames / FPS:g}", *SCENE, "--quiet")
    train_s, _ = stgs_step("train", str(scene), str(model), "--budget", "quick", "--layers", "layered",
                           "--grid-side", "16", "--static-grid-side", "16", "--gop-size", "60",
                           "--max-memory", max_memory, "--quiet")
    report = json.loads((model / "train_report.json").read_text())
    cells = [f"{report['frames']:,}", f"{len(report['gops'])}", f"{report['peak_rss_mb']:.0f}", f"{train_s:.0f}",
             f"{report['static_seconds']:.0f}"]
    if not play:
        return "| " + " | ".join(cells + ["–"] * 3) + " |"
    pack_s, pack_mb = stgs_step("pack", str(model), str(dash), "--quiet")
    with served(dash.parent) as base:
        log = work / f"play{frames}.json"
        play_s, _ = stgs_step("play", f"{base}{dash.name}/{MANIFEST}", "--log", str(log), "--size", "160x120",
                              "--allow-loopback")
    doc = json.loads(log.read_text())
    if doc["error"]:
        raise SystemExit(f"stgs play: {doc['error']}")
    cells += [f"{pack_mb:.0f} ({pack_s:.0f} s)", f"{doc['process_peak_rss_mb']:.0f} ({play_s:.0f} s)",
              f"{doc['rendered_frames']:,} of {report['frames']:,}"]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", default="60,150,600,1800",
                   help="capture lengths in frames (comma-separated; synth rounds up to whole 60-frame GOPs)")
    p.add_argument("--max-memory", default="256M", help="stgs train --max-memory for every run")
    p.add_argument("--play", type=int, action="append", default=[],
                   help="also pack, serve and play the capture of this many frames (repeatable)")
    p.add_argument("--work", type=Path, help="keep the scenes and models here (default: a temporary folder)")
    args = p.parse_args()
    print("| frames | GOPs | train peak MB | train s | stage A s | pack peak MB (s) | play peak MB (s) "
          "| frames played |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for frames in (int(f) for f in args.frames.split(",")):
            print(row(frames, work, args.max_memory, frames in args.play), flush=True)


if __name__ == "__main__":
    main()
