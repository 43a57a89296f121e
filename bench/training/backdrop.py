"""A/B of one layered GOP-stage training step drawn over the kept static layer (stgs.model.renderer.static_backdrops)
against one differentiable splat of both layers.

    python -m bench.training.backdrop --model MODEL_DIR --steps 20 --rounds 4

Per trained layered model dir (format 2; its cameras.json), GOP 0: each step deforms the dynamic layer with
gradients at one (frame, camera) pair, draws it with the frozen static layer, and back-propagates the
photometric loss (L1 + SSIM) against a fixed target (the model's own frame, brightened: the cost does not
depend on what the target shows), as stage B does. "one splat": `splat` of both layers (the trainer's path
before the kept layer); "kept": `splat_over` a backdrop kept per camera. The two alternate in each round, on the
same pairs, so that the machine's drift hits both alike; every kept step of the first round is checked against
the one-splat step (`same_step`: the image and the gradients of the dynamic layer's colours, equal up to the
float32 rounding of the kept layer's native projection). Also printed: the share of tiles the dynamic layer
reaches, which bounds what the kept layer saves. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import time
from pathlib import Path

import torch

from bench import ms_cell
from stgs.camera import read_scene_cameras
from stgs.model.renderer import guarded_opacities, splat_over, static_backdrops, static_view
from stgs.model.store import load_gop, load_static, read_meta
from stgs.render.native import bin_native, f32
from stgs.render.project import project
from stgs.train import losses


def reached_share(g, cam) -> float:
    """Share of the image's tiles that a guarded Gaussian of g reaches."""
    opacities = guarded_opacities(g, cam).detach()
    p = project(g.means.detach().double(), g.quats.detach().double(), g.scales.detach().double(), opacities,
                cam.viewmat, cam.K)
    bins = bin_native(*(f32(t) for t in (p.means2d, p.conics, opacities, p.depths, p.extents)), cam.width,
                      cam.height).bins()
    return float((bins.tile_start[1:] > bins.tile_start[:-1]).float().mean())


def same_step(image: torch.Tensor, grad: torch.Tensor, twin_image: torch.Tensor, twin_grad: torch.Tensor) -> bool:
    """Whether two steps drew the same image and gradients up to float32 rounding. The kept layer is projected
    natively and its copied tiles come from the inference kernel: a static Gaussian whose alpha sits at the 1/255
    cut can be in one image and not the other (measured on Panoptic: at most 0.015 % of the values, by at most
    1e-3); the gradients of the dynamic layer agreed to 1e-9 of their norm."""
    differs = (image - twin_image).abs()
    return bool(differs.max() < 1e-2 and (differs > 1e-5).float().mean() < 1e-3
                and (grad - twin_grad).norm() <= 1e-3 * twin_grad.norm())


def measure(model_dir: Path, steps: int, rounds: int) -> str:
    meta = read_meta(model_dir)
    static = load_static(model_dir, meta)
    if static is None:
        raise SystemExit(f"{model_dir} has no static layer (format 1)")
    model = load_gop(model_dir, meta, 0)
    cams = read_scene_cameras(model_dir)
    start = time.perf_counter()
    kept = static_backdrops(static, cams)
    keep_ms = (time.perf_counter() - start) * 1e3 / len(cams)
    plain = [static_view(static, cam) for cam in cams]
    gen = torch.Generator().manual_seed(0)
    pairs = [(int(torch.randint(meta.shape.gop_size, (1,), generator=gen)),
              int(torch.randint(len(cams), (1,), generator=gen))) for _ in range(steps)]
    with torch.no_grad():
        targets = {p: (splat_over(kept[p[1]], model.deform(p[0], cams[p[1]].center.float()), cams[p[1]]) * 1.1 + 0.02)
                   .clamp(0, 1) for p in pairs}

    def step(backdrops, f: int, c: int) -> tuple[torch.Tensor, torch.Tensor]:
        model.zero_grad(set_to_none=True)
        g = model.deform(f, cams[c].center.float())
        image = splat_over(backdrops[c], g, cams[c])
        losses.photometric(image, targets[f, c], 0.2).backward()
        return image.detach(), model.color.grad.clone()

    step(plain, *pairs[0])
    times: dict[str, list[float]] = {"plain": [], "kept": []}
    for r in range(rounds):
        for name in ("plain", "kept") if r % 2 == 0 else ("kept", "plain"):
            for f, c in pairs:
                began = time.perf_counter()
                image, grad = step(plain if name == "plain" else kept, f, c)
                times[name].append((time.perf_counter() - began) * 1e3)
                if name == "kept" and r == 0:
                    twin_image, twin_grad = step(plain, f, c)
                    if not same_step(image, grad, twin_image, twin_grad):
                        raise SystemExit(f"{model_dir.name} frame {f} camera {cams[c].name}: the kept layer "
                                         "changed the image or the gradients")
    with torch.no_grad():
        shares = [reached_share(model.deform(f, cams[c].center.float()), cams[c]) for f, c in pairs]
    med = {k: statistics.median(v) for k, v in times.items()}
    return (f"| {model_dir.name} | {meta.static.capacity:,} + {meta.shape.capacity:,} | "
            f"{100 * statistics.mean(shares):.0f} % ({100 * min(shares):.0f}–{100 * max(shares):.0f} %) | "
            f"{ms_cell(med['plain'])} | {ms_cell(med['kept'])} | {med['kept'] / med['plain']:.2f} | "
            f"{ms_cell(keep_ms)} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="a trained layered model dir")
    parser.add_argument("--steps", type=int, default=20, help="(frame, camera) pairs per round")
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"<!-- python -m bench.training.backdrop, {platform.processor() or platform.machine()}, "
          f"torch threads {torch.get_num_threads()}, commit {commit} -->")
    print("| scene | Gaussians static + dynamic | tiles the dynamic layer reaches, mean (range) | step ms, one splat | "
          "step ms, static layer kept | kept / one splat | keeping the layer, ms per camera |")
    print("|---|---|---|---|---|---|---|")
    for model in args.model:
        print(measure(model, args.steps, args.rounds), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
