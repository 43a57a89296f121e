"""Raw footage of a synthetic rig, as a rig of real cameras would record it: one MP4 per camera (H.264, near
lossless), cameras started some frames late, each with an audio track of one shared random click pattern
shifted by the same offsets."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from stgs.camera import Camera, orbit
from stgs.data.synth import SynthReader
from stgs.interop import ply
from stgs.interop.splats import Splats, colour_to_dc
from stgs.synth import SynthConfig
from stgs.synth.config import SCENE_TARGET
from stgs.synth.generate import ProceduralScene, imported_backdrop, write_ground_truth

AUDIO_RATE = 48000


def textured_backdrop(path: Path, count: int = 30000, seed: int = 0) -> Path:
    """A 3DGS PLY of opaque blobs of random colour and size around and under the rig, at depths from 4 to 7
    (what SIFT matches across views, where the procedural backdrop's stripes repeat)."""
    rng = np.random.default_rng(seed)
    wall, floor = count * 2 // 3, count - count * 2 // 3
    theta = rng.uniform(0, 2 * np.pi, wall)
    radius = rng.uniform(4.0, 7.0, wall)
    wall_means = np.stack([radius * np.cos(theta), rng.uniform(-0.2, 4.0, wall), radius * np.sin(theta)], 1)
    r = np.sqrt(rng.uniform(0.3 ** 2, 4.5 ** 2, floor))
    phi = rng.uniform(0, 2 * np.pi, floor)
    floor_means = np.stack([r * np.cos(phi), rng.uniform(-0.01, 0.3, floor) * (r > 2.2), r * np.sin(phi)], 1)
    means = np.concatenate([wall_means, floor_means]).astype(np.float32)
    scales = np.exp(rng.uniform(np.log(0.015), np.log(0.04), (count, 1))) * np.ones((1, 3))
    splats = Splats(means, np.log(scales).astype(np.float32), np.tile(np.float32([1, 0, 0, 0]), (count, 1)),
                    np.full(count, 6.0, np.float32),
                    colour_to_dc(rng.uniform(0, 1, (count, 3))).astype(np.float32)[:, None, :])
    path.write_bytes(ply.encode(splats))
    return path


def rig_cameras(count: int, arc_deg: float, width: int, height: int) -> list[Camera]:
    """`count` cameras on an arc of `arc_deg` around the scene, all looking at its centre."""
    ring = orbit(round(count * 360 / arc_deg), 3.2, 1.4, SCENE_TARGET, width, height, prefix="cam")
    return [Camera(f"cam{i:02d}", c.K, c.viewmat, width, height) for i, c in enumerate(ring[:count])]


def synthetic_rig(out: Path, cfg: SynthConfig, cameras: list[Camera]) -> SynthReader:
    """The scene's ground-truth views at `cameras` (its backdrop from cfg.static_from), read as a dataset."""
    scene = ProceduralScene(cfg.grid_side ** 2, tuple(cfg.effects), cfg.seed, cfg.static_grid_side ** 2)
    if cfg.static_from is not None:
        scene.static = imported_backdrop(cfg)
    write_ground_truth(out, scene, cfg, cameras, progress=False)
    return SynthReader(out)


def click_track(seconds: float, seed: int = 0, clicks_per_second: float = 4.0) -> np.ndarray:
    """Mono float32 audio at AUDIO_RATE: silence with short noise bursts at random times, plus faint hiss."""
    rng = np.random.default_rng(seed)
    n = int(seconds * AUDIO_RATE)
    audio = rng.normal(0, 0.002, n)
    for at in rng.uniform(0, seconds, int(seconds * clicks_per_second)):
        i = int(at * AUDIO_RATE)
        burst = rng.normal(0, 0.5, 96) * np.exp(-np.arange(96) / 24)
        audio[i:i + burst.size] += burst[:max(0, n - i)]
    return np.clip(audio, -1, 1).astype(np.float32)


def write_footage(path: Path, frames: list[np.ndarray], fps: int, audio: np.ndarray | None = None,
                  rotation: int = 0, codec: str = "libx264") -> Path:
    """`frames` (RGB uint8) as a constant-rate video at `fps` (H.264 at QP 0 in MP4, or FFV1 in MKV), with a
    mono AAC (or FLAC in MKV) track of `audio` and a display rotation (counter-clockwise degrees)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=fps)
        stream.width, stream.height = frames[0].shape[1], frames[0].shape[0]
        if codec == "libx264":
            stream.pix_fmt, stream.options = "yuv444p", {"qp": "0", "preset": "ultrafast"}
        else:
            stream.pix_fmt = "bgr0"
        if rotation:
            stream.set_display_rotation(rotation)
        sound = None
        if audio is not None:
            sound = container.add_stream("aac" if path.suffix == ".mp4" else "flac", rate=AUDIO_RATE,
                                         layout="mono")
        for rgb in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")))
        container.mux(stream.encode())
        if sound is not None:
            for start in range(0, audio.size, 1024):
                chunk = av.AudioFrame.from_ndarray(audio[None, start:start + 1024], format="flt", layout="mono")
                chunk.sample_rate = AUDIO_RATE
                chunk.pts = start
                chunk.time_base = Fraction(1, AUDIO_RATE)
                container.mux(sound.encode(chunk))
            container.mux(sound.encode())
    return path


def write_rig_footage(ds: SynthReader, folder: Path, late: dict[str, int], fps: int = 30, seed: int = 0,
                      audio: bool = True, tail: int = 0) -> list[Path]:
    """One MP4 per camera of `ds`: camera c starts `late[c]` frames into the scene (its audio too); every video
    runs to the scene's end (`tail` frames more of its last view)."""
    seconds = ds.num_frames / fps + 1.0
    track = click_track(seconds, seed) if audio else None
    paths = []
    for name in ds.camera_names:
        k = late.get(name, 0)
        frames = [ds.pixels(f, name) for f in range(k, ds.num_frames)] + [ds.pixels(ds.num_frames - 1, name)] * tail
        sound = track[int(k / fps * AUDIO_RATE):] if track is not None else None
        paths.append(write_footage(folder / f"{name}.mp4", frames, fps, sound))
    return paths
