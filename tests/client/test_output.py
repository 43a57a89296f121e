"""Frame sinks: the MP4 written by PyAV's libx264 reads back with OpenCV at its size, rate and content; a failed
encode leaves nothing behind."""

import cv2
import numpy as np
import pytest
import torch

from stgs.client.output import Mp4Sink, NullSink, PngSink, open_sink
from stgs.errors import StgsError


def _gradient(h: int, w: int, shift: float) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return torch.from_numpy(np.stack([x / w, y / h, np.full((h, w), shift)], axis=-1).astype(np.float32))


def test_mp4_of_odd_size_keeps_frames_and_time(tmp_path):
    h, w = 25, 33  # odd: the encoder pads to 34x26
    sink = open_sink(tmp_path / "clip.mp4", 12.0, w, h)
    assert isinstance(sink, Mp4Sink)
    sink.write(0, _gradient(h, w, 0.2))
    sink.repeat(1)  # a dropped frame repeats the last one
    sink.write(2, _gradient(h, w, 0.8))
    sink.close()
    assert not list(tmp_path.glob(".clip.mp4*"))
    cap = cv2.VideoCapture(str(tmp_path / "clip.mp4"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0)
    frames = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        frames.append(bgr[..., ::-1].astype(np.float32) / 255)
    assert len(frames) == 3 and frames[0].shape == (h + 1, w + 1, 3)
    for got, want in zip(frames, [0.2, 0.2, 0.8], strict=True):
        assert abs(float(got[:h, :w, 2].mean()) - want) < 0.03  # blue channel = the frame's constant


def test_mp4_abort_leaves_nothing(tmp_path):
    sink = Mp4Sink(tmp_path / "clip.mp4", 30.0, 16, 16)
    sink.write(0, torch.zeros(16, 16, 3))
    sink.abort()
    assert list(tmp_path.iterdir()) == []


def test_sink_choice(tmp_path):
    assert type(open_sink(None, 30.0, 8, 8)) is NullSink
    assert isinstance(open_sink(tmp_path / "frames", 30.0, 8, 8), PngSink)
    (tmp_path / "file").write_text("x")
    with pytest.raises(StgsError, match="not a folder"):
        open_sink(tmp_path / "file", 30.0, 8, 8)
