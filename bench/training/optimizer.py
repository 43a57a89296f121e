"""A/B of the GOP stage's Adam step: torch's fused CPU kernel (stgs.train.ops.Optimizer's) against its
per-parameter loop.

    python -m bench.training.optimizer --capacities 9216,16384 --steps 30
    python -m bench.training.optimizer --model MODEL_DIR --steps 40      # whole iterations on a trained model's GOP 0

Per capacity N: the parameter groups of a GOP model of N Gaussians (60-frame GOP, window 3: 62 × N × 16 temporal
features, the canonical attributes and the deformation field), as `Optimizer` builds them, with fixed random
gradients. Each implementation steps `steps` times from the same start; the median step is timed (the two
alternate, so the machine's drift hits both alike), and the parameters after the last step are compared (the
two differ by float32 rounding only). With --model: whole GOP-stage iterations on a trained model dir's GOP 0
(the deformation at one frame, the splat from one of its cameras, L1 + SSIM against a fixed target, the temporal
Huber term, the backward pass and the step), the two optimizers on two copies of the model,
alternating. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import torch

from bench import capacity_parser, ms_cell, print_capacity_table, torch_table_header
from stgs.camera import read_scene_cameras
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.renderer import splat
from stgs.model.store import load_gop, read_meta
from stgs.train import budget, losses
from stgs.train.ops import Optimizer


def measure(capacity: int, steps: int) -> str:
    torch.manual_seed(0)
    start = GOPModel(GOPShape(capacity, 60, 3))
    grads = [torch.randn_like(p) * 1e-3 for p in start.parameters()]
    cfg = budget("cpu")
    runs = {}
    for fused in (False, True):
        model = GOPModel(start.shape)
        model.load_state_dict(start.state_dict())
        for p, g in zip(model.parameters(), grads, strict=True):
            p.grad = g.clone()
        runs[fused] = (model, Optimizer(model, cfg, 1.0, None, fused=fused), [])
    for _ in range(steps):
        for _, opt, times in runs.values():
            begin = time.perf_counter()
            opt.opt.step()
            times.append(time.perf_counter() - begin)
    loop, fused = (runs[f] for f in (False, True))
    pairs = zip(loop[0].parameters(), fused[0].parameters(), strict=True)
    diff = max(float((a - b).detach().abs().max()) for a, b in pairs)
    ms = {f: 1000 * statistics.median(run[2]) for f, run in runs.items()}
    values = sum(p.numel() for p in start.parameters())
    return (f"| {capacity:,} | {values / 1e6:.1f} M | {ms_cell(ms[False])} | {ms_cell(ms[True])} | "
            f"{ms[True] / ms[False]:.2f} | {diff:.1e} |")


def measure_iterations(model_dir: Path, steps: int) -> str:
    meta = read_meta(model_dir)
    cams = read_scene_cameras(model_dir)
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(cams[0].height, cams[0].width, 3, generator=gen)
    runs = {}
    for fused in (False, True):
        model = load_gop(model_dir, meta, 0)
        runs[fused] = (model, Optimizer(model, budget("cpu"), 1.0, None, fused=fused), [], [])
    shape = meta.shape
    for it in range(steps + 2):
        frame, cam = it % shape.gop_size, cams[it % len(cams)]
        for model, opt, whole, step in runs.values():
            begin = time.perf_counter()
            image = splat(model.deform(frame, cam.center.float()), cam)
            loss = losses.photometric(image, target, 0.2) + losses.temporal_huber(model.features)
            opt.opt.zero_grad(set_to_none=True)
            loss.backward()
            stepping = time.perf_counter()
            opt.opt.step()
            end = time.perf_counter()
            if it >= 2:  # warm-up
                whole.append(end - begin)
                step.append(end - stepping)
    ms = {f: (1000 * statistics.median(r[2]), 1000 * statistics.median(r[3])) for f, r in runs.items()}
    return (f"| {model_dir.name} | {shape.capacity:,} | {ms_cell(ms[False][0])} ({ms_cell(ms[False][1])}) | "
            f"{ms_cell(ms[True][0])} ({ms_cell(ms[True][1])}) | {ms[True][0] / ms[False][0]:.2f} |")


def main() -> int:
    parser = capacity_parser(__doc__, "9216,16384")
    parser.add_argument("--model", type=Path, action="append", help="a trained model dir: time whole iterations")
    args = parser.parse_args()
    print(torch_table_header("training.optimizer"))
    if args.model:
        print("| scene | Gaussians N | iteration ms (of it the step), per-parameter loop | fused | fused / loop |")
        print("|---|---|---|---|---|")
        for model_dir in args.model:
            print(measure_iterations(model_dir, args.steps), flush=True)
        return 0
    return print_capacity_table(args, "| Gaussians N | parameters | Adam step ms, per-parameter loop | fused | "
                                f"fused / loop | largest parameter difference after {args.steps} steps |", measure)


if __name__ == "__main__":
    raise SystemExit(main())
