"""The Spark comparison page (web/bench/spark.ts, bench/web/web_spark.py) in Chromium against `stgs serve`: Spark
draws the player's own deformed Gaussians straight from its GPU textures, and its picture matches ours within
Spark's quantisation; the player's CSP refuses the blob: worker Spark makes by default (the bench build serves it
as a file)."""

from __future__ import annotations

import cv2

from bench.web.web_spark import build_bench_page, measure
from stgs.cli.browser import served as serve_root
from tests.web.conftest import need_browser


def test_spark_draws_the_players_gaussians_from_its_textures(web_root, tmp_path):
    need_browser()
    page = build_bench_page()
    with serve_root(web_root, player_dir=page) as base:
        packed = measure(base, "small", "192x144", frames=4, ext=False, pictures=tmp_path)
        ext = measure(base, "small", "192x144", frames=4, ext=True, pictures=tmp_path)
    ours = cv2.imread(str(tmp_path / "small-ours.png"))
    assert ours is not None and ours.shape == (144, 192, 3) and ours.std() > 5
    for row, name in ((packed, "spark-packed"), (ext, "spark-ext")):
        assert row["gaussians"] == 512  # both layers: 256 static + 256 dynamic
        spark = cv2.imread(str(tmp_path / f"small-{name}.png"))
        assert spark.shape == ours.shape and spark.std() > 5
        assert row["psnr"] >= 30, (name, row["psnr"])
        assert row["spark"] > 0 and row["ours"] > 0
    assert ext["psnr"] >= packed["psnr"] - 0.5  # the 32-byte buffer is not worse than the 16-byte one
    assert packed["blob_refused"] is True
