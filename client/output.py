"""Where rendered frames go: numbered PNGs in a folder, an MP4 (H.264 through ffmpeg), or nowhere."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from stgs.codec.ffmpeg import FFmpegError, Writer, require_ffmpeg
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
    """An H.264 MP4 at the presentation's frame rate; a dropped frame repeats the previous one, so time holds.

    ffmpeg writes a temp file beside the target, renamed into place on close().
    """

    def __init__(self, path: Path, fps: float, width: int, height: int):
        require_ffmpeg()
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".mp4", dir=self.path.parent)
        os.close(fd)
        self.size = (width, height)
        self.last: bytes | None = None
        self.encoder = Writer(["-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}",
                               "-framerate", f"{fps:g}", "-i", "pipe:", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",
                               "-c:v", "libx264", "-preset", "veryfast", "-crf", "18", "-pix_fmt", "yuv420p",
                               "-movflags", "+faststart", self.tmp])

    def _send(self, data: bytes) -> None:
        try:
            self.encoder.write(data)
        except FFmpegError as exc:
            self.abort()
            raise StgsError(f"{self.path}: {exc}") from None

    def write(self, frame: int, image) -> None:
        data = np.ascontiguousarray(to_uint8(image)).tobytes()
        self.last = data
        self._send(data)

    def repeat(self, frame: int) -> None:
        self._send(self.last if self.last is not None else bytes(self.size[0] * self.size[1] * 3))

    def close(self) -> None:
        try:
            self.encoder.close()
        except FFmpegError as exc:
            self.abort()
            raise StgsError(f"{self.path}: {exc}") from None
        os.chmod(self.tmp, FILE_MODE)
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        self.encoder.abort()
        if os.path.exists(self.tmp):
            os.unlink(self.tmp)


def open_sink(out: Path | None, fps: float, width: int, height: int) -> NullSink:
    """A sink for `--out`: an .mp4 path -> MP4, anything else -> a folder of PNGs, None -> nothing."""
    if out is None:
        return NullSink()
    if Path(out).suffix.lower() == ".mp4":
        return Mp4Sink(Path(out), fps, width, height)
    return PngSink(Path(out))
