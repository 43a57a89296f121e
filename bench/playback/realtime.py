"""Real-time playback benchmark: does `stgs play --realtime` hold 30 fps with no drop and no stall, per scene,
QP, deformation precision and feature decoder threads; start-up, seek and peak memory; a per-frame timeline
plot.

    python -m bench.playback.realtime --model /work/runs/s1 --model /tmp/demo/model --seconds 60 --qps 16,24,32 \\
        --work /tmp/rt --timeline docs/realtime_timeline.png

Each model dir (a trained or `stgs synth` scene, format 1 or layered format 2) is looped to `--seconds` of
content (its GOPs repeated in order: decode and render cost are per GOP, the content repeats) and packed once
at the QPs; a
packaged tree (`--dash`, or `stgs bench play --dash`) is played as it is. The real server serves it on
loopback and the real `stgs play --realtime` plays it in its own process at the scene's first camera,
640x360, for the whole duration; then a seek: `--start` at the middle, 4 seconds. Start-up and seek are
noisy on a loaded loopback (the server shares the cores): each is measured `--repeats` times, the whole run
counting as one start-up and the others playing 4 seconds from the start, and the table gives the median
and the worst. A virtual machine's host may take CPU time from it (steal): the table gives the share taken
during each whole run (/proc/stat), since a busy host drops frames the player would not. Prints Markdown
for docs/BENCHMARKS.md; the logs stay in --work.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import platform
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from bench.playback.playlog_stats import cpu_times, frame_stats, held_realtime, latency_cell, steal_share
from stgs.camera import read_scene_cameras
from stgs.client.manifest import Presentation
from stgs.model.native_deform import runnable_precisions
from stgs.model.store import read_meta
from stgs.packager import PackConfig, pack
from stgs.server.app import loopback
from stgs.tree import CAMERAS, MANIFEST, MODEL_META, STATS

SEEK_SECONDS = 4.0


def loop_model(src: Path, dst: Path, seconds: float) -> Path:
    """A model dir playing `seconds`: src's GOPs repeated in order (files linked, not copied)."""
    meta = read_meta(src)
    doc = json.loads((src / MODEL_META).read_text())
    count = max(meta.num_gops, math.ceil(seconds * meta.fps / meta.shape.gop_size))
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for entry in doc["gops"]:
        (dst / entry["file"]).symlink_to((src / entry["file"]).resolve())
    for extra in (CAMERAS, "gt", (doc.get("static") or {}).get("file")):  # a layered scene's static layer too
        if extra and (src / extra).exists():
            (dst / extra).symlink_to((src / extra).resolve())
    gops = doc["gops"]
    doc["gops"] = [{**gops[i % len(gops)], "index": i} for i in range(count)]
    doc.setdefault("extra", {})["looped_from"] = str(src)
    (dst / MODEL_META).write_text(json.dumps(doc, indent=1) + "\n")
    return dst


async def play_process(url: str, log: Path, args: list[str]) -> dict:
    """`stgs play` in its own process (its own peak memory); returns its log."""
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "stgs.cli", "play", url, "--log", str(log),
                                                *args, stdout=asyncio.subprocess.DEVNULL,
                                                stderr=asyncio.subprocess.PIPE)
    _, err = await proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"stgs play failed: {err.decode().strip()}")
    return json.loads(log.read_text())


def row(name: str, n: int, qp: int, setting: Setting, kbps: float, log: dict, starts: list[dict],
        seeks: list[dict], steal: float | None = None) -> str:
    """starts: the runs whose start-up is reported (`log` and the repeats); seeks: the seek runs; steal: the
    host's steal share during `log`'s run."""
    s = frame_stats(log)
    ok = held_realtime(log)
    cells = [name, f"{n:,}", str(qp), setting.precision, str(log["threads"]["decode"]), str(log["render_ahead"]),
             f"{kbps / 1e3:.2f}",
             f"{log['frames']}", f"**{log['dropped_frames']}**", f"**{log['stalls']['count']}**",
             "yes" if ok else "no",
             *(f"{s[k][0]:.1f} / {s[k][1]:.1f}" for k in ("decode", "wait", "deform", "splat")),
             latency_cell(starts), latency_cell(seeks),
             f"{log['process_peak_rss_mb']:.0f}", "–" if steal is None else f"{steal * 100:.0f}"]
    return "| " + " | ".join(cells) + " |"


