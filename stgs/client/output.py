"""Where rendered frames go: numbered PNGs in a folder, an MP4 (H.264, PyAV), or nowhere."""

from __future__ import annotations

import contextlib
import os
import tempfile
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from stgs.camera import Camera
from stgs.client.config import PlaybackError
from stgs.errors import StgsError
from stgs.fsio import DIR_MODE, FILE_MODE, atomic_write_bytes, encode_png, to_uint8


class NullSink:
    """Discards frames (benchmarks, `--out` not given)."""

    def write(self, frame: int, image) -> None:
        pass

    def repeat(self, frame: int) -> None:
        pass

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


class PngSink(NullSink):
    """OUT/<frame:05d>.png per rendered frame (frame = index in the presentation); dropped frames are absent."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise StgsError(f"{folder}: exists and is not a folder")
        self.folder.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)

    def write(self, frame: int, image) -> None:
        atomic_write_bytes(self.folder / f"{frame:05d}.png", encode_png(image))


class Mp4Sink(NullSink):
    """An H.264 MP4 at the presentation's frame rate (libx264 in-process through PyAV); a dropped frame repeats the
    previous one, so time holds. Written to a temp file beside the target, renamed into place on close()."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".mp4", dir=self.path.parent)
        os.close(fd)
        self.size = (width, height)
        self.last: np.ndarray | None = None
        try:
            self.container = av.open(self.tmp, "w", format="mp4", options={"movflags": "+faststart"})
            self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001),
                                                    options={"preset": "veryfast", "crf": "18"})
            # yuv420p needs even sides: the encoder's picture is padded by one row/column where needed
            self.stream.width, self.stream.height = width + width % 2, height + height % 2
            self.stream.pix_fmt = "yuv420p"
        except av.FFmpegError as exc:
            self.abort()
            raise StgsError(f"{self.path}: cannot start the H.264 encode ({exc.strerror or exc})") from None
        self.count = 0

    def _send(self, rgb: np.ndarray) -> None:
        width, height = self.stream.width, self.stream.height
        if rgb.shape[:2] != (height, width):
            rgb = np.pad(rgb, ((0, height - rgb.shape[0]), (0, width - rgb.shape[1]), (0, 0)), mode="edge")
        frame = av.VideoFrame.from_ndarray(rgb, format="rgb24").reformat(format="yuv420p")
        frame.pts = self.count
        self.count += 1
        try:
            self.container.mux(self.stream.encode(frame))
        except (av.FFmpegError, OSError) as exc:
            self.abort()
            raise StgsError(f"{self.path}: the H.264 encode failed ({getattr(exc, 'strerror', None) or exc})") \
                from None

    def write(self, frame: int, image) -> None:
        self.last = np.ascontiguousarray(to_uint8(image))
        self._send(self.last)

    def repeat(self, frame: int) -> None:
        width, height = self.size
        self._send(self.last if self.last is not None else np.zeros((height, width, 3), np.uint8))

    def close(self) -> None:
        try:
            self.container.mux(self.stream.encode(None))
            self.container.close()
        except (av.FFmpegError, OSError) as exc:
            self.abort()
            raise StgsError(f"{self.path}: the H.264 encode failed ({getattr(exc, 'strerror', None) or exc})") \
                from None
        os.chmod(self.tmp, FILE_MODE)
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        container = getattr(self, "container", None)
        if container is not None:
            with contextlib.suppress(av.FFmpegError, OSError):
                container.close()
        if os.path.exists(self.tmp):
            os.unlink(self.tmp)


def open_sink(out: Path | None, fps: float, width: int, height: int) -> NullSink:
    """A sink for `--out`: an .mp4 path -> MP4, anything else -> a folder of PNGs, None -> nothing."""
    if out is None:
        return NullSink()
    if Path(out).suffix.lower() == ".mp4":
        return Mp4Sink(Path(out), fps, width, height)
    return PngSink(Path(out))


def open_view_sink(out: Path | None, fps: float, cameras: list[Camera]) -> NullSink:
    """open_sink for frames drawn from `cameras` (a camera path): an MP4 needs one image size."""
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) > 1 and out is not None and Path(out).suffix.lower() == ".mp4":
        raise PlaybackError("an MP4 needs one image size; the camera path has several (use PNG output)")
    return open_sink(out, fps, cameras[0].width, cameras[0].height)
