"""Layered scenes, the stream side: the same scene packed as format 2 (static layer sent once) and as format 1
(every GOP carries the backdrop), side by side per QP.

    python -m bench.training.layered_stream --tree /tmp/demo/dash --tree /tmp/demo/dash_format1 --work /tmp/ls

(`stgs demo` writes both trees of its scene: `dash` and `dash_format1`.) Per tree: the static segment's bytes;
per QP: bytes per GOP (keyframe + features), KB per frame with the static layer amortised over the scene and
over 60 s of content, the rendered PSNR stats.json gives (against each format's own uncompressed model), and,
from a real `stgs play` in its own process against the real server on loopback (pinned QP, 640x360 at the
scene's first camera, the whole scene): feature decode ms per frame (median), deform + splat ms per frame
(median) and the time from the first request to the first frame. Then, for each format-1 rung, the KB per frame a
format-2 tree of the same scene needs at the same rendered PSNR (its ladder interpolated, log KB linear in PSNR
between neighbouring rungs, never extrapolated: pack the format-2 tree with QPs that span format 1's PSNRs) and the
ratio. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import platform
import statistics
from pathlib import Path

import numpy as np

from bench.playback.realtime import play_process
from stgs.camera import read_scene_cameras
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


def kb_at_psnr(ladder: list[tuple[float, float]], psnr: float) -> float | None:
    """KB per frame at rendered PSNR `psnr` on a ladder of (PSNR dB, KB per frame) rungs: log KB interpolated
    linearly in PSNR between the two rungs around it; None outside the ladder's PSNR range."""
    rungs = sorted(ladder)
    if not rungs or not rungs[0][0] <= psnr <= rungs[-1][0]:
        return None
    xs = np.array([r[0] for r in rungs])
    logs = np.log([r[1] for r in rungs])
    return math.exp(float(np.interp(psnr, xs, logs)))


def equal_psnr_rows(reference: dict[str, dict], candidate: dict[str, dict], key: str) -> list[dict]:
    """Per `reference` rung (size_rows output, QP order): the `candidate` ladder's KB per frame (column `key`) at
    the reference rung's rendered PSNR, and the ratio candidate / reference (None where outside the ladder)."""
    ladder = [(r["render_psnr"], r[key]) for r in candidate.values()]
    rows = []
    for ref in sorted(reference.values(), key=lambda r: r["qp"]):
        kb = kb_at_psnr(ladder, ref["render_psnr"])
        rows.append({"qp": ref["qp"], "psnr": ref["render_psnr"], "reference_kb": ref[key], "candidate_kb": kb,
                     "ratio": None if kb is None else kb / ref[key]})
    return rows


async def play_rows(tree: Path, work: Path, qps: list[int], size: str) -> dict[int, dict]:
    view = ["--size", size]
    if (tree / CAMERAS).is_file():
        view += ["--camera", read_scene_cameras(tree)[0].name]
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


def print_equal_psnr(reference: tuple[str, dict], candidate: tuple[str, dict]) -> None:
    """The equal-PSNR table of a format-2 ladder (candidate) against a format-1 ladder (reference)."""
    (ref_name, ref_rows), (cand_name, cand_rows) = reference, candidate
    print(f"\n{cand_name} against {ref_name} at {ref_name}'s rendered PSNR per rung:\n")
    print(f"| {ref_name} QP | rendered PSNR dB | {ref_name} KB/frame | {cand_name} KB/frame (scene) | ratio | "
          f"{cand_name} KB/frame (60 s) | ratio (60 s) |")
    print("|---|---|---|---|---|---|---|")
    scene = equal_psnr_rows(ref_rows, cand_rows, "kb_frame_scene")
    long = equal_psnr_rows(ref_rows, cand_rows, "kb_frame_60s")
    for a, b in zip(scene, long, strict=True):
        def cell(row: dict) -> str:
            return ("outside the ladder | -" if row["candidate_kb"] is None
                    else f"{row['candidate_kb']:.2f} | **{row['ratio']:.2f}**")
        print(f"| {a['qp']} | {a['psnr']:.2f} | {a['reference_kb']:.2f} | {cell(a)} | {cell(b)} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tree", type=Path, action="append", required=True, help="packaged tree (repeatable)")
    parser.add_argument("--qps", help="QPs to play (default: each tree's whole ladder)")
    parser.add_argument("--no-play", action="store_true", help="sizes and PSNR only, no playback")
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--work", type=Path, required=True, help="folder for the playback logs")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    print("| tree | static layer | QP | bytes/GOP | KB/frame (scene) | KB/frame (60 s) | rendered PSNR dB | "
          "feature decode ms/frame | deform + splat ms/frame | first frame s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    ladders: dict[bool, list[tuple[str, dict]]] = {False: [], True: []}
    for tree in args.tree:
        stats = json.loads((tree / STATS).read_text())
        rows = size_rows(stats)
        ladders["static" in stats].append((tree.name, rows))
        sizes = {r["qp"]: r for r in rows.values()}
        qps = sorted(sizes) if args.qps is None else [int(q) for q in args.qps.split(",") if int(q) in sizes]
        played = {} if args.no_play else asyncio.run(play_rows(tree, args.work, qps, args.size))
        static = f"{stats['static']['capacity']:,} G, {stats['static']['bytes'] / 1e3:.1f} kB" \
            if stats.get("static") else "-"
        for qp in qps:
            s = sizes[qp]
            p = (f"{played[qp]['decode_ms']:.2f} | {played[qp]['render_ms']:.1f} | {played[qp]['first_frame_s']:.2f}"
                 if qp in played else "- | - | -")
            print(f"| {tree.name} | {static} | {qp} | {s['gop_bytes'] / 1e3:,.1f} kB | {s['kb_frame_scene']:.2f} | "
                  f"{s['kb_frame_60s']:.2f} | {s['render_psnr']:.2f} | {p} |")
    for reference in ladders[False]:
        for candidate in ladders[True]:
            print_equal_psnr(reference, candidate)
    print(f"\nMachine: {platform.machine()} {platform.processor() or ''}; {args.size}, pinned QP, whole scene")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
