"""Spark (the three.js Gaussian splat renderer) against the web player's own splat pass, on the same deformed
Gaussians, in headless Chromium (Debian's; WebGL2 on SwiftShader): per-frame milliseconds of each and the PSNR
of Spark's picture against ours (ours matches `stgs play` to >= 40 dB: tests/web). Answers whether the player
should hand its Gaussians to Spark instead of splatting them itself (docs/WEB.md, "Spark, measured").

    python -m bench.web.web_spark TREE [TREE ...] [--size 640x360] [--frames 12]

Builds web/dist-bench (`node build.mjs --bench`: web/bench/spark.ts, never shipped) and serves it at /player/
beside each TREE. Per scene, the page first plays `--frames` frames one by one with our pass (timing=sync), then
again, handing each frame's deform textures to a Spark SplatGenerator (no CPU copy of a Gaussian), once with
Spark's 16-byte PackedSplats and once with its 32-byte ExtSplats. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import base64
import json
import math
import statistics
import subprocess
import sys
import urllib.request
from pathlib import Path

from stgs.cli.browser import WEB, browse, missing_browser, served_trees

OUR_EXTENT = math.sqrt(2 * math.log(255))
"""Spark's quad half-size (standard deviations) at which the most opaque splat's alpha reaches our 1/255 cut-off;
Spark's own default is sqrt(8) = 2.83 (a smaller quad: less fill, the splat's tail cut)."""


def build_bench_page() -> Path:
    subprocess.run(["node", "build.mjs", "--bench"], cwd=WEB, check=True, stdout=subprocess.DEVNULL)
    return WEB / "dist-bench"


def measure(base: str, name: str, size: str, frames: int, ext: bool, pictures: Path | None,
            std_dev: float = OUR_EXTENT) -> dict:
    scene = next(s for s in json.loads(urllib.request.urlopen(base + "scenes").read())["scenes"] if s["name"] == name)
    top = max((r for r in scene["ladder"] if r["codec"] == "av1"), key=lambda r: r["bandwidth"])["id"]
    cams = json.loads(urllib.request.urlopen(f"{base}{name}/cameras.json").read())["cameras"]
    url = (f"{base}player/?mpd=/{name}/manifest.mpd&size={size}&quality={top}&camera={cams[0]['name']}"
           f"&frames={frames}&ext={int(ext)}&pictures={int(pictures is not None)}&stddev={std_dev}")
    out, failure = browse({"viewport": [900, 700], "steps": [
        {"goto": url},
        {"eval": "window.sparkBench", "as": "bench"},
    ]}, timeout=3600)
    if failure:
        raise SystemExit(f"bench.web.web_spark: {failure} (page errors: {out.get('errors')}, console: "
                         f"{[c['text'] for c in out.get('console', []) if c['type'] == 'error'][:3]})")
    r = out["results"]["bench"]
    if pictures is not None:
        pictures.mkdir(parents=True, exist_ok=True)
        for who, url in zip(("ours", "spark-ext" if ext else "spark-packed"), r["pictures"], strict=True):
            (pictures / f"{name}-{who}.png").write_bytes(base64.b64decode(url.split(",", 1)[1]))
    ours = r["ours"][2:]  # the first frames include shader warm-up
    spark = r["spark"][2:]

    def med(rows: list[dict], *keys: str) -> float:
        return statistics.median(sum(t[k] for k in keys) for t in rows)

    return {"scene": name, "gaussians": r["gaussians"], "size": size, "ext": ext, "std_dev": std_dev,
            "deform": med(ours, "deform"),
            "ours_sort": med(ours, "sort"), "ours_draw": med(ours, "draw"), "ours": med(ours, "sort", "draw"),
            "spark_update": med(spark, "update"), "spark_draw": med(spark, "draw"),
            "spark": med(spark, "update", "draw"),
            "psnr": r["psnr"], "blob_refused": r["blobWorkerRefused"], "agent": r["agent"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("trees", nargs="+", type=Path)
    p.add_argument("--size", default="640x360")
    p.add_argument("--frames", type=int, default=12,
                   help="frames shown one by one per scene and renderer (default: 12)")
    p.add_argument("--max-std-dev", type=float, action="append",
                   help=f"Spark's quad half-size in standard deviations (repeat to compare; default {OUR_EXTENT:.2f}, "
                        "ours)")
    p.add_argument("--pictures", type=Path, help="save each scene's middle frame by both renderers here (PNG)")
    args = p.parse_args(argv)
    if missing_browser():
        raise SystemExit(f"bench.web.web_spark: {missing_browser()}")
    page = build_bench_page()
    with served_trees(args.trees, player_dir=page) as base:
        rows = [measure(base, tree.resolve().name, args.size, args.frames, ext, args.pictures, k)
                for tree in args.trees for ext in (False, True) for k in (args.max_std_dev or [OUR_EXTENT])]
    print(f"Chromium: {rows[0]['agent']}; the player's CSP refuses Spark's blob: worker: "
          f"{'yes' if rows[0]['blob_refused'] else 'no'}\n")
    print("| scene | Gaussians | size | Spark buffer | Spark quad (σ) | deform + read-back ms (both) | "
          "ours: sort + draw ms | Spark: generate + read-back + sort ms | Spark: draw ms | "
          "Spark / ours (after deform) | Spark vs ours PSNR dB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        buffer = "ExtSplats 32 B" if r["ext"] else "PackedSplats 16 B"
        print(f"| {r['scene']} | {r['gaussians']:,} | {r['size']} | {buffer} | {r['std_dev']:.2f} | "
              f"{r['deform']:.1f} | {r['ours_sort']:.1f} + {r['ours_draw']:.1f} = {r['ours']:.1f} | "
              f"{r['spark_update']:.1f} | {r['spark_draw']:.1f} | {r['spark'] / r['ours']:.2f}x | {r['psnr']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
