"""A/B of the GOP stage's feature terms: the frame's window and the temporal Huber term over all Gaussians in native
kernels with one gradient buffer (stgs.train.losses.window_and_temporal_huber, what the trainer runs), the torch
term with its hand-written backward (stgs.train.losses.temporal_huber) beside autograd's slice of the window, autograd
through torch's huber_loss, and the sampled gather the trainer used before those (8,192 random Gaussians per
iteration, or N where smaller).

    python -m bench.training.temporal --capacities 9216,16384,65536 --steps 30

Per capacity N: the (62, N, 16) temporal features of a 60-frame GOP (window 3) and one iteration's feature terms,
as stgs.train.objective draws them: the frame's window through a stand-in linear layer, the smoothness of the
frame's feature grid, and the temporal term. The variants alternate (the machine's drift hits them alike); the
median forward + backward is timed. The gradients of the hand-written backward and of the native terms are compared
with autograd's on the same features. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable

import torch

from bench import capacity_parser, ms_cell, print_capacity_table, torch_table_header
from stgs.memory import reuse_large_allocations
from stgs.model.gop import flat_window
from stgs.train import losses

FRAMES, WINDOW, CHANNELS, DELTA, SAMPLE = 62, 3, 16, 0.01, 8192


def autograd_huber(features: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.huber_loss(features[1:], features[:-1], delta=DELTA)


def variants(features: torch.Tensor, gen: torch.Generator) -> dict[str, Callable[[], torch.Tensor]]:
    side = math.isqrt(features.shape[1])
    weight = torch.randn(WINDOW * CHANNELS, 64, generator=gen)

    def iteration(terms: Callable[[int], tuple[torch.Tensor, torch.Tensor]]) -> Callable[[], torch.Tensor]:
        """One iteration's feature terms; `terms(i)` gives the window's block and the temporal term."""
        def run() -> torch.Tensor:
            i = int(torch.randint(FRAMES - WINDOW + 1, (1,), generator=gen))
            block, temporal = terms(i)
            loss = (flat_window(block) @ weight).square().mean()
            return loss + temporal + 0.01 * losses.grid_smoothness(block[0], side)
        return run

    def sliced(temporal: Callable[[], torch.Tensor]) -> Callable[[int], tuple[torch.Tensor, torch.Tensor]]:
        return lambda i: (features[i:i + WINDOW], temporal())

    def sampled() -> torch.Tensor:
        idx = torch.randint(features.shape[1], (min(SAMPLE, features.shape[1]),), generator=gen)
        return autograd_huber(features[:, idx])

    return {"sampled": iteration(sliced(sampled)), "autograd": iteration(sliced(lambda: autograd_huber(features))),
            "hand": iteration(sliced(lambda: losses.temporal_huber(features, DELTA))),
            "native": iteration(lambda i: losses.window_and_temporal_huber(features, i, WINDOW, DELTA))}


def measure(capacity: int, steps: int) -> str:
    gen = torch.Generator().manual_seed(0)
    features = torch.nn.Parameter((torch.rand(FRAMES, capacity, CHANNELS, generator=gen) * 0.02).cumsum(0))
    (expected,) = torch.autograd.grad(autograd_huber(features), features)
    (hand,) = torch.autograd.grad(losses.temporal_huber(features, DELTA), features)
    (native,) = torch.autograd.grad(losses.window_and_temporal_huber(features, 0, WINDOW, DELTA)[1], features)
    diff = max(float((got - expected).abs().max()) for got in (hand, native))
    runs = variants(features, gen)
    times: dict[str, list[float]] = {name: [] for name in runs}
    for it in range(steps + 2):
        for name, run in runs.items():
            features.grad = None
            begin = time.perf_counter()
            run().backward()
            if it >= 2:  # warm-up: the allocator's first large buffers
                times[name].append(time.perf_counter() - begin)
    ms = {name: 1000 * statistics.median(t) for name, t in times.items()}
    return (f"| {capacity:,} | {ms_cell(ms['sampled'])} | {ms_cell(ms['autograd'])} | {ms_cell(ms['hand'])} | "
            f"{ms_cell(ms['native'])} | {ms['native'] / ms['hand']:.2f} | {diff:.1e} |")


def main() -> int:
    parser = capacity_parser(__doc__, "9216,16384,65536")
    args = parser.parse_args()
    reuse_large_allocations()  # as the trainer does
    print(torch_table_header("training.temporal"))
    return print_capacity_table(args, f"| Gaussians N | feature terms ms, Huber on {SAMPLE:,} sampled (autograd) | "
                                "all, autograd | all, hand-written backward | all, native, one buffer | "
                                "native / hand | largest gradient difference to autograd |", measure)


if __name__ == "__main__":
    raise SystemExit(main())
