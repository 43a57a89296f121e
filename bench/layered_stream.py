"""Layered scenes, the stream side: the same scene packed as format 2 (static layer sent once) and as format 1
(every GOP carries the backdrop), side by side per QP.

    python -m bench.layered_stream --tree /tmp/demo/dash --tree /tmp/demo/dash_format1 --work /tmp/ls

(`stgs demo` writes both trees of its scene: `dash` and `dash_format1`.) Per tree: the static segment's bytes;
per QP: bytes per GOP (keyframe + features), KB per frame with the static layer amortised over the scene and
over 60 s of content, the rendered PSNR stats.json gives (against each format's own uncompressed model), and,
from a real `stgs play` in its own process against the real server on loopback (pinned QP, 640x360 at the
scene's first camera, the whole scene): feature decode ms per frame (median), deform + splat ms per frame
(median) and the time from the first request to the first frame. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import statistics
from pathlib import Path

from bench.realtime import play_process
from stgs.client.view import parse_scene_cameras
from stgs.packager.manifest import kb_per_frame
from stgs.server.app import loopback
from stgs.tree import CAMERAS, MANIFEST, STATS

AMORTISE_S = 60.0
"""The static layer's bytes spread over this much content, beside the scene's own length."""


def size_rows(stats: dict) -> dict[str, dict]:
    """Per Representation: bytes per GOP and KB per frame (static over the scene; over AMORTISE_S)."""
    gops = stats["gops"]
    frames_60s = round(AMORTISE_S * stats["frames_per_gop"] / stats["segment_seconds"])
    rows = {}
    for rid, rep in stats["representations"].items():
        per_gop = statistics.mean(gop["keyframe_bytes"] + gop["representations"][rid]["bytes"] for gop in gops)
        rows[rid] = {"qp": rep["qp"], "gop_bytes": per_gop, "kb_frame_scene": kb_per_frame(stats, rid),
                     "kb_frame_60s": kb_per_frame(stats, rid, frames_60s), "render_psnr": rep["mean_render_psnr"]}
    return rows


async def play_rows(tree: Path, work: Path, qps: list[int], size: str) -> dict[int, dict]:
    view = ["--size", size]
    if (tree / CAMERAS).is_file():
        view += ["--camera", parse_scene_cameras(json.loads((tree / CAMERAS).read_text()))[0].name]
    out = {}
    async with loopback(tree) as base:
        url = base + MANIFEST
        await play_process(url, work / f"{tree.name}-warmup.json", [*view, "--duration", "0.5"])
        for qp in qps:
            log = await play_process(url, work / f"{tree.name}-qp{qp}.json", [*view, "--qp", str(qp)])
            gops = log["gops"]
            decode = [ms for g in gops for ms in g["decode_ms"]]
            render = [d + s for g in gops for d, s in zip(g["deform_ms"], g["splat_ms"], strict=True)]
            out[qp] = {"decode_ms": statistics.median(decode), "render_ms": statistics.median(render),
                       "first_frame_s": log["time_to_first_frame_s"]}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tree", type=Path, action="append", required=True, help="packaged tree (repeatable)")
    parser.add_argument("--qps", default="16,20,24,28,32")
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--work", type=Path, required=True, help="folder for the playback logs")
    args = parser.parse_args(argv)
    qps = [int(q) for q in args.qps.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    print("| tree | static layer | QP | bytes/GOP | KB/frame (scene) | KB/frame (60 s) | rendered PSNR dB | "
          "feature decode ms/frame | deform + splat ms/frame | first frame s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for tree in args.tree:
        stats = json.loads((tree / STATS).read_text())
        sizes = {r["qp"]: r for r in size_rows(stats).values()}
        played = asyncio.run(play_rows(tree, args.work, qps, args.size))
        static = f"{stats['static']['capacity']:,} G, {stats['static']['bytes'] / 1e3:.1f} kB" \
            if stats.get("static") else "-"
        for qp in qps:
            s, p = sizes[qp], played[qp]
            print(f"| {tree.name} | {static} | {qp} | {s['gop_bytes'] / 1e3:,.1f} kB | {s['kb_frame_scene']:.2f} | "
                  f"{s['kb_frame_60s']:.2f} | {s['render_psnr']:.2f} | {p['decode_ms']:.2f} | "
                  f"{p['render_ms']:.1f} | {p['first_frame_s']:.2f} |")
    print(f"\nMachine: {platform.machine()} {platform.processor() or ''}; {args.size}, pinned QP, whole scene")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
