"""The web player's frame time in headless Chromium (Debian's; WebGL2 on SwiftShader, which runs the GPU's work on
this machine's CPU cores): per-stage milliseconds (feature copy, deform + read-back, depth sort in its worker,
splat + composite), frames per second, start-up and seek times, per packaged scene.

    python -m bench.web.web TREE [TREE ...] [--size 640x360] [--quality top|lowest] [--frames 20]
        [--backend webgl2-texture|webgl2-uniform|webgpu ...]

Each TREE is a packaged scene folder with an AV1 set, or a still scene. `stgs serve` offers them on loopback; the
page shows each scene's first frames one by one at a scene camera with `timing=sync` (a one-pixel read after each
draw, so the draw's GPU work is counted in its own stage, not in the next frame's read-back), then seeks to the
middle GOP; a still is drawn that many times from the camera (no deformation, no seek; its "keyframe decode" is
the static layer's, its start-up from the manifest's request to the first picture). Prints
Markdown for docs/BENCHMARKS.md ("Web player") and the per-Gaussian cost model of each stage.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import urllib.request
from pathlib import Path

from stgs.cli.browser import browse, missing_browser, served_trees


def run(plan: dict) -> dict:
    out, failure = browse(plan, timeout=3600)
    if failure:
        raise SystemExit(f"browse failed: {failure}")
    return out


BACKENDS = {"webgl2-texture": "weights=texture", "webgl2-uniform": "weights=uniform", "webgpu": "deform=webgpu"}
"""Deformation back ends: WebGL2 with the weights in a texture (the default) or in uniform blocks, WebGPU compute."""


def measure(base: str, name: str, size: str, quality: str, frames: int, backend: str) -> dict:
    """Stage times over `frames` frames shown one by one (each presented: no frame is dropped), start-up (first
    frame after load) and a seek to the middle GOP (first frame after the seek), at the scene's first camera."""
    mpd = json.loads(urllib.request.urlopen(base + "scenes").read())["scenes"]
    scene = next(s for s in mpd if s["name"] == name)
    still = scene.get("still", False)
    av1 = sorted((r for r in scene["ladder"] if r["codec"] == "av1"), key=lambda r: r["bandwidth"])
    ladder = [r["id"] for r in av1]
    rung = "-" if still else ladder[-1] if quality == "top" else ladder[0]
    cams = json.loads(urllib.request.urlopen(f"{base}{name}/cameras.json").read())["cameras"]
    url = (f"{base}player/?mpd=/{name}/manifest.mpd&timing=sync&size={size}&camera={cams[0]['name']}&autoplay=0"
           + ("" if still else f"&quality={rung}&{BACKENDS[backend]}"))
    storage = "'none (a still)'" if still else "p.deform.kind"
    state = ("({times: s.frameTimes, startup: s.startupMs, keyframe: s.keyframeMs, static: s.staticMs, copy: s.copyMs, "
             "visible: s.visible, capacity: p.manifest.shape.capacity, staticCount: p.manifest.staticLayer ? "
             f"p.manifest.staticLayer.capacity : 0, storage: {storage}}})")
    shown = "0" if still else "f"
    steps = [
        {"goto": url},
        {"wait": "window.stgsPlayer && stgsPlayer.stats.shown !== null", "timeout": 600_000},
        {"eval": f"(async () => {{ for (let f = 1; f < {frames}; f++) await stgsPlayer.showFrame({shown}, 600000); "
                 "return 1; })()", "as": "_"},
        {"eval": f"((p, s) => {state})(stgsPlayer, stgsPlayer.stats)", "as": "play"},
    ]
    if not still:
        steps += [
            {"eval": f"(window.before = stgsPlayer.stats.presentedFrames, stgsPlayer.seek({scene['gops'] // 2}), 1)",
             "as": "_"},
            {"wait": "stgsPlayer.stats.presentedFrames > window.before", "timeout": 600_000},
            {"eval": "stgsPlayer.stats.seekMs", "as": "seek"}]
    steps.append({"eval": "navigator.userAgent", "as": "agent"})
    out = run({"webgpu": True, "viewport": [900, 700], "steps": steps})
    r = out["results"]
    times = r["play"]["times"][2:]  # the first frames include shader warm-up

    def med(key: str) -> float:
        return statistics.median(t[key] for t in times)

    total = [t["deform"] + t["sortWait"] + t["draw"] for t in times]
    return {"scene": name, "dynamic": r["play"]["capacity"], "static": r["play"]["staticCount"],
            "visible": r["play"]["visible"], "rung": rung, "size": size, "storage": r["play"]["storage"],
            "deform": med("deform"), "sort": med("sort"), "sort_wait": med("sortWait"), "draw": med("draw"),
            "frame": statistics.median(total), "fps": 1000 / statistics.median(total),
            "keyframe": r["play"]["static" if still else "keyframe"], "copy": r["play"]["copy"],
            "startup": r["play"]["startup"],
            "seek": r.get("seek"), "agent": r["agent"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("trees", nargs="+", type=Path)
    p.add_argument("--size", default="640x360")
    p.add_argument("--quality", choices=("top", "lowest"), default="top")
    p.add_argument("--backend", choices=tuple(BACKENDS), action="append",
                   help="deformation back end (repeat to compare; default: webgl2-texture)")
    p.add_argument("--frames", type=int, default=20, help="frames shown one by one per scene (default: 20)")
    args = p.parse_args(argv)
    if missing_browser():
        raise SystemExit(f"bench.web.web: {missing_browser()}")
    with served_trees(args.trees) as base:
        rows = [measure(base, tree.resolve().name, args.size, args.quality, args.frames, backend)
                for tree in args.trees for backend in (args.backend or ["webgl2-texture"])]
    print(f"Chromium: {rows[0]['agent']}\n")
    print("| scene | Gaussians (static + dynamic) | drawn | size | deformation | copy ms | deform + read-back ms | "
          "sort ms (worker; round trip) | draw ms | frame ms | fps | keyframe decode ms | start-up ms | seek ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['static']:,} + {r['dynamic']:,} | {r['visible']:,} | {r['size']} | "
              f"{r['storage']} | {r['copy']:.2f} | {r['deform']:.1f} | {r['sort']:.1f}; {r['sort_wait']:.1f} | "
              f"{r['draw']:.1f} | {r['frame']:.1f} | {r['fps']:.1f} | {r['keyframe'] or 0:.0f} | {r['startup']:.0f} | "
              f"{'-' if r['seek'] is None else format(r['seek'], '.0f')} |")
    print("\nPer-Gaussian cost of each stage (ms per 1,000 Gaussians of the layer it touches):\n")
    print("| scene | deform + read-back / 1k dynamic | sort / 1k Gaussians | draw / 1k drawn |")
    print("|---|---|---|---|")
    for r in rows:
        sort = 1000 * r["sort"] / (r["dynamic"] + r["static"])
        deform = f"{1000 * r['deform'] / r['dynamic']:.2f}" if r["dynamic"] else "-"
        print(f"| {r['scene']} | {deform} | {sort:.3f} | "
              f"{1000 * r['draw'] / max(r['visible'], 1):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