HEADER = ("| scene | Gaussians | QP | deformation | decoder threads | render ahead | feature Mbit/s | frames | "
          "dropped | stalls | 30 fps held | decode + dequantise ms (median / p95) | wait ms | deform ms | splat ms | "
          "start-up s, median (worst) | seek s, median (worst) | peak RSS MB | host steal % |\n" + "|---" * 19 + "|")


@dataclass(frozen=True)
class Setting:
    """One player setting the benchmark plays each scene and QP with."""

    precision: str
    """Deformation precision (`stgs play --precision`)."""
    decode_threads: int | None
    """libavcodec threads of the feature decoder (None: the player's default for the core count)."""
    render_ahead: int | None = None
    """Frame slots a frame may render early (`stgs play --render-ahead`; None: the player's default)."""

    def flags(self) -> list[str]:
        threads = [] if self.decode_threads is None else ["--decode-threads", str(self.decode_threads)]
        ahead = [] if self.render_ahead is None else ["--render-ahead", str(self.render_ahead)]
        return ["--precision", self.precision, *threads, *ahead]

    @property
    def tag(self) -> str:
        return (self.precision + ("" if self.decode_threads is None else f"-dec{self.decode_threads}")
                + ("" if self.render_ahead is None else f"-ahead{self.render_ahead}"))


def prepare(source: Path, work: Path, seconds: float, qps: list[int]) -> tuple[str, Path]:
    """(name, packaged tree): a tree as it is, a model dir looped to `seconds` and packed at `qps`."""
    name = source.resolve().name
    if (source / MANIFEST).is_file():
        return name.removesuffix("-dash"), source
    looped = loop_model(source, work / f"{name}-looped", seconds)
    print(f"{name}: {read_meta(looped).num_gops} GOPs; packing at QPs {qps} ...", flush=True)
    pack(looped, work / f"{name}-dash", PackConfig(ladder="fixed", qps=tuple(qps), resume=True), progress=False)
    return name, work / f"{name}-dash"


