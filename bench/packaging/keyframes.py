"""Keyframe rungs: what each keyframe attribute tolerates, and what the keyframe rungs cost and keep
(`python -m bench.packaging.keyframes --model DIR [--model DIR ...]`, prints Markdown for docs/BENCHMARKS.md,
"Packaging: keyframe rungs").

Per model, GOP 0 is prepared as `stgs pack` prepares it (PLAS-sorted, its reference views rendered from the
uncompressed GOP at the pack's quality cameras, every frame) and its features are taken at 12 bits, so that only the
keyframe differs from the reference. `--sensitivity`: each attribute image in turn is quantised to fewer bits (the
weights: per-row codes, stgs.codec.keyframe.quantize_weight), the others staying lossless; per step its JPEG XL
bytes and the rendered PSNR against the uncompressed model. `--rungs`: each keyframe rung of
stgs.codec.quant.KEYFRAME_RUNGS encoded and decoded as a player does; its bytes, encode and decode time, rendered
PSNR and, where the model dir tells its own error, the PSNR against the capture.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from stgs.codec.attributes import SPECS, attribute_range, dequantize, quantize
from stgs.codec.features import features_from_frames
from stgs.codec.jxl import encode_jxl
from stgs.codec.keyframe import Keyframe, decode_keyframe, dequantize_weight, encode_keyframe, quantize_weight
from stgs.codec.quant import KEYFRAME_RUNGS, LOSSLESS
from stgs.metrics import mse_psnr
from stgs.model.renderer import FrameRenderer
from stgs.packager.packer import PackConfig, Packer
from stgs.packager.segments import PreparedGOP

FIELD_BITS = (8, 6, 5, 4)
"""Weight bits the sensitivity study tries."""


def prepared(model_dir: Path, frames: int | None) -> tuple[Packer, PreparedGOP, torch.Tensor]:
    """GOP 0 prepared as a pack does, and its 12-bit features as a player decodes them."""
    packer = Packer(model_dir, Path(tempfile.mkdtemp()) / "dash", PackConfig(stats_frames=frames, jobs=1),
                    progress=False)
    gop = packer.prepare_gop(0)
    return packer, gop, features_from_frames(gop.frames[12], packer.side, gop.ranges, 12)


def render_error(packer: Packer, gop: PreparedGOP, keyframe: Keyframe, features: torch.Tensor) -> float:
    """Mean squared error of the GOP's reference views rendered with `keyframe`."""
    renderer = FrameRenderer(keyframe.to_model(features), static=packer.static)
    errors = [(renderer.render(f, cam).clamp(0, 1).double() - ref.double()).square().mean().item()
              for (f, cam), ref in zip(gop.views, gop.reference, strict=True)]
    return sum(errors) / len(errors)


def sensitivity(model_dir: Path, frames: int | None) -> list[dict]:
    packer, gop, features = prepared(model_dir, frames)
    kf, side = gop.decoded_keyframe, packer.side
    rows = []
    for spec in SPECS:
        values = kf.attributes[spec.name]
        rng = attribute_range(spec, values)
        full = spec.levels.bit_length() - 1
        for bits in range(full, 2, -1 if full < 9 else -2):
            coarse = replace(spec, levels=1 << bits)
            codes = quantize(coarse, values, rng, side)
            lossy = replace(kf, attributes=kf.attributes | {spec.name: dequantize(coarse, codes, rng)})
            rows.append({"model": model_dir.name, "image": spec.name, "bits": bits, "bytes": len(encode_jxl(codes)),
                         "render_psnr": mse_psnr([render_error(packer, gop, lossy, features)])})
    float_bytes = sum(w.numel() * 4 for w in kf.field.values())
    rows.append({"model": model_dir.name, "image": "field", "bits": 32, "bytes": float_bytes,
                 "render_psnr": mse_psnr([render_error(packer, gop, kf, features)])})
    for bits in FIELD_BITS:
        field, nbytes = {}, 0
        for name, weight in kf.field.items():
            codes, rng = quantize_weight(weight, bits)
            nbytes += len(encode_jxl(codes)) + rng.numel() * 4
            field[name] = dequantize_weight(codes, rng, bits)
        rows.append({"model": model_dir.name, "image": "field", "bits": bits, "bytes": nbytes,
                     "render_psnr": mse_psnr([render_error(packer, gop, replace(kf, field=field), features)])})
    return rows


def rungs(model_dir: Path, frames: int | None) -> list[dict]:
    packer, gop, features = prepared(model_dir, frames)
    model = gop.decoded_keyframe.to_model(features)
    rows = []
    for name, quant in KEYFRAME_RUNGS.items():
        start = time.perf_counter()
        data = encode_keyframe(0, model, gop.ranges, quant)
        encode_s = time.perf_counter() - start
        start = time.perf_counter()
        kf = decode_keyframe(data, packer.meta.shape, 0, len(data), quant)
        decode_s = time.perf_counter() - start
        mse = render_error(packer, gop, kf, features)
        row = {"model": model_dir.name, "rung": name, "quant": quant.value, "bytes": len(data),
               "kbps": len(data) * 8 / packer.seconds_per_gop / 1e3, "encode_s": encode_s, "decode_s": decode_s,
               "render_psnr": mse_psnr([mse])}
        if gop.model_mse is not None:
            row["truth_psnr"] = mse_psnr([gop.model_mse + mse])
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="model dir (repeatable)")
    parser.add_argument("--sensitivity", action="store_true", help="each image's bits against rendered PSNR")
    parser.add_argument("--rungs", action="store_true", help="the keyframe rungs' bytes, time and PSNR")
    parser.add_argument("--frames", type=int, help="frames per GOP rendered (default: every frame)")
    args = parser.parse_args(argv)
    print(f"<!-- python -m bench.packaging.keyframes ({platform.processor() or platform.machine()}), "
          f"frames per GOP: {args.frames or 'all'} -->")
    if args.sensitivity:
        print("| model | image | bits | bytes | rendered PSNR (dB) |\n|---|---|---|---|---|")
        for model in args.model:
            for r in sensitivity(model, args.frames):
                lossless = r["bits"] == (32 if r["image"] == "field" else getattr(LOSSLESS, r["image"]))
                print(f"| {r['model']} | {r['image']} | {r['bits']}{' (lossless)' if lossless else ''} | "
                      f"{r['bytes']:,} | {r['render_psnr']:.2f} |", flush=True)
    if args.rungs:
        print("\n| model | rung | quant | bytes | kbit/s | encode s | decode s | rendered PSNR (dB) "
              "| vs capture (dB) |\n|---|---|---|---|---|---|---|---|---|")
        for model in args.model:
            for r in rungs(model, args.frames):
                truth = f"{r['truth_psnr']:.2f}" if "truth_psnr" in r else "–"
                print(f"| {r['model']} | {r['rung']} | `{r['quant']}` | {r['bytes']:,} | {r['kbps']:.0f} | "
                      f"{r['encode_s']:.2f} | {r['decode_s']:.2f} | {r['render_psnr']:.2f} | {truth} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
