"""Player benchmark: per-GOP download and pre-decode, per-frame deform and splat (`stgs bench play`).

Streams a packaged scene from the real server on loopback with the real
player, once per pinned QP (and once with the dynamic ABR), rendering every
frame at a scene camera (else an orbit) at the requested size, as fast as
possible. Per GOP: download, keyframe decode (JPEG XL), feature decode
(HEVC), dequantise (untile + model build) and their sum, the pre-decode the
player overlaps with playback; per frame: deform and splat. Prints Markdown
for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import asyncio
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

from stgs.client import PlayConfig, play
from stgs.client.view import ViewSpec, parse_scene_cameras
from stgs.native.build import available
from stgs.packager import PackConfig, pack
from stgs.server.app import loopback
from stgs.synth import SynthConfig, synthesize
from stgs.tree import CAMERAS, MANIFEST, STATS

PREDECODE_TARGET_MS = 500.0
FRAME_TARGET_MS = 33.0


def prepare(dash: Path | None, scene: SynthConfig, qps: list[int], work: Path) -> Path:
    if dash is not None:
        return dash
    print(f"synthesising a {scene.grid_side ** 2}-Gaussian scene and packing it at QPs {qps} (minutes) ...",
          flush=True)
    synthesize(scene, work / "model", progress=False)
    pack(work / "model", work / "dash", PackConfig(qps=tuple(qps)), progress=False)
    return work / "dash"


def ms(values: list[float]) -> str:
    return f"{statistics.median(values) * 1e3:.0f}" if values else "–"


def row(label: str, log: dict, stats: dict, width: int, height: int) -> str:
    gops = log["gops"]
    predecode = [g["decode_s"] for g in gops]
    deform = statistics.mean(g["deform_ms_mean"] for g in gops)
    splat = statistics.mean(g["splat_ms_mean"] for g in gops)
    render = statistics.median(r for g in gops for r in g["render_ms"])
    psnrs = [stats["gops"][g["index"]]["representations"][g["rep"]]["render_psnr"] for g in gops]
    cells = [label, f"{width}×{height}", f"{log['kb_per_frame']:.1f}", f"{statistics.mean(psnrs):.2f}",
             ms([g["download_s"] for g in gops]), ms([g["keyframe_decode_s"] for g in gops]),
             ms([g["feature_decode_s"] for g in gops]), ms([g["dequantise_s"] for g in gops]),
             f"**{ms(predecode)}** (max {max(predecode) * 1e3:.0f})", f"{deform:.1f}", f"{splat:.1f}",
             f"**{render:.1f}**", str(log["stalls"]["count"])]
    return "| " + " | ".join(cells) + " |"


async def measure(dash: Path, qps: list[int], width: int, height: int) -> list[str]:
    stats = json.loads((dash / STATS).read_text())
    camera = None
    if (dash / CAMERAS).is_file():  # the scene's first camera (cam00 for synthetic scenes)
        camera = parse_scene_cameras(json.loads((dash / CAMERAS).read_text()))[0].name
    view = ViewSpec(camera=camera, width=width, height=height)
    rows = []
    async with loopback(dash) as base:
        url = base + MANIFEST
        await play(PlayConfig(url, qp=qps[0], view=view, duration_s=0.1))  # warm-up: native lib, page cache
        for qp in qps:
            rows.append(row(f"QP {qp}", await play(PlayConfig(url, qp=qp, view=view)), stats, width, height))
        rows.append(row("dynamic ABR", await play(PlayConfig(url, abr="dynamic", view=view)), stats, width, height))
    return rows


def main(dash: Path | None, scene: SynthConfig, qps: list[int], width: int, height: int) -> int:
    with tempfile.TemporaryDirectory(prefix="stgs-bench-play-") as tmp:
        start = time.perf_counter()
        root = prepare(dash, scene, qps, Path(tmp))
        prep_s = time.perf_counter() - start
        rows = asyncio.run(measure(root, qps, width, height))
    print(f"\nMachine: {platform.machine()}, {platform.processor() or 'cpu'}, native kernels "
          f"{'on' if available() else 'off'}; scene prepared in {prep_s:.0f} s. Medians over GOPs; "
          f"per-frame times are means over a GOP's frames, the render column the median frame.\n")
    print("| stream | size | KB/frame | rendered PSNR (dB) | download ms/GOP | keyframe decode ms | "
          "feature decode ms | dequantise ms | pre-decode ms/GOP | deform ms/frame | splat ms/frame | "
          "deform + splat ms | stalls |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(r)
    print(f"\nTargets: pre-decode ≤ {PREDECODE_TARGET_MS:.0f} ms per 2-second GOP, deform + splat ≤ "
          f"{FRAME_TARGET_MS:.0f} ms per frame.")
    return 0
