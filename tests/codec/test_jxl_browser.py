"""Every JPEG XL image the packager writes (keyframes, static layers with and without view-dependent colour)
decodes bit-exactly in the browser's decoder: jxl-oxide-wasm under Node, through the same PNG route the web
player takes (web/tools/jxl-decode.mjs), against OpenImageIO's decode. Node and web/'s npm packages (from its
lockfile) are set up by ./bin/test; without Node this test skips."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.numpy import load

from stgs.codec.jxl import decode_jxl
from stgs.codec.static import encode_static
from stgs.model.static import StaticLayer
from stgs.packager import PackConfig, pack
from stgs.synth import SynthConfig, synthesize

WEB = Path(__file__).resolve().parents[2] / "web"
DECODER = WEB / "tools" / "jxl-decode.mjs"
SCENE = SynthConfig(grid_side=16, num_gops=2, gop_size=6, width=64, height=48, num_cameras=2, fit_steps=30,
                    effects=("rigid", "nonrigid", "color", "static_background"), static_grid_side=12)

pytestmark = pytest.mark.skipif(shutil.which("node") is None, reason="Node.js is not installed")


def jxl_images(segment: bytes) -> dict[str, bytes]:
    """The `image.*` tensors (JPEG XL payloads) of a keyframe or static-layer segment."""
    return {k: v.tobytes() for k, v in load(segment).items() if k.startswith("image.")}


def browser_decode(files: list[Path], out: Path) -> list[dict]:
    if not (WEB / "node_modules" / "jxl-oxide-wasm").is_dir():
        pytest.fail("web/node_modules is missing: ./bin/test runs `npm ci` in web/ (Node is installed)")
    result = subprocess.run(["node", str(DECODER), str(out), *map(str, files)], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    return [json.loads(line) for line in result.stdout.splitlines()]


def sh1_static_layer(side: int) -> StaticLayer:
    gen = torch.Generator().manual_seed(3)
    layer = StaticLayer(side * side, sh_degree=1)
    with torch.no_grad():
        for p in layer.parameters():
            p.copy_(torch.randn(p.shape, generator=gen))
    return layer


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> dict[str, bytes]:
    """Every JPEG XL image of a packed layered scene, plus a view-dependent static layer's."""
    tmp = tmp_path_factory.mktemp("jxl")
    synthesize(SCENE, tmp / "model", progress=False)
    pack(tmp / "model", tmp / "dash", PackConfig(ladder="fixed", qps=(24,), codecs=("hevc",), jobs=2), progress=False)
    found = {}
    for seg in sorted((tmp / "dash").rglob("*.stg[kl]")):
        found |= {f"{seg.name}:{k}": v for k, v in jxl_images(seg.read_bytes()).items()}
    found |= {f"sh1:{k}": v for k, v in jxl_images(encode_static(sh1_static_layer(9))).items()}
    return found


def test_every_packaged_jxl_image_decodes_bit_exactly_in_jxl_oxide_wasm(images, tmp_path):
    assert any(k.startswith("layer.stgl:") for k in images) and any(k.startswith("gop_00001") for k in images)
    assert any(k.startswith("sh1:image.sh1_") for k in images)
    files = []
    for i, data in enumerate(images.values()):
        files.append(tmp_path / f"{i}.jxl")
        files[-1].write_bytes(data)
    decoded = browser_decode(files, tmp_path)
    assert len(decoded) == len(images)
    layouts = set()
    for (name, data), info in zip(images.items(), decoded, strict=True):
        dtype = np.uint16 if info["depth"] == 16 else np.uint8
        shape = (info["height"], info["width"], info["channels"])
        theirs = np.fromfile(info["raw"], dtype).reshape(shape)
        ours = decode_jxl(data, shape, dtype)
        assert np.array_equal(theirs, ours), f"{name}: jxl-oxide-wasm and OpenImageIO disagree"
        layouts.add((info["channels"], info["depth"]))
    assert layouts == {(1, 8), (3, 8), (4, 8), (3, 16)}  # opacity; scale; rotation; position, colour, sh1


def test_a_corrupt_image_is_one_line_from_the_browser_decoder(images, tmp_path):
    data = next(iter(images.values()))
    bad = tmp_path / "bad.jxl"
    bad.write_bytes(data[: len(data) // 3])
    result = subprocess.run(["node", str(DECODER), str(tmp_path), str(bad)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 1 and result.stderr.count("\n") == 1 and "bad.jxl" in result.stderr
