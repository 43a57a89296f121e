"""Where a splat's time goes, stage by stage, and how much of the binning early termination could save.

    python -m bench.frame.splat_stages --model /work/runs/s1 --model /tmp/rt/demo --repeats 30

Per model (format 1, its GOP 0, frame G/2) at its first camera, 640x360, native fp32 deformation with the
player's culling: the native projection, the binning alone (sort + tile lists), and the whole inference
forward (binning + compositing), medians of `repeats`; then the (tile, Gaussian) pairs binned and the pairs
each tile's compositing reached before every pixel saturated (the largest last-contributor rank of its
pixels). Pairs past that point are binned but never composited: "early termination before binning" could
at most save their share of the binning's list-filling, which bounds that lever from above.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import torch

from bench.frame.culling import first_camera, table_main
from stgs.camera import resize
from stgs.model.renderer import FrameRenderer
from stgs.model.store import load_gop, read_meta
from stgs.render.native import bin_native, f32, project_native, raster_forward
from stgs.render.stages import TILE


def reached_pairs(n_contrib: torch.Tensor) -> int:
    """Sum over tiles of the largest 1-based last-contributor rank among the tile's pixels."""
    h, w = n_contrib.shape
    pad = torch.zeros(-(-h // TILE) * TILE, -(-w // TILE) * TILE, dtype=torch.int32)
    pad[:h, :w] = n_contrib
    tiles = pad.reshape(pad.shape[0] // TILE, TILE, pad.shape[1] // TILE, TILE)
    return int(tiles.amax(dim=(1, 3)).sum())


def measure(model_dir: Path, repeats: int) -> str:
    meta = read_meta(model_dir)
    model = load_gop(model_dir, meta, 0)
    cam = resize(first_camera(model_dir), 640, 360)
    with torch.no_grad():
        g = FrameRenderer(model).gaussians(meta.shape.gop_size // 2, cam)
    view, K = cam.viewmat.float(), cam.K.float()
    bg = torch.zeros(3)
    colors = f32(g.colors)

    def project():
        return project_native(g.means, g.quats, g.scales, g.opacities, view, K)

    p = project()
    args = (f32(p.means2d), f32(p.conics), f32(g.opacities), f32(p.depths), f32(p.extents))

    def binning():
        return bin_native(*args, cam.width, cam.height)

    def forward(for_backward: bool = False):
        means2d, conics, opacities, depths, extents = args
        return raster_forward(means2d, conics, opacities, colors, bg, depths, extents, cam.width, cam.height,
                              for_backward)

    times: dict[str, list[float]] = {"project": [], "bin": [], "forward": []}
    for _ in range(3):
        project(), binning(), forward()
    for _ in range(repeats):
        for name, fn in (("project", project), ("bin", binning), ("forward", forward)):
            start = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - start) * 1e3)
    pairs = binning().pairs()
    _, handle = forward(for_backward=True)
    reached = reached_pairs(handle.pixels()[1])
    med = {k: statistics.median(v) for k, v in times.items()}
    unused = 1.0 - reached / max(pairs, 1)
    return (f"| {model_dir.name} | {meta.shape.capacity:,} | {med['project']:.2f} | {med['bin']:.2f} | "
            f"{med['forward'] - med['bin']:.2f} | {med['forward']:.2f} | {pairs:,} | {reached:,} | "
            f"{100 * unused:.0f} % | {100 * med['bin'] / (med['project'] + med['forward']):.0f} % |")


def main() -> int:
    return table_main(__doc__, "| scene | Gaussians | project ms | bin ms (sort + lists) | composite ms | forward ms | "
                      "pairs binned | pairs reached | binned, never composited | "
                      "binning's share of project + forward |", measure)


if __name__ == "__main__":
    raise SystemExit(main())
