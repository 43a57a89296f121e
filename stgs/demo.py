"""`stgs demo`: the end-to-end path that exists so far, on the embedded default scene.

Synthesise the default scene (preset "demo"), render a free-viewpoint orbit
from the fitted model, and write the frames, a contact sheet and a
truth | model | error comparison, printing the model's fidelity.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

from stgs.camera import Camera, intrinsics, look_at
from stgs.fsio import atomic_write_bytes, load_png, save_png
from stgs.model.store import load_model
from stgs.model.view import FrameRenderer
from stgs.native.build import available
from stgs.synth import GROUND_TRUTH_DIR, PRESETS, SCENE_TARGET, load_ground_truth, synthesize

SHEET_COLUMNS = 6


def orbit_camera(frame: int, frames: int, width: int, height: int) -> Camera:
    """A camera that circles the scene once over the whole playback."""
    angle = 2 * math.pi * frame / frames
    eye = (3.0 * math.sin(angle), 1.2 + 0.3 * math.sin(2 * angle), 3.0 * math.cos(angle))
    return Camera(f"orbit{frame:05d}", intrinsics(width, height, 60.0), look_at(eye, SCENE_TARGET),
                  width, height)


def grid(images: list[torch.Tensor], columns: int) -> torch.Tensor:
    """Tile equally sized (H, W, 3) images row-major, padding the last row with black."""
    h, w, _ = images[0].shape
    rows = math.ceil(len(images) / columns)
    sheet = torch.zeros(rows * h, columns * w, 3)
    for i, img in enumerate(images):
        r, c = divmod(i, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = img
    return sheet


def run(out: Path, progress: bool = True) -> int:
    out = Path(out)
    cfg = PRESETS["demo"]
    print(f"stgs demo: native kernels {'on' if available() else 'OFF (pure-torch reference)'}")
    start = time.perf_counter()
    report = synthesize(cfg, out / "model", progress=progress)
    synth_s = time.perf_counter() - start
    meta, gops = load_model(out / "model")
    renderers = [FrameRenderer(g) for g in gops]
    frames = meta.num_frames
    orbit_frames, times = [], []
    for f in tqdm(range(frames), desc="render orbit", unit="frame", disable=not progress):
        gop, local = divmod(f, meta.shape.gop_size)
        cam = orbit_camera(f, frames, cfg.width, cfg.height)
        t0 = time.perf_counter()
        image = renderers[gop].render(local, cam).clamp(0, 1)
        times.append(time.perf_counter() - t0)
        save_png(out / "frames" / f"{f:05d}.png", image)
        orbit_frames.append(image)
    step = max(1, frames // (2 * SHEET_COLUMNS))
    save_png(out / "contact_sheet.png", grid(orbit_frames[::step][:2 * SHEET_COLUMNS], SHEET_COLUMNS))
    doc, cameras = load_ground_truth(out / "model")
    compare = []
    for f in range(0, frames, max(1, frames // 4))[:4]:
        gop, local = divmod(f, meta.shape.gop_size)
        truth = load_png(out / "model" / GROUND_TRUTH_DIR / doc["pattern"].format(camera=cameras[0].name, frame=f))
        model = renderers[gop].render(local, cameras[0]).clamp(0, 1)
        compare += [truth, model, ((model - truth).abs() * 10).clamp(0, 1)]
    save_png(out / "compare.png", grid(compare, 3))
    ms = sorted(t * 1e3 for t in times)
    summary = {"gaussians": meta.shape.capacity, "gops": meta.num_gops, "frames": frames,
               "resolution": [cfg.width, cfg.height], "fidelity_psnr_db": report.fidelity_psnr,
               "fidelity_views": report.fidelity_views, "synth_seconds": synth_s,
               "render_ms_median": ms[len(ms) // 2], "render_fps": 1e3 / ms[len(ms) // 2]}
    atomic_write_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    print(f"model: {meta.shape.capacity} Gaussians, {meta.num_gops} GOPs x {meta.shape.gop_size} "
          f"frames at {meta.fps:g} fps ({cfg.width}x{cfg.height})")
    print(f"fidelity vs ground truth: {report.fidelity_psnr:.2f} dB PSNR over {report.fidelity_views} views")
    print(f"render (deform + splat): {summary['render_ms_median']:.1f} ms/frame median "
          f"({summary['render_fps']:.0f} fps)")
    print(f"wrote {out / 'frames'}/ ({frames} PNG), {out / 'contact_sheet.png'}, "
          f"{out / 'compare.png'}, {out / 'summary.json'}")
    return 0
