"""The auto ladder: how many frames a rung's quality needs, and what the auto ladder costs and chooses against the
fixed one (`python -m bench.packaging.ladder --model DIR [--model DIR ...]`, prints Markdown for docs/BENCHMARKS.md,
"Packaging: the auto ladder").

`--frames`: per model, GOP 0 is encoded at every candidate point of both codecs, and every frame of the GOP is
rendered at the pack's quality cameras (stgs.packager.segments.quality_views). Per sample size n, the rendered PSNR
of n frames spread evenly (first and last included, as the packer picks them) is set against that of every frame:
the largest and the mean |difference| over the candidates.

`--compare`: per model, `stgs pack` with the fixed ladder and with the auto ladder, each timed alone (one after
the other, `--jobs` encoders); the auto pack's candidates (pairs of a feature point and a keyframe rung), bytes and
rendered PSNR with the rungs it kept, as a table and, with `--plot`, a rate-quality plot (a curve per codec and
keyframe rung).
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import torch

from stgs.codec.video import decode_segment
from stgs.metrics import mse_psnr
from stgs.packager import pack
from stgs.packager.packer import PackConfig, Packer
from stgs.packager.segments import view_errors
from stgs.picks import spread

SAMPLES = (3, 5, 8, 12, 20, 30)
"""Frames per GOP the --frames check tries (those above the GOP's size are skipped)."""


def frame_rows(model_dir: Path, samples: tuple[int, ...]) -> tuple[dict, list[dict]]:
    """GOP 0 at every candidate point: per sample size, the largest and mean |PSNR(sample) - PSNR(every frame)|."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = PackConfig(stats_frames=None, jobs=1)  # every frame of the GOP
        packer = Packer(model_dir, Path(tmp) / "dash", cfg, progress=False)
        shape, side = packer.meta.shape, packer.side
        gop = packer.prepare_gop(0)
        frames_of = [f for f, _ in gop.views]
        per_point = {}
        for codec, q in cfg.encodes():
            init, media = packer.encoder.encode(0, codec, q, gop.frames[codec.bits])
            decoded = decode_segment(init, media, shape.num_features, 4 * side, 4 * side, codec=codec)
            errors = view_errors(gop, decoded, codec.bits, packer.static)
            per_frame = {}
            for f, e in zip(frames_of, errors, strict=True):
                per_frame.setdefault(f, []).append(e)
            per_point[codec.rep_id(q)] = per_frame
    g = shape.gop_size
    info = {"model": model_dir.name, "gop_size": g, "cameras": len(gop.views) // g, "points": len(per_point)}
    rows = []
    for n in (s for s in samples if s <= g):
        picked = spread(list(range(g)), n)
        diffs = []
        for per_frame in per_point.values():
            every = mse_psnr([e for f in range(g) for e in per_frame[f]])
            diffs.append(mse_psnr([e for f in picked for e in per_frame[f]]) - every)
        rows.append({"frames": n, "max_abs_db": max(abs(d) for d in diffs),
                     "mean_abs_db": sum(abs(d) for d in diffs) / len(diffs)})
    return info, rows


def compare(model_dir: Path, jobs: int, work: Path) -> dict:
    """The fixed and the auto pack of one model, timed, and the auto ladder's candidates."""
    out = {}
    for ladder in ("fixed", "auto"):
        start = time.perf_counter()
        stats = pack(model_dir, work / f"{model_dir.name}-{ladder}", PackConfig(ladder=ladder, jobs=jobs),
                     progress=False)
        out[ladder] = {"seconds": time.perf_counter() - start, "stats": stats}
    return out


def plot(results: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4.2), squeeze=False)
    for ax, (name, result) in zip(axes[0], results.items(), strict=True):
        stats = result["auto"]["stats"]
        seconds = stats["segment_seconds"] * len(stats["gops"])
        measure = "render_psnr"
        for codec, ladder in stats["ladders"].items():
            cands, measure = ladder["candidates"], ladder["measure"]
            for kf in sorted({c.get("keyframes", "keyframes") for c in cands}):  # one curve per keyframe rung
                curve = [c for c in cands if c.get("keyframes", "keyframes") == kf]
                ax.plot([c["total_bytes"] * 8 / seconds / 1e3 for c in curve], [c[measure] for c in curve], "o-",
                        alpha=0.4, markersize=4, label=f"{codec}, {kf}")
            kept = [(c["total_bytes"] * 8 / seconds / 1e3, c[measure]) for c in cands if c["kept"]]
            ax.plot(*zip(*kept, strict=True), "s", markersize=9, label=f"{codec} rungs kept")
        for codec, ladder in result["fixed"]["stats"]["ladders"].items():
            cands = ladder["candidates"]
            ax.plot([c["total_bytes"] * 8 / seconds / 1e3 for c in cands], [c[measure] for c in cands], "x",
                    markersize=8, label=f"{codec} fixed ladder")
        ax.set_xscale("log")
        ax.set_xlabel("keyframes + features, kbit/s")
        ax.set_ylabel("PSNR vs the capture (estimated), dB" if measure == "truth_psnr"
                      else "rendered PSNR vs the uncompressed model, dB")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="model dir (repeatable)")
    parser.add_argument("--frames", action="store_true", help="how many frames per GOP a rung's PSNR needs")
    parser.add_argument("--samples", default=",".join(map(str, SAMPLES)), help="frames per GOP to try (--frames)")
    parser.add_argument("--compare", action="store_true", help="the fixed ladder against the auto ladder")
    parser.add_argument("--jobs", type=int, default=2, help="parallel encodes (--compare; default: 2)")
    parser.add_argument("--plot", type=Path, help="rate-quality plot (--compare)")
    parser.add_argument("--work", type=Path, help="keep the packed trees here (--compare; default: a temp folder)")
    args = parser.parse_args(argv)
    print(f"<!-- python -m bench.packaging.ladder ({platform.processor() or platform.machine()}), "
          f"{torch.get_num_threads()} threads -->")
    if args.frames:
        samples = tuple(int(s) for s in args.samples.split(","))
        print("| scene | GOP frames | cameras | candidates | frames rendered | max \\|Δ\\| dB | mean \\|Δ\\| dB |")
        print("|---|---|---|---|---|---|---|")
        for model_dir in args.model:
            info, rows = frame_rows(model_dir, samples)
            for r in rows:
                print(f"| {info['model']} | {info['gop_size']} | {info['cameras']} | {info['points']} "
                      f"| {r['frames']} | {r['max_abs_db']:.3f} | {r['mean_abs_db']:.3f} |", flush=True)
    if args.compare:
        results = {}
        with tempfile.TemporaryDirectory() as tmp:
            work = args.work or Path(tmp)
            for model_dir in args.model:
                results[model_dir.name] = compare(model_dir, args.jobs, work)
        print("\n| scene | ladder | pack s | ratio |\n|---|---|---|---|")
        for name, r in results.items():
            for ladder in ("fixed", "auto"):
                print(f"| {name} | {ladder} | {r[ladder]['seconds']:.1f} "
                      f"| {r[ladder]['seconds'] / r['fixed']['seconds']:.2f} |")
        print("\n| scene | codec | candidate | features kbit/s | with keyframes | dB vs model | dB vs capture (est.) "
              "| kept | why |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, r in results.items():
            stats = r["auto"]["stats"]
            seconds = stats["segment_seconds"] * len(stats["gops"])
            for codec, ladder in stats["ladders"].items():
                for c in ladder["candidates"]:
                    truth = f"{c['truth_psnr']:.2f}" if "truth_psnr" in c else "–"
                    print(f"| {name} | {codec} | {c['representation']} | {c['bytes'] * 8 / seconds / 1e3:,.0f} "
                          f"| {c['total_bytes'] * 8 / seconds / 1e3:,.0f} | {c['render_psnr']:.2f} | {truth} "
                          f"| {'**yes**' if c['kept'] else 'no'} | {c['reason']} |")
            print(f"| {name} | | per-GOP ladders would save | "
                  + ", ".join(f"{codec} {ladder['per_gop_saving']:.1%}" for codec, ladder in stats["ladders"].items())
                  + " | | | | | |")
        if args.plot:
            plot(results, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
