"""Synchronising the cameras: each camera's offset, in frames, from a reference camera, and the span all of them
cover (docs/CAPTURE.md, "Preparing raw footage").

An offset of k means the camera started k frames after the reference: its frame i shows the reference's frame
i + k. With audio on every camera, the offsets come from cross-correlating the audio envelopes against the
reference's, to the sample, then rounded to frames; each comes with its peak-to-side ratio. Without audio the
frame indices are taken as they are (offset 0); offsets given by hand override either.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import av
import numpy as np
from scipy import signal

from stgs.prepare.footage import Footage, FootageError
from stgs.prepare.settings import SYNC_METHODS

SYNC_SECONDS = 120.0
"""Audio read from the start of each video to find its offset: offsets up to about half of this are found."""
MIN_CONFIDENCE = 2.0
"""The least peak-to-side ratio an audio offset is taken at (the highest correlation peak against the highest
one more than a frame away from it)."""
SMOOTH_SECONDS = 0.001
"""The envelope's smoothing window (rectified audio averaged over it)."""
BASELINE_SECONDS = 0.05
"""The slow level subtracted from the envelope, so that onsets, not loudness, correlate."""


class SyncError(FootageError):
    """Cameras that cannot be synchronised: an unclear audio peak, a camera without audio when audio is asked,
    a hand-given offset naming no camera, no common span."""


@dataclass
class Offset:
    """One camera's offset from the reference."""

    camera: str
    frames: int
    """Frames the camera started after the reference (negative: before)."""
    seconds: float | None
    """The audio's offset in seconds, before rounding to frames (None where it did not come from audio)."""
    confidence: float | None
    """Peak-to-side ratio of the audio correlation (None where it did not come from audio)."""
    source: str
    """"reference", "audio", "index" or "given"."""

    def to_json(self) -> dict:
        return {"camera": self.camera, "frames": self.frames, "seconds": self.seconds,
                "confidence": self.confidence, "source": self.source}


@dataclass
class Span:
    """The trimmed common span: reference frames `start`..`start + frames - 1`, every camera's own first frame."""

    start: int
    frames: int
    first_frame: dict[str, int]
    """Each camera's frame index that shows the span's first frame."""
    rate: Fraction

    @property
    def seconds(self) -> float:
        return self.frames / float(self.rate)

    def to_json(self) -> dict:
        return {"start": self.start, "frames": self.frames, "seconds": self.seconds,
                "first_frame": self.first_frame}


def parse_offsets(text: str) -> dict[str, int]:
    """`cam=frames,cam=frames` as a dict (ValueError naming the bad item)."""
    out: dict[str, int] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = item.partition("=")
        try:
            if not sep or not name.strip():
                raise ValueError
            out[name.strip()] = int(value)
        except ValueError:
            raise ValueError(f"{item!r} is not camera=frames") from None
    return out


def envelope(footage: Footage, rate: int, seconds: float = SYNC_SECONDS) -> np.ndarray:
    """The first `seconds` of the camera's audio as an onset envelope at `rate` samples per second: mono,
    rectified, smoothed over SMOOTH_SECONDS, its slow level (BASELINE_SECONDS) removed."""
    chunks: list[np.ndarray] = []
    wanted = int(seconds * rate)
    try:
        with av.open(str(footage.path)) as container:
            if not container.streams.audio:
                raise SyncError(f"{footage.camera}: {footage.path} has no audio track")
            resampler = av.AudioResampler(format="flt", layout="mono", rate=rate)
            got = 0
            for frame in container.decode(container.streams.audio[0]):
                for out in resampler.resample(frame):
                    chunks.append(out.to_ndarray().reshape(-1))
                    got += chunks[-1].size
                if got >= wanted:
                    break
    except av.FFmpegError as exc:
        raise SyncError(f"{footage.path}: its audio could not be decoded ({exc.strerror or exc})") from None
    audio = np.concatenate(chunks)[:wanted].astype(np.float64) if chunks else np.zeros(0)
    if audio.size < rate // 10:
        raise SyncError(f"{footage.camera}: {footage.path} holds less than 0.1 s of audio")
    rectified = np.abs(audio)
    smooth = _moving_mean(rectified, max(1, int(SMOOTH_SECONDS * rate)))
    return smooth - _moving_mean(smooth, max(1, int(BASELINE_SECONDS * rate)))


def _moving_mean(x: np.ndarray, width: int) -> np.ndarray:
    if width <= 1:
        return x
    return signal.oaconvolve(x, np.full(width, 1.0 / width), mode="same")


