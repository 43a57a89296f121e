"""`stgs demo`: the whole path on the embedded default scene, on this machine, with no downloads.

synthesise (preset "demo" with a static backdrop: a layered scene, model
format 2) -> pack (five QPs) -> serve on a free loopback port -> play a
free-viewpoint orbit with the look-ahead ABR -> write the video, a contact
sheet, a truth | streamed | error comparison and a summary. The same scene is
also synthesised and packed as format 1 (the backdrop folded into every GOP)
to print what the static layer saves: both formats' KB/frame and rendered
PSNR per QP.

This is the one place that drives every stage; it imports them lazily.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import threading
import time
from pathlib import Path

import cv2
import torch

from stgs.camera import Camera, intrinsics, look_at
from stgs.fsio import atomic_write_bytes, image_grid, save_png
from stgs.metrics import psnr
from stgs.model.renderer import FrameRenderer
from stgs.native.library import available
from stgs.synth import PRESETS, SCENE_TARGET, synthesize
from stgs.tree import KEYFRAME_REP, MANIFEST

SHEET_COLUMNS = 6
SHEET_ROWS = 2
COMPARE_FRAMES = 4


def orbit_camera(frame: int, frames: int, width: int, height: int) -> Camera:
    """A camera that circles the scene once over the whole playback."""
    angle = 2 * math.pi * frame / frames
    eye = (3.0 * math.sin(angle), 1.2 + 0.3 * math.sin(2 * angle), 3.0 * math.cos(angle))
    return Camera(f"orbit{frame:05d}", intrinsics(width, height, 60.0), look_at(eye, SCENE_TARGET),
                  width, height)


def video_frames(path: Path, count: int) -> list[torch.Tensor]:
    """`count` frames spread evenly over an MP4, as (H, W, 3) float RGB."""
    cap = cv2.VideoCapture(str(path))
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    frames = []
    for i in range(count):
        cap.set(cv2.CAP_PROP_POS_FRAMES, i * total // count)
        ok, bgr = cap.read()
        if ok:
            frames.append(torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).float() / 255)
    cap.release()
    return frames


class TruthProbe:
    """Compares every streamed GOP with the ground truth and the uncompressed model at a scene camera."""

    def __init__(self, model_dir: Path, gop_size: int):
        from stgs.data.synth import SynthReader
        from stgs.model.store import load_model, load_static

        self.gop_size = gop_size
        self.truth = SynthReader(model_dir)
        self.camera = self.truth.cameras(0)[0]
        meta, self.local = load_model(model_dir)
        self.static = load_static(model_dir, meta)
        self.rows: list[tuple[float, float]] = []
        """(PSNR vs truth, PSNR vs uncompressed model) per compared frame."""
        self.compare: list[torch.Tensor] = []
        self.lock = threading.Lock()

    def __call__(self, k: int, i: int, renderer: FrameRenderer, window: list[torch.Tensor]) -> None:
        """The player's frame hook: frames 0 and G/2 of each GOP, at the scene's first camera."""
        if i not in (0, self.gop_size // 2):
            return
        f = k * self.gop_size + i
        truth = self.truth.image(f, self.camera.name)
        streamed = renderer.render(i, self.camera, window=window).clamp(0, 1)
        reference = FrameRenderer(self.local[k], static=self.static).render(i, self.camera).clamp(0, 1)
        with self.lock:
            self.rows.append((psnr(streamed, truth), psnr(streamed, reference)))
            if len(self.compare) < 3 * COMPARE_FRAMES:
                self.compare += [truth, streamed, ((streamed - truth).abs() * 10).clamp(0, 1)]


async def stream(dash: Path, play_cfg_kwargs: dict, probe: TruthProbe) -> dict:
    """Serve `dash` on a free loopback port and play it; returns the playback log."""
    from stgs.client import PlayConfig, play
    from stgs.server.app import loopback

    async with loopback(dash) as base:
        return await play(PlayConfig(url=base + MANIFEST, **play_cfg_kwargs), on_frame=probe)


def format_rows(stats: dict) -> dict[str, dict]:
    """Per feature Representation of a packed tree, played with the lossless keyframe (so that the two formats
    compare like with like, whatever keyframe rungs the auto ladder paired): KB per frame (keyframes, features and,
    in format 2, the static layer amortised over the scene's frames) and the mean rendered PSNR against the
    uncompressed model, from the ladder's candidates."""
    frames = len(stats["gops"]) * stats["frames_per_gop"]
    static = stats["static"]["bytes"] if "static" in stats else 0
    rows = {}
    for ladder in stats["ladders"].values():
        for c in ladder["candidates"]:
            rid = c.get("features", c["representation"])
            if rid in stats["representations"] and c.get("keyframes", KEYFRAME_REP) == KEYFRAME_REP:
                rows[rid] = {"kb_per_frame": (c["total_bytes"] + static) / frames / 1e3,
                             "render_psnr": c["render_psnr"]}
    return rows


def run(out: Path, progress: bool = True, fit_steps: int | None = None) -> int:
    from stgs.client.config import ViewSpec
    from stgs.packager import PackConfig, pack
    from stgs.tree import packaged_rep_id

    out = Path(out)
    cfg = dataclasses.replace(PRESETS["demo"], effects=(*PRESETS["demo"].effects, "static_background"))
    if fit_steps is not None:
        cfg = dataclasses.replace(cfg, fit_steps=fit_steps)
    cfg.validate()
    print(f"stgs demo: native kernels {'on' if available() else 'OFF (pure-torch reference)'}")
    clock = time.perf_counter()
    report = synthesize(cfg, out / "model", progress=progress)
    synth_s = time.perf_counter() - clock
    clock = time.perf_counter()
    stats = pack(out / "model", out / "dash", PackConfig(), progress=progress)
    pack_s = time.perf_counter() - clock
    single_report = synthesize(dataclasses.replace(cfg, fold=True), out / "model_format1", progress=progress)
    # the folded twin at the rungs the layered scene's auto ladder kept, so that each rung compares with itself
    kept = {codec: tuple(packaged_rep_id(c.get("features", c["representation"]))[1] for c in ladder["candidates"]
                         if c["kept"])
            for codec, ladder in stats["ladders"].items()}
    single_stats = pack(out / "model_format1", out / "dash_format1",
                        PackConfig(ladder="fixed", qps=kept["hevc"], av1_qps=kept["av1"]), progress=progress)
    frames = cfg.num_gops * cfg.gop_size
    orbit = out / "orbit.mp4"
    probe = TruthProbe(out / "model", cfg.gop_size)
    path = out / "orbit_path.json"
    atomic_write_bytes(path, json.dumps([orbit_camera(f, frames, cfg.width, cfg.height).to_json()
                                         for f in range(frames)]).encode())
    log = asyncio.run(stream(out / "dash", {"abr": "mpc", "out": orbit, "log": out / "playback.json",
                                            "view": ViewSpec(path=str(path))}, probe))
    save_png(out / "contact_sheet.png", image_grid(video_frames(orbit, SHEET_COLUMNS * SHEET_ROWS), SHEET_COLUMNS))
    save_png(out / "compare.png", image_grid(probe.compare, 3))
    truth_db = sum(r[0] for r in probe.rows) / len(probe.rows)
    model_db = sum(r[1] for r in probe.rows) / len(probe.rows)
    summary = {
        "gaussians": cfg.grid_side ** 2, "gops": cfg.num_gops, "frames": frames,
        "resolution": [cfg.width, cfg.height], "synth_seconds": synth_s, "pack_seconds": pack_s,
        "model_fidelity_psnr_db": report.fidelity_psnr,
        "streamed_vs_truth_psnr_db": truth_db, "streamed_vs_model_psnr_db": model_db,
        "qps": [g["qp"] for g in log["gops"]], "kb_per_frame": log["kb_per_frame"],
        "startup_delay_s": log["startup_delay_s"], "stalls": log["stalls"],
        "render_ms_median": log["render_ms_median"], "render_fps": log["render_fps"],
        "ladder_kbps": {rid: rep["bandwidth"] / 1e3 for rid, rep in stats["representations"].items()},
        "static_gaussians": cfg.static_grid_side ** 2, "static_bytes": stats["static"]["bytes"],
        "formats": {"2": {"fidelity_psnr_db": report.fidelity_psnr, "per_qp": format_rows(stats)},
                    "1": {"fidelity_psnr_db": single_report.fidelity_psnr,
                          "gaussians": model_capacity(out / "model_format1"),
                          "per_qp": format_rows(single_stats)}},
    }
    atomic_write_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    print(f"scene: {summary['gaussians']} moving Gaussians + a static layer of {summary['static_gaussians']} "
          f"({summary['static_bytes'] / 1e3:.0f} kB, sent once), {cfg.num_gops} GOPs x {cfg.gop_size} frames at "
          f"{cfg.fps:g} fps ({cfg.width}x{cfg.height}); synthesised in {synth_s:.0f} s, packed in {pack_s:.0f} s")
    print_formats(summary["formats"])
    print(f"streamed with the look-ahead (mpc) ABR: QPs {','.join(map(str, summary['qps']))}, "
          f"{summary['kb_per_frame']:.1f} KB/frame, start-up {summary['startup_delay_s']:.2f} s, "
          f"{log['stalls']['count']} stall(s)")
    print(f"streamed frames vs ground truth: {truth_db:.2f} dB PSNR (uncompressed model: "
          f"{report.fidelity_psnr:.2f} dB; streamed vs model {model_db:.2f} dB)")
    print(f"render (deform + splat): {summary['render_ms_median']:.1f} ms/frame median "
          f"({summary['render_fps']:.0f} fps)")
    print(f"wrote {orbit}, {out / 'contact_sheet.png'}, {out / 'compare.png'}, {out / 'playback.json'}, "
          f"{out / 'summary.json'}")
    web_screenshot(out / "dash", out / "web.png")
    print(f"watch it in a browser and fly the camera yourself: stgs serve {out / 'dash'}  then open "
          f"http://127.0.0.1:8080/player/?mpd=/{MANIFEST}")
    return 0


def web_screenshot(tree: Path, png: Path, tries: int = 2) -> None:
    """The web player mid-playback in headless Chromium, saved to `png` (where Node, the built player and
    Chromium are here; else one line says why not). A failed try is reported with what the page logged, and a
    fresh browser tries again: a headless browser's first start on a new machine can miss a step's deadline."""
    from stgs.cli.browser import browse, missing_browser, served

    why = missing_browser()
    if why:
        print(f"web player screenshot skipped: {why}")
        return
    for attempt in range(1, tries + 1):
        with served(tree) as base:
            out, failure = browse({"viewport": [800, 560], "steps": [
                {"goto": f"{base}player/?mpd=/{MANIFEST}&camera=cam00"},
                {"wait": "window.stgsPlayer && stgsPlayer.current >= stgsPlayer.totalFrames / 2", "timeout": 120_000},
                {"press": "i"},
                {"sleep": 600},
                {"screenshot": str(png)},
            ]})
        if failure is None:
            print(f"web player mid-playback: {png}")
            return
        logged = "; ".join(out.get("errors", []) + [m["text"] for m in out.get("console", []) if m["type"] == "error"])
        print(f"web player screenshot failed (try {attempt} of {tries}): {failure}"
              + (f" (the page logged: {logged[:400]})" if logged else ""))


def model_capacity(model_dir: Path) -> int:
    """Gaussian slots of each GOP of a model dir."""
    from stgs.model.store import read_meta

    return read_meta(model_dir).shape.capacity


def print_formats(formats: dict) -> None:
    """Both formats of the scene side by side: KB/frame and rendered PSNR (vs each uncompressed model) per QP, each
    with the lossless keyframe."""
    two, one = formats["2"], formats["1"]
    print(f"format 2 (static layer sent once) vs format 1 (every GOP carries the backdrop, lossless keyframes, "
          f"{one['gaussians']} Gaussians): model fidelity {two['fidelity_psnr_db']:.2f} vs "
          f"{one['fidelity_psnr_db']:.2f} dB")
    for rid, row in two["per_qp"].items():
        other = one["per_qp"][rid]
        print(f"  {rid}: {row['kb_per_frame']:6.1f} vs {other['kb_per_frame']:6.1f} KB/frame "
              f"({row['kb_per_frame'] / other['kb_per_frame']:.2f}x), rendered {row['render_psnr']:.2f} vs "
              f"{other['render_psnr']:.2f} dB")
