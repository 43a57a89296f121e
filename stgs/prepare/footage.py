"""Raw footage: one video file per camera, as a rig records it. What `stgs prepare` checks before doing anything
(docs/CAPTURE.md, "Preparing raw footage"), and frames read one at a time, upright.

A camera is named by its file's stem. Frame `i` of a camera is the i-th frame of its video stream in
presentation order; a video's display rotation (its display matrix) is applied to every frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from stgs.data.frames import natural_key
from stgs.errors import StgsError

VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mts", ".ts")
"""What a folder of footage is searched for (any container PyAV reads works when named one by one)."""
VFR_TOLERANCE = 0.25
"""A frame whose timestamp step differs from the nominal frame time by more than this fraction of it makes the
video variable-rate."""


class FootageError(StgsError):
    """Footage that cannot be prepared: a file that is not a video, differing frame rates, variable frame rate,
    a camera without audio when audio sync is asked, a span longer than the footage."""


@dataclass
class Footage:
    """One camera's video, as probed (nothing decoded but the first frame)."""

    camera: str
    """The camera's name: the file's stem."""
    path: Path
    rate: Fraction
    """Average frame rate of the video stream."""
    frames: int
    """Frames in the video stream (counted from its packets)."""
    width: int
    """Frame width after the display rotation."""
    height: int
    rotation: int
    """Counter-clockwise degrees the frames are turned by to stand upright (0, 90, 180, 270)."""
    audio_rate: int | None
    """Sample rate of the first audio stream; None where there is no audio."""

    @property
    def seconds(self) -> float:
        return self.frames / float(self.rate)

    def to_json(self) -> dict:
        return {"camera": self.camera, "path": str(self.path), "fps": float(self.rate),
                "fps_fraction": f"{self.rate.numerator}/{self.rate.denominator}", "frames": self.frames,
                "width": self.width, "height": self.height, "rotation": self.rotation,
                "audio_rate": self.audio_rate}


def find_videos(paths: list[Path]) -> list[Path]:
    """The video files named, a folder standing for the videos it holds (VIDEO_SUFFIXES, in natural order)."""
    found: list[Path] = []
    for path in paths:
        if path.is_dir():
            inside = sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES),
                            key=lambda p: natural_key(p.name))
            if not inside:
                raise FootageError(f"{path}: holds no videos ({', '.join(VIDEO_SUFFIXES)})")
            found += inside
        elif path.is_file():
            found.append(path)
        else:
            raise FootageError(f"{path}: no such file or folder")
    stems = [p.stem for p in found]
    dup = next((s for s in stems if stems.count(s) > 1), None)
    if dup is not None:
        raise FootageError(f"two videos for camera {dup!r} (a camera is named by its file's stem)")
    if len(found) < 2:
        raise FootageError(f"{len(found)} video given: a multi-view capture needs one video per camera, two or more")
    return found


def _rotation(stream: av.video.stream.VideoStream, first: av.VideoFrame | None) -> int:
    degrees = first.rotation if first is not None else 0
    turn = round(degrees / 90.0) % 4 * 90
    if abs(degrees % 90) > 1e-6 and abs(degrees % 90 - 90) > 1e-6:
        raise FootageError(f"{stream.container.name}: a display rotation of {degrees}° is not a quarter turn")
    return turn


def probe(path: Path) -> Footage:
    """The video's stream facts, checked: it opens, holds a video stream with frames, and is constant-rate
    (FootageError otherwise, naming the file)."""
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise FootageError(f"{path}: holds no video stream")
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.guessed_rate
            if not rate or rate <= 0:
                raise FootageError(f"{path}: the container states no frame rate")
            stamps = [p.pts for p in container.demux(stream) if p.size and p.pts is not None]
            audio = container.streams.audio[0].sample_rate if container.streams.audio else None
            container.seek(0)
            first = next(container.decode(stream), None)
            if first is None:
                raise FootageError(f"{path}: the video stream has no frames")
            turn = _rotation(stream, first)
            if stream.time_base is None:
                raise FootageError(f"{path}: the video stream has no time base")
            step = float(1 / (Fraction(rate) * stream.time_base))
    except av.FFmpegError as exc:
        raise FootageError(f"{path}: not a readable video ({exc.strerror or exc})") from None
    stamps.sort()
    if len(stamps) > 2:
        deltas = np.diff(np.asarray(stamps, dtype=np.float64))
        worst = float(np.max(np.abs(deltas - step))) / step
        if worst > VFR_TOLERANCE:
            raise FootageError(f"{path}: variable frame rate (a frame step {worst:.0%} off the nominal "
                               f"{float(rate):.3f} fps); re-encode it at a constant rate first, e.g. "
                               f"ffmpeg -i {path.name} -fps_mode cfr -r {float(rate):g} -c:v ffv1 out.mkv")
    width, height = (first.height, first.width) if turn in (90, 270) else (first.width, first.height)
    return Footage(path.stem, path, Fraction(rate), len(stamps), width, height, turn, audio)


def check_rates(footage: list[Footage]) -> Fraction:
    """The rig's frame rate: every video's, or FootageError naming the videos that differ from the most common."""
    rates = [f.rate for f in footage]
    common = max(set(rates), key=rates.count)
    odd = [f for f in footage if f.rate != common]
    if odd:
        names = ", ".join(f"{f.camera} ({float(f.rate):.3f} fps)" for f in odd)
        raise FootageError(f"frame rates differ: {names} against {float(common):.3f} fps for the rest; "
                           "re-encode the odd ones at the rig's rate")
    return common


def upright(rgb: np.ndarray, rotation: int) -> np.ndarray:
    return np.ascontiguousarray(np.rot90(rgb, rotation // 90)) if rotation else rgb


def read_frames(footage: Footage, first: int, count: int) -> Iterator[tuple[int, np.ndarray]]:
    """Frames `first`..`first + count - 1` of the camera as (index, (H, W, 3) uint8 RGB upright), decoded one
    at a time from the nearest keyframe before `first`."""
    wanted = range(first, first + count)
    if count <= 0:
        return
    try:
        with av.open(str(footage.path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            origin = stream.start_time or 0
            if stream.time_base is None:
                raise FootageError(f"{footage.path}: the video stream has no time base")
            tick = 1 / (footage.rate * stream.time_base)
            if first > 0:
                container.seek(int(origin + math.floor(first * tick)), stream=stream, backward=True)
            for frame in container.decode(stream):
                if frame.pts is None:
                    continue
                index = round((frame.pts - origin) / tick)
                if index < first:
                    continue
                if index >= wanted.stop:
                    return
                yield index, upright(frame.to_ndarray(format="rgb24"), footage.rotation)
    except av.FFmpegError as exc:
        raise FootageError(f"{footage.path}: decoding failed ({exc.strerror or exc})") from None


def read_frames_at(footage: Footage, indices: list[int]) -> dict[int, np.ndarray]:
    """The frames at `indices` (each decoded from the keyframe before it)."""
    out: dict[int, np.ndarray] = {}
    for index in sorted(set(indices)):
        for got, rgb in read_frames(footage, index, 1):
            out[got] = rgb
        if index not in out:
            raise FootageError(f"{footage.path}: frame {index} could not be decoded")
    return out
