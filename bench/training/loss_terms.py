"""A/B of a splat training step's image-sized and per-Gaussian parts outside the rasteriser: the SSIM term
(autograd through depthwise convolutions, the written-out backward in torch, the native kernel of
csrc/ssim.cpp), the masked photometric term (boolean indexing against a weighted sum), and the projection with
gradients (autograd through the float64 torch projection against csrc/project.cpp's backward).

    python -m bench.training.loss_terms --capacities 9216,16384,25600 --steps 30

Images are 640x360 (Panoptic's training size), random, with a mask of nine-tenths of the pixels; the projection
runs random Gaussians through one camera, with random upstream gradients (none for the culled ones, as the
rasteriser gives). The variants of each row alternate (the machine's drift hits them
alike); medians of forward + backward. Each row's last cell is the largest difference of the variants' outputs
and gradients from the first variant's. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch

from bench import capacity_parser, ms_cell, torch_table_header
from stgs.memory import reuse_large_allocations
from stgs.metrics import _ssim_parts, ssim_map
from stgs.render.native import project_trainable
from stgs.render.project import project
from stgs.train import losses

WIDTH, HEIGHT = 640, 360


def alternate(runs: dict[str, Callable[[], None]], steps: int) -> dict[str, float]:
    """Median ms of each run, the runs taking turns; two warm-up rounds (the allocator's first large buffers)."""
    times: dict[str, list[float]] = {name: [] for name in runs}
    for it in range(steps + 2):
        for name, run in runs.items():
            begin = time.perf_counter()
            run()
            if it >= 2:
                times[name].append(time.perf_counter() - begin)
    return {name: 1000 * statistics.median(t) for name, t in times.items()}


def largest_difference(outputs: dict[str, list[torch.Tensor]]) -> float:
    first, *others = outputs.values()
    return max(float((a.double() - b.double()).abs().max()) for other in others for a, b in zip(first, other,
                                                                                                 strict=True))


def image_rows(steps: int) -> list[str]:
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(HEIGHT, WIDTH, 3, generator=gen).requires_grad_()
    target = (image.detach() + 0.1 * torch.randn(HEIGHT, WIDTH, 3, generator=gen)).clamp(0, 1)
    mask = torch.rand(HEIGHT, WIDTH, generator=gen) > 0.1

    def autograd_ssim() -> torch.Tensor:
        return _ssim_parts(image.permute(2, 0, 1), target.permute(2, 0, 1))[0].mean(0)

    def indexed_loss() -> torch.Tensor:
        values = ssim_map(image, target)
        return 0.8 * (image - target).abs()[mask].mean() + 0.2 * (1 - values[mask].mean())

    ssims = {"autograd": autograd_ssim, "torch": lambda: ssim_map(image, target, backend="torch"),
             "native": lambda: ssim_map(image, target)}
    masked = {"indexed": indexed_loss, "weighted": lambda: losses.photometric(image, target, 0.2, mask)}
    rows = []
    for label, variants in (("SSIM map, fwd + bwd: autograd / written-out torch / native", ssims),
                            ("masked L1 + SSIM term (native SSIM): boolean indexing / weighted sum", masked)):
        outputs = {}
        for name, fn in variants.items():
            image.grad = None
            out = fn()
            out.mean().backward()
            outputs[name] = [out.detach().clone(), image.grad.clone()]

        def timed(fn: Callable[[], torch.Tensor]) -> Callable[[], None]:
            def run() -> None:
                image.grad = None
                fn().mean().backward()
            return run

        ms = alternate({name: timed(fn) for name, fn in variants.items()}, steps)
        cells = " / ".join(ms_cell(v) for v in ms.values())
        rows.append(f"| {label} | {WIDTH}x{HEIGHT} | {cells} | {min(ms.values()) / max(ms.values()):.2f} | "
                    f"{largest_difference(outputs):.1e} |")
    return rows


def projection_row(capacity: int, steps: int) -> str:
    gen = torch.Generator().manual_seed(capacity)
    means = torch.randn(capacity, 3, generator=gen) * 1.5
    means[:, 2] += 6.0
    inputs = [means, torch.randn(capacity, 4, generator=gen), torch.rand(capacity, 3, generator=gen) * 0.05]
    opacities = torch.rand(capacity, generator=gen)
    view = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[500.0, 0, WIDTH / 2], [0, 500.0, HEIGHT / 2], [0, 0, 1]], dtype=torch.float64)
    grad_xy, grad_conic = torch.randn(capacity, 2, generator=gen), torch.randn(capacity, 3, generator=gen)
    culled = project(means.double(), inputs[1].double(), inputs[2].double(), opacities, view, K).depths < 0
    grad_xy[culled] = grad_conic[culled] = 0.0  # as the rasteriser's: a culled Gaussian is never drawn
    params = [t.clone().requires_grad_() for t in inputs]

    def torch_projection() -> list[torch.Tensor]:
        p = project(*(t.double() for t in params), opacities, view, K)
        return [p.means2d.float(), p.conics.float()]

    def native_projection() -> list[torch.Tensor]:
        p = project_trainable(*params, opacities, view, K)
        return [p.means2d, p.conics]

    variants = {"torch": torch_projection, "native": native_projection}

    def backward(outs: list[torch.Tensor]) -> None:
        ((outs[0] * grad_xy).sum() + (outs[1] * grad_conic).sum()).backward()

    outputs = {}
    for name, fn in variants.items():
        for p in params:
            p.grad = None
        outs = fn()
        backward(outs)
        outputs[name] = [o.detach() for o in outs] + [p.grad.clone() for p in params]
    scale = max(float(o.abs().max()) for o in outputs["torch"])

    def timed(fn: Callable[[], list[torch.Tensor]]) -> Callable[[], None]:
        def run() -> None:
            for p in params:
                p.grad = None
            backward(fn())
        return run

    ms = alternate({name: timed(fn) for name, fn in variants.items()}, steps)
    return (f"| projection, fwd + bwd: torch float64 / native | {capacity:,} Gaussians | {ms_cell(ms['torch'])} / "
            f"{ms_cell(ms['native'])} | {ms['native'] / ms['torch']:.2f} | "
            f"{largest_difference(outputs) / scale:.1e} (relative) |")


def main() -> int:
    parser = capacity_parser(__doc__, "9216,16384,25600")
    args = parser.parse_args()
    reuse_large_allocations()  # as the trainer does
    print(torch_table_header("training.loss_terms"))
    print("| part | size | ms per variant | fastest / slowest | largest difference from the first |")
    print("|---|---|---|---|---|")
    for row in image_rows(args.steps):
        print(row, flush=True)
    for n in args.capacities.split(","):
        print(projection_row(int(n), args.steps), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
