"""Splatter and deformation benchmark: accuracy vs time per backend (`stgs bench render`).

Scene: the procedural synthetic scene at N Gaussians seen from a ground-truth
camera, and a GOP model of the same N with random weights for `deform`.
Prints Markdown rows for docs/BENCHMARKS.md. Timings are medians of
`repeats` runs after one warm-up; compare ratios within one run.
"""

from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Callable

import torch

from stgs.camera import Camera, intrinsics, look_at
from stgs.metrics import psnr
from stgs.model.gop import GOPModel, GOPShape
from stgs.native.library import available
from stgs.render import rasterize
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.synth.scene import ProceduralScene

SLOW_MS = 2000.0
"""A first run slower than this counts as the measurement (no warm-up for the slow reference)."""


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Median milliseconds of fn over `repeats` runs (after a warm-up) and its last result."""
    start = time.perf_counter()
    result = fn()
    first_ms = (time.perf_counter() - start) * 1e3
    if first_ms > SLOW_MS:
        return first_ms, result
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), result


def bench_camera(width: int, height: int) -> Camera:
    return Camera("bench", intrinsics(width, height, 60.0),
                  look_at((0.0, 1.3, 2.6), (0.0, 0.5, 0.0)), width, height)


def scene_inputs(n: int, dtype: torch.dtype, cam: Camera) -> list[torch.Tensor]:
    truth = ProceduralScene(n, DEFAULT_EFFECTS, seed=0).at(0.5)
    args = [truth.means, truth.quats, truth.log_scales.exp(), truth.opacities,
            truth.colors(cam.center)]
    return [a.to(dtype) for a in args]


def splat_fn(args: list[torch.Tensor], cam: Camera, backend: str, backward: bool):
    dtype = args[0].dtype

    def run():
        params = [a.clone().requires_grad_(backward) for a in args]
        with torch.set_grad_enabled(backward):
            img = rasterize(*params, cam.viewmat.to(dtype), cam.K.to(dtype), cam.width, cam.height,
                            backend=backend)
            if backward:
                img.sum().backward()
        return img.detach()

    return run


def error_cells(img: torch.Tensor, ref64: torch.Tensor | None) -> str:
    """Max abs error and the share of pixels off by more than 1e-4 (isolated 1/255-threshold flips)."""
    if ref64 is None:
        return "- | -"
    diff = (img.double() - ref64).abs().amax(dim=-1)
    return f"{diff.max().item():.1e} | {(diff > 1e-4).double().mean().item() * 100:.4f} %"


def random_model(n: int) -> GOPModel:
    torch.manual_seed(0)
    model = GOPModel(GOPShape(capacity=n, gop_size=60))
    truth = ProceduralScene(n, DEFAULT_EFFECTS, seed=0).at(0.0)
    with torch.no_grad():
        for p in model.field.parameters():
            p.normal_(0, 0.05)
        model.features.normal_(0, 0.1)
    truth.copy_into(model, 1e-4)
    return model


def bench_size(n: int, width: int, height: int, repeats: int, reference_max: int) -> list[str]:
    cam = bench_camera(width, height)
    rows = []
    ref64 = None
    f64 = scene_inputs(n, torch.float64, cam)
    f32 = scene_inputs(n, torch.float32, cam)
    runs = [("reference", "fp64", f64), ("reference", "fp32", f32)]
    if available():
        runs.append(("native", "fp32", f32))
    for backend, precision, args in runs:
        if backend == "reference" and n > reference_max:
            rows.append(f"| {n} | {backend} {precision} | skipped (> --reference-max) | | | |")
            continue
        fwd_ms, img = timed(splat_fn(args, cam, backend, False), repeats)
        bwd_ms, _ = timed(splat_fn(args, cam, backend, True), max(1, repeats // 2))
        if ref64 is None and precision == "fp64":
            ref64 = img
        rows.append(f"| {n} | {backend} {precision} | {fwd_ms:.1f} | {bwd_ms:.1f} | {error_cells(img, ref64)} |")
    return rows


def deform_rows(n: int, width: int, height: int, repeats: int) -> list[str]:
    """Deformation alone and deformation + splat per precision; accuracy against the fp32 deformation's image."""
    from stgs.model.native_deform import bf16_backends, int16_kernel, runnable_precisions
    from stgs.model.renderer import FrameRenderer

    cam = bench_camera(width, height)
    model = random_model(n)
    center = cam.center.float()
    rows = []
    with torch.no_grad():
        torch_ms, _ = timed(lambda: model.deform(30, center), repeats)
        rows.append(f"| {n} | torch fp32 | {torch_ms:.1f} | | | |")
        if not available():
            return rows
        backends = bf16_backends()
        fp32_image = None
        for precision in runnable_precisions():
            renderer = FrameRenderer(model, precision=precision)
            deform_ms, _ = timed(lambda r=renderer: r.gaussians(30, cam), repeats)
            total_ms, image = timed(lambda r=renderer: r.render(30, cam), repeats)
            fp32_image = image if fp32_image is None else fp32_image
            accuracy = "(itself) | 0" if precision == "fp32" else \
                f"{psnr(image.clamp(0, 1), fp32_image.clamp(0, 1)):.1f} | {(image - fp32_image).abs().max().item():.1e}"
            kernel = {"bf16": backends[0] if backends else None, "int16": int16_kernel()}.get(precision)
            name = f"native {precision}" + (f" ({kernel})" if kernel else "")
            rows.append(f"| {n} | {name} | {deform_ms:.1f} | **{total_ms:.1f}** | {accuracy} |")
    return rows


def main(sizes: list[int], width: int, height: int, repeats: int, reference_max: int) -> int:
    print(f"<!-- stgs bench render: {width}x{height}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, {platform.processor() or platform.machine()} -->")
    print("| N | backend | forward ms | forward+backward ms | max abs error vs fp64 reference "
          "| pixels off by > 1e-4 |")
    print("|---|---|---|---|---|---|")
    for n in sizes:
        for row in bench_size(n, width, height, repeats, reference_max):
            print(row, flush=True)
    print()
    print("| N | deformation | deform ms | deform + splat ms | image PSNR vs fp32 deformation (dB) "
          "| max abs pixel error |")
    print("|---|---|---|---|---|---|")
    for n in sizes:
        for row in deform_rows(n, width, height, repeats):
            print(row, flush=True)
    return 0