async def run_scene(source: Path, work: Path, seconds: float, qps: list[int], settings: list[Setting],
                    size: str, repeats: int = 1) -> tuple[list[str], list[tuple[int, int, str, bool, Path]]]:
    """repeats: start-up and seek are each measured this many times (the whole run counts as one start-up;
    the others play SEEK_SECONDS from the start)."""
    name, dash = prepare(source, work, seconds, qps)
    stats = json.loads((dash / STATS).read_text())
    pres = Presentation.parse((dash / MANIFEST).read_bytes(), "http://localhost/" + MANIFEST)
    n = pres.shape.capacity + (pres.static.capacity if pres.static else 0)  # a layered scene: both layers
    if pres.static:
        name += f" (static {pres.static.capacity:,} + dynamic {pres.shape.capacity:,})"
    seconds = stats["segment_seconds"] * len(stats["gops"])
    view = ["--size", size]
    if (dash / CAMERAS).is_file():  # the scene's first camera, else the player's default orbit
        view += ["--camera", read_scene_cameras(dash)[0].name]
    rows, verdicts = [], []
    async with loopback(dash) as base:
        url = base + MANIFEST
        await play_process(url, work / "warmup.json", [*view, "--duration", "1"])  # page cache, native build
        for setting in settings:
            for qp in qps:
                tag = f"{name}-qp{qp}-{setting.tag}"
                common = [*view, "--realtime", "--qp", str(qp), *setting.flags()]
                before = cpu_times()
                log = await play_process(url, work / f"{tag}.json", common)
                steal = steal_share(before, cpu_times())
                starts, seeks = [log], []
                for r in range(repeats):
                    suffix = "" if r == 0 else f"-{r}"
                    if r:
                        starts.append(await play_process(url, work / f"{tag}-start{suffix}.json",
                                                         [*common, "--duration", f"{SEEK_SECONDS:g}"]))
                    seeks.append(await play_process(url, work / f"{tag}-seek{suffix}.json",
                                                    [*common, "--start", f"{seconds / 2:g}",
                                                     "--duration", f"{SEEK_SECONDS:g}"]))
                kbps = stats["representations"][f"qp{qp}"]["bandwidth"] / 1e3
                rows.append(row(name, n, qp, setting, kbps, log, starts, seeks, steal))
                verdicts.append((n, qp, setting.tag, held_realtime(log), work / f"{tag}.json"))
                print(rows[-1], flush=True)
    return rows, verdicts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, action="append", default=[], help="model dir (repeatable)")
    parser.add_argument("--dash", type=Path, action="append", default=[], help="packaged tree (repeatable)")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--qps", default="16,24,32")
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--precisions", default="fp32,bf16", help="deformation precisions, e.g. fp32,int16 "
                        "(those this CPU cannot run are skipped and said so)")
    parser.add_argument("--decode-threads", help="feature decoder threads to compare, e.g. 1,2 (default: the "
                        "player's default)")
    parser.add_argument("--render-ahead", help="frame slots of rendering ahead to compare, e.g. 0,2 (default: the "
                        "player's default)")
    parser.add_argument("--repeats", type=int, default=3, help="start-up and seek runs per scene, QP and "
                        "setting (the table gives the median and the worst; default: 3)")
    parser.add_argument("--work", type=Path, required=True, help="folder for looped models, trees and logs")
    parser.add_argument("--timeline", type=Path, help="PNG of the per-frame timeline of one run")
    parser.add_argument("--timeline-log", type=Path, help="the run to plot (default: the largest scene that "
                        "held 30 fps at the middle QP, else the smallest scene's)")
    args = parser.parse_args(argv)
    if not args.model and not args.dash:
        parser.error("give at least one --model or --dash")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    qps = [int(q) for q in args.qps.split(",")]
    runnable = runnable_precisions()
    precisions = [p for p in args.precisions.split(",") if p in runnable]
    skipped = sorted(set(args.precisions.split(",")) - set(precisions))
    threads = [None] if args.decode_threads is None else [int(t) for t in args.decode_threads.split(",")]
    aheads = [None] if args.render_ahead is None else [int(r) for r in args.render_ahead.split(",")]
    settings = [Setting(p, t, r) for p in precisions for t in threads for r in aheads]
    args.work.mkdir(parents=True, exist_ok=True)
    rows, verdicts = [], []
    for source in [*args.model, *args.dash]:
        r, v = asyncio.run(run_scene(source, args.work, args.seconds, qps, settings, args.size, args.repeats))
        rows += r
        verdicts += v
    print(f"\nMachine: {platform.machine()} {platform.processor() or ''}; {args.seconds:g} s per run at {args.size}"
          + (f"; not run here: {', '.join(skipped)} (this CPU cannot)" if skipped else "") + "\n")
    print(HEADER)
    print("\n".join(rows))
    print("\nLargest scene that held 30 fps (no drop, no stall) for the whole run:\n")
    print("| QP | setting | largest Gaussians |\n|---|---|---|")
    for setting in settings:
        for qp in qps:
            held = [n for n, q, tag, ok, _ in verdicts if q == qp and tag == setting.tag and ok]
            print(f"| {qp} | {setting.tag} | {max(held):,} |" if held else f"| {qp} | {setting.tag} | none |")
    if args.timeline:
        from bench.playback.timeline import plot_timeline

        chosen = args.timeline_log or pick_timeline(verdicts, qps, settings[0].tag)
        plot_timeline(json.loads(chosen.read_text()), args.timeline, title=chosen.stem)
        print(f"\ntimeline of {chosen.name}: {args.timeline}")
    return 0


def pick_timeline(verdicts: list[tuple[int, int, str, bool, Path]], qps: list[int], tag: str) -> Path:
    """The run of setting `tag` at the middle QP: the largest scene that held 30 fps, else the smallest one."""
    middle = qps[len(qps) // 2]
    runs = [(n, ok, path) for n, q, t, ok, path in verdicts if q == middle and t == tag]
    held = [(n, path) for n, ok, path in runs if ok]
    return max(held)[1] if held else min((n, path) for n, _, path in runs)[1]



def cli(dash: Path | None, scene, qps: list[int], width: int, height: int, repeats: int = 3) -> int:
    """`stgs bench play`: a packaged tree as it is, else the SynthConfig `scene` synthesised, looped to 60 s and
    packed (in a temporary folder)."""
    import tempfile

    from stgs.synth import synthesize

    with tempfile.TemporaryDirectory(prefix="stgs-bench-play-") as tmp:
        argv = ["--qps", ",".join(map(str, qps)), "--size", f"{width}x{height}", "--repeats", str(repeats),
                "--work", tmp]
        if dash is not None:
            return main([*argv, "--dash", str(dash)])
        print(f"synthesising a {scene.grid_side ** 2}-Gaussian scene (minutes) ...", flush=True)
        synthesize(scene, Path(tmp) / "model", progress=False)
        return main([*argv, "--model", str(Path(tmp) / "model")])


if __name__ == "__main__":
    raise SystemExit(main())