def audio_lag(reference: np.ndarray, other: np.ndarray, exclusion: int) -> tuple[int, float]:
    """(lag, peak-to-side ratio): `other`'s sample n is `reference`'s sample n + lag; the side peak is the highest
    correlation more than `exclusion` samples from the peak."""
    corr = signal.correlate(reference, other, mode="full", method="fft")
    peak = int(np.argmax(corr))
    lag = peak - (other.size - 1)
    side = np.concatenate([corr[:max(0, peak - exclusion)], corr[peak + exclusion + 1:]])
    top = float(corr[peak])
    rest = float(side.max()) if side.size else 0.0
    ratio = top / rest if rest > 0 else float("inf") if top > 0 else 0.0
    return lag, ratio


def find_offsets(footage: list[Footage], rate: Fraction, method: str = "auto",
                 given: dict[str, int] | None = None) -> list[Offset]:
    """Each camera's offset from the first (the reference): from audio (method "audio", or "auto" where every
    video has audio), else frame index; `given` overrides any camera's (SyncError for a name no video has)."""
    given = dict(given or {})
    names = {f.camera for f in footage}
    unknown = sorted(set(given) - names)
    if unknown:
        raise SyncError(f"offset given for {unknown[0]!r}, which no video is named (cameras: "
                        f"{', '.join(f.camera for f in footage)})")
    if method not in SYNC_METHODS:
        raise SyncError(f"sync method must be one of {', '.join(SYNC_METHODS)}, not {method!r}")
    silent = [f.camera for f in footage if f.audio_rate is None]
    use_audio = method == "audio" or (method == "auto" and not silent)
    if method == "audio" and silent:
        raise SyncError(f"camera {silent[0]} has no audio track; audio sync needs audio on every camera "
                        "(or sync by frame index, or give the offsets)")
    reference = footage[0]
    out = [Offset(reference.camera, given.get(reference.camera, 0), 0.0 if use_audio else None,
                  None, "given" if reference.camera in given else "reference")]
    if use_audio and len(given) < len(footage) - 1:
        sample_rate = reference.audio_rate or 48000
        ref = envelope(reference, sample_rate)
        exclusion = max(1, round(sample_rate / float(rate)))
    for cam in footage[1:]:
        if cam.camera in given:
            out.append(Offset(cam.camera, given[cam.camera], None, None, "given"))
        elif use_audio:
            lag, ratio = audio_lag(ref, envelope(cam, sample_rate), exclusion)
            seconds = lag / sample_rate
            if not ratio >= MIN_CONFIDENCE:
                raise SyncError(f"camera {cam.camera}: its audio matches the reference's ({reference.camera}) "
                                f"with no clear peak (peak-to-side {ratio:.2f}, {MIN_CONFIDENCE} needed); "
                                "give its offset by hand (camera=frames) or sync by frame index")
            out.append(Offset(cam.camera, round(seconds * float(rate)) + out[0].frames, seconds,
                              round(ratio, 3), "audio"))
        else:
            out.append(Offset(cam.camera, 0, None, None, "index"))
    return out


def common_span(footage: list[Footage], offsets: list[Offset], rate: Fraction, start_seconds: float = 0.0,
                seconds: float | None = None) -> Span:
    """The reference frames every camera covers, cut to `start_seconds` (from the span's start) and `seconds`
    (SyncError where nothing is common, FootageError where the footage is shorter than asked)."""
    shift = {o.camera: o.frames for o in offsets}
    begin = max(shift[f.camera] for f in footage)
    end = min(shift[f.camera] + f.frames for f in footage)
    if end <= begin:
        raise SyncError(f"the videos share no frame once synchronised (offsets "
                        f"{', '.join(f'{o.camera}={o.frames}' for o in offsets)})")
    skip = round(start_seconds * float(rate))
    if skip < 0:
        raise FootageError(f"the start must be 0 s or later, not {start_seconds} s")
    available = end - begin - skip
    if available <= 0:
        raise FootageError(f"the common span is {(end - begin) / float(rate):.2f} s; it does not reach the start "
                           f"at {start_seconds} s")
    count = available
    if seconds is not None:
        count = round(seconds * float(rate))
        if count < 1:
            raise FootageError(f"the span must hold at least one frame ({seconds} s asked)")
        if count > available:
            short = min(footage, key=lambda f: shift[f.camera] + f.frames)
            raise FootageError(f"{seconds} s asked from {start_seconds} s, but the common span holds "
                               f"{available / float(rate):.2f} s from there (camera {short.camera} ends first)")
    start = begin + skip
    return Span(start, count, {f.camera: start - shift[f.camera] for f in footage}, rate)
