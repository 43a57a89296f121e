"""The AV1 feature set decodes bit-exactly in a browser: a packed tree's segment, alone after its init segment, through
WebCodecs' VideoDecoder in Debian's headless Chromium (driven by playwright-core on the system binary:
web/tools/webcodecs-decode.mjs), gives I420P10 frames whose luma plane is the Python player's decode, frame for
frame. ./bin/test installs Chromium (as root) and web/'s npm packages; without Node or Chromium this skips."""

from __future__ import annotations

import base64
import hashlib
import io
import json
import shutil
import subprocess
from pathlib import Path

import av
import numpy as np
import pytest

from stgs.codec.av1 import av1_codecs
from stgs.codec.video import AV1, decode_segment

WEB = Path(__file__).resolve().parents[2] / "web"
CHROMIUM = shutil.which("chromium")

pytestmark = pytest.mark.skipif(shutil.which("node") is None or CHROMIUM is None,
                                reason="Node.js or Debian's chromium is not installed")


def chunks_job(init: bytes, media: bytes, width: int, height: int) -> dict:
    """What a page's VideoDecoder needs (what mp4box.js gives the web player): the codecs string, the av1C
    payload as `description`, and the samples in decode order."""
    chunks = []
    with av.open(io.BytesIO(init + media)) as container:
        stream = container.streams.video[0]
        description = bytes(stream.codec_context.extradata or b"")
        for packet in container.demux(stream):
            if packet.size:
                chunks.append({"key": bool(packet.is_keyframe), "timestamp": int(packet.pts),
                               "data": base64.b64encode(bytes(packet)).decode()})
    return {"codec": av1_codecs(init), "width": width, "height": height,
            "description": base64.b64encode(description).decode(), "chunks": chunks}


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    from stgs.packager import PackConfig, pack
    from stgs.synth import SynthConfig, synthesize

    base = tmp_path_factory.mktemp("webcodecs")
    synthesize(SynthConfig(grid_side=16, num_gops=2, gop_size=6, width=64, height=48, num_cameras=2, fit_steps=30),
               base / "model", progress=False)
    pack(base / "model", base / "dash", PackConfig(ladder="fixed",
                                                   codecs=("av1",), av1_qps=(12, 43), jobs=2), progress=False)
    return base / "dash"


@pytest.mark.parametrize("rep, gop", [("av1q12", 0), ("av1q43", 1)])
def test_a_packed_av1_segment_decodes_in_chromium_to_our_frames(tree, tmp_path, rep, gop):
    if not (WEB / "node_modules" / "playwright-core").is_dir():
        pytest.fail("web/node_modules is missing: ./bin/test runs `npm ci` in web/ (Node is installed)")
    folder = next(tree.glob(f"v-*/features/{rep}"))
    init, media = (folder / "init.mp4").read_bytes(), (folder / f"seg_{gop:05d}.m4s").read_bytes()
    e, size = 6 + 2, 4 * 16
    ours = decode_segment(init, media, e, size, size, codec=AV1)
    job = tmp_path / "job.json"
    job.write_text(json.dumps(chunks_job(init, media, size, size)))
    result = subprocess.run(["node", str(WEB / "tools" / "webcodecs-decode.mjs"), str(job), CHROMIUM],
                            capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr
    browser = json.loads(result.stdout)
    assert browser["supported"] and browser["format"] == "I420P10"
    assert browser["frames"] == [hashlib.sha256(f.astype("<u2").tobytes()).hexdigest() for f in ours]
    assert np.ptp(ours) > 100  # real content, not a flat plane that any decoder gets right
