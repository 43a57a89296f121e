"""Model dir save/load: versioned, no pickle, every size checked before use."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file, save_file

from stgs.errors import StgsError
from stgs.model.store import load_model, read_meta, save_model
from tests.model.test_gop import random_model


@pytest.fixture
def model_dir(tmp_path):
    gops = [random_model(n=64, gop_size=6, seed=s) for s in range(2)]
    save_model(tmp_path / "m", gops, fps=24.0, extra={"note": "test"})
    return tmp_path / "m", gops


def test_round_trip_is_bit_exact(model_dir):
    path, gops = model_dir
    meta, loaded = load_model(path)
    assert meta.num_gops == 2 and meta.fps == 24.0 and meta.shape == gops[0].shape
    assert meta.extra == {"note": "test"}
    for a, b in zip(gops, loaded, strict=True):
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys()
        assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_files_are_safetensors_with_versioned_json(model_dir):
    path, _ = model_dir
    doc = json.loads((path / "model.json").read_text())
    assert doc["format"] == "streamstgs-model" and doc["version"] == 1, "a scene without a static layer stays format 1"
    assert [g["file"] for g in doc["gops"]] == ["gop_0000.safetensors", "gop_0001.safetensors"]
    header_len = int.from_bytes((path / "gop_0000.safetensors").read_bytes()[:8], "little")
    header = json.loads((path / "gop_0000.safetensors").read_bytes()[8:8 + header_len])
    assert json.loads(header["__metadata__"]["streamstgs"]) == {"format": "streamstgs-model", "version": 1}
    assert not list(path.glob(".*")), "no temp files left behind"


def corrupt(path, name, fn):
    tensors = load_file(str(path / "gop_0001.safetensors"))
    fn(tensors)
    save_file(tensors, str(path / "gop_0001.safetensors"))


@pytest.mark.parametrize("damage,message", [
    (lambda t: t.__setitem__("features", t["features"][:, :10].contiguous()), "has shape"),
    (lambda t: t.pop("xyz"), "missing"),
    (lambda t: t["color"].__setitem__((0, 0), float("nan")), "NaN or Inf"),
    (lambda t: t.__setitem__("extra", torch.zeros(1)), "unknown"),
])
def test_bad_tensors_are_clear_errors(model_dir, damage, message):
    path, _ = model_dir
    corrupt(path, "gop_0001.safetensors", damage)
    with pytest.raises(StgsError, match=message):
        load_model(path)


def test_bad_metadata_is_a_clear_error(model_dir):
    path, _ = model_dir
    doc = json.loads((path / "model.json").read_text())
    for key, value, message in [("version", 99, "not supported"), ("capacity", 1 << 40, "capacity"),
                                ("gop_size", -1, "gop_size"), ("fps", "fast", "fps"),
                                ("fps", 0.0001, r"'fps' must be a number in 1\.\.1000"),  # looped forever
                                ("fps", True, "fps"), ("fps", float("nan"), "fps"), ("capacity", 16.0, "capacity")]:
        bad = dict(doc, **{key: value})
        (path / "model.json").write_text(json.dumps(bad))
        with pytest.raises(StgsError, match=message):
            read_meta(path)
    bad = dict(doc, gops=[{"file": "../escape.safetensors"}])
    (path / "model.json").write_text(json.dumps(bad))
    with pytest.raises(StgsError, match="plain file name"):
        read_meta(path)


def test_garbage_files_are_clear_errors(model_dir, tmp_path):
    path, _ = model_dir
    (path / "gop_0000.safetensors").write_bytes(b"\x80\x04not a safetensors file")
    with pytest.raises(StgsError, match="unreadable GOP file"):
        load_model(path)
    (path / "model.json").write_text("{not json")
    with pytest.raises(StgsError, match="not valid JSON"):
        load_model(path)
    (path / "model.json").write_text("[" * 100_000)  # a RecursionError traceback before
    with pytest.raises(StgsError, match=r"nested too deeply|not valid JSON"):
        load_model(path)
    (path / "model.json").write_bytes(b" " * (17 << 20))
    with pytest.raises(StgsError, match=r"over the .*-byte limit"):
        load_model(path)
    with pytest.raises(StgsError, match="not a model dir"):
        load_model(tmp_path / "nowhere")
