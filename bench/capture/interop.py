"""What importing a 3DGS file costs: spherical harmonics above degree 1 folded into our static layer's degree 0 and 1,
and each format's round trip of an exported frame (`python -m bench.capture.interop`, prints Markdown for
docs/BENCHMARKS.md, "Interop").

Fold: a synth scene's backdrop (its static layer) is given view-dependent colour of degree 3, coefficients drawn
with a standard deviation per degree (`--sigma`, about what trained 3DGS scenes hold), as a file made elsewhere
would have it. The full degree-3 colour is the reference; the folded layer is drawn by our renderer (colour
relu(C) + d . sh1). PSNR over the scene's training cameras (those the fit sees) and over an orbit of other cameras,
and the fold's time per million Gaussians.

Formats: frame 7 of the scene exported as PLY, glb and SPZ, read back into a static layer and drawn from a scene
camera against the frame as the player renders it; file size and write + read time.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera, rig_orbit
from stgs.data import open_dataset
from stgs.interop import sh as harmonics
from stgs.interop.files import read_splats, write_splats
from stgs.interop.frames import frame_splats, open_source
from stgs.interop.splats import Splats, from_static, to_static
from stgs.interop.static import fold_over
from stgs.metrics import psnr
from stgs.model.renderer import FrameRenderer, in_guard_band, splat
from stgs.render import rasterize
from stgs.synth import SynthConfig, synthesize

SCENE = SynthConfig(grid_side=32, num_gops=2, gop_size=6, width=160, height=120, num_cameras=8, fit_steps=200,
                    effects=("rigid", "color", "view_dependent", "static_background"), static_grid_side=64)


def full_sh_image(s: Splats, cam: Camera) -> torch.Tensor:
    """The 3DGS image of `s` (its whole degree, colour clamped at 0 after the sum) by our splatter, with the
    model's guard band as every model render has it."""
    means = torch.from_numpy(s.means)
    d = s.means.astype(np.float64) - cam.center.double().numpy()
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    colours = torch.from_numpy(np.maximum(harmonics.evaluate(s.sh, d), 0).astype(np.float32))
    opacities = torch.sigmoid(torch.from_numpy(s.opacity_logits)) * in_guard_band(means, cam).float()
    return rasterize(means, torch.from_numpy(s.quats), torch.from_numpy(s.log_scales).exp(), opacities, colours,
                     cam.viewmat.float(), cam.K.float(), cam.width, cam.height)


def mean_psnr(layer, foreign: Splats, views: list[Camera]) -> float:
    """Mean PSNR of the folded layer against the file's full colour over `views`."""
    return float(np.mean([psnr(splat(layer.gaussians(c.center.float()), c), full_sh_image(foreign, c))
                          for c in views]))


def fold_rows(scene: Path, sigmas: list[float], seed: int) -> list[str]:
    source = open_source(scene)
    cams = open_dataset(scene, "synth").cameras(0)
    others = rig_orbit(cams, 12, cams[0].width, cams[0].height)
    base = from_static(source.static)
    rows = []
    rng = np.random.default_rng(seed)
    for sigma in sigmas:
        sh = np.zeros((base.count, 16, 3), dtype=np.float32)
        sh[:, 0] = base.sh[:, 0]
        sh[:, 1:] = rng.normal(0, sigma, (base.count, 15, 3)).astype(np.float32)
        foreign = Splats(base.means, base.log_scales, base.quats, base.opacity_logits, sh)
        for how, with_cams in (("dropped (no cameras)", None), ("fitted over the cameras", cams)):
            start = time.perf_counter()
            folded = fold_over(foreign, with_cams, None, "bench")
            seconds = time.perf_counter() - start
            layer = to_static(Splats(base.means, base.log_scales, base.quats, base.opacity_logits, folded))
            rows.append(f"| {sigma:g} | {how} | {mean_psnr(layer, foreign, cams):.2f} | "
                        f"{mean_psnr(layer, foreign, others):.2f} | "
                        f"{seconds / base.count * 1e6:.1f} |")
    return rows


def format_rows(scene: Path, work: Path) -> list[str]:
    source = open_source(scene)
    cam = open_dataset(scene, "synth").cameras(0)[1]
    k, i = divmod(7, source.gop_size)
    frame = FrameRenderer(source.gop(k), native=False, static=source.static).render(i, cam)
    exported = frame_splats(source, 7, cam.center)
    rows = []
    for fmt in ("ply", "glb", "spz"):
        start = time.perf_counter()
        size = write_splats(work / f"f.{fmt}", exported)
        back = read_splats(work / f"f.{fmt}")
        seconds = time.perf_counter() - start
        image = splat(to_static(back).gaussians(cam.center.float()), cam)
        exact = "yes" if torch.equal(image, frame) else f"no (max {float((image - frame).abs().max().detach()):.1e})"
        rows.append(f"| {fmt} | {size} | {size / exported.count:.1f} | {psnr(image, frame):.2f} | {exact} | "
                    f"{seconds * 1e3:.1f} |")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sigma", default="0.02,0.05,0.1", help="coefficient std of degrees 1-3, comma-separated")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.manual_seed(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        synthesize(dataclasses.replace(SCENE, seed=args.seed), scene, progress=False)
        print(f"Scene: {SCENE.static_grid_side ** 2} static + {SCENE.grid_side ** 2} dynamic Gaussians, "
              f"{SCENE.width}x{SCENE.height}, {SCENE.num_cameras} cameras, seed {args.seed}")
        print("\n| coefficient std | degrees 2-3 | PSNR at the cameras (dB) | PSNR on an orbit (dB) | "
              "fold µs / Gaussian |\n|---|---|---|---|---|")
        print("\n".join(fold_rows(scene, [float(s) for s in args.sigma.split(",")], args.seed)))
        print("\n| format | bytes | bytes / Gaussian | PSNR vs the frame (dB) | bit-exact | write + read ms |\n"
              "|---|---|---|---|---|---|")
        print("\n".join(format_rows(scene, Path(tmp))))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"\ncommit {commit}, {platform.processor() or platform.machine()}, torch {torch.__version__}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
