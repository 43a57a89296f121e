"""The one route to ffmpeg: its binary (Debian's, with libx265 8/10/12-bit) through three small helpers.

`run` for a whole job (bytes in, bytes or a file out), `FrameReader` for raw
frames read one at a time from a decode (the memory a caller holds is one
frame, whatever the segment says), `Writer` for raw frames streamed into an
encode. Every call has the same quiet flags, and a failure raises
`FFmpegError` with ffmpeg's own message. The binary, not an in-process
binding: it is the ffmpeg the system already validates (12-bit x265), and a
hostile segment can crash only a child process.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator

from stgs.errors import StgsError

QUIET = ["-hide_banner", "-nostdin", "-loglevel", "error"]
STDERR_BYTES = 1 << 16
"""At most this much of ffmpeg's error output is kept for a message."""


class FFmpegError(RuntimeError):
    """ffmpeg or ffprobe exited with an error (the message is its own)."""


def require_ffmpeg() -> None:
    if shutil.which("ffmpeg") is None or shutil.which("ffprobe") is None:
        raise StgsError("ffmpeg and ffprobe are required (Debian: apt-get install ffmpeg)")


def _message(stderr: bytes) -> str:
    return stderr[:STDERR_BYTES].decode(errors="replace").strip()


def run(args: list[str], input: bytes | None = None, tool: str = "ffmpeg") -> bytes:
    """Run ffmpeg (or ffprobe) with `args` to the end; returns its stdout."""
    flags = ["-hide_banner", "-v", "error"] if tool == "ffprobe" else QUIET
    result = subprocess.run([tool, *flags, *args], input=input, capture_output=True, check=False)
    if result.returncode != 0:
        raise FFmpegError(f"{tool} failed: {_message(result.stderr)}")
    return result.stdout


class FrameReader:
    """Raw frames of `frame_bytes` each from an ffmpeg decode writing to stdout, read one at a time.

    Iterating yields whole frames; a short last frame or an ffmpeg error raises FFmpegError; `close()` (or leaving
    a `with` block) kills a decode that still runs, so a caller that stops early never reads what it did not ask
    for."""

    def __init__(self, args: list[str], frame_bytes: int):
        self.frame_bytes = frame_bytes
        self.proc = subprocess.Popen(["ffmpeg", *QUIET, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    def __iter__(self) -> Iterator[bytes]:
        while True:
            data = self.proc.stdout.read(self.frame_bytes)
            if len(data) == self.frame_bytes:
                yield data
                continue
            err = self.proc.stderr.read(STDERR_BYTES)
            if self.proc.wait() != 0:
                raise FFmpegError(_message(err) or f"ffmpeg exited with {self.proc.returncode}")
            if data:
                raise FFmpegError(f"the decode ended inside a frame ({len(data)} of {self.frame_bytes} bytes)")
            return

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self.proc.stdout.close()
        self.proc.stderr.close()

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Writer:
    """An ffmpeg encode fed raw frames on stdin (`write`), finished by `close` or killed by `abort`."""

    def __init__(self, args: list[str]):
        self.proc = subprocess.Popen(["ffmpeg", *QUIET, "-y", *args], stdin=subprocess.PIPE, stderr=subprocess.PIPE)

    def write(self, data: bytes) -> None:
        try:
            self.proc.stdin.write(data)
        except BrokenPipeError:
            err = self.proc.stderr.read(STDERR_BYTES)
            self.abort()
            raise FFmpegError(f"ffmpeg stopped reading ({_message(err)})") from None

    def close(self) -> None:
        self.proc.stdin.close()
        err = self.proc.stderr.read(STDERR_BYTES)
        if self.proc.wait() != 0:
            raise FFmpegError(f"ffmpeg failed ({_message(err)})")

    def abort(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
