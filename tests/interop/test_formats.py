"""The three file formats: read back to the same bytes (PLY, glb) or within SPZ's quantisation, against the format's
reference tools (Niantic's SPZ loader, the Khronos glTF validator), foreign INRIA files, and bad input."""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from stgs.cli.browser import WEB
from stgs.interop import gltf, ply, spz
from stgs.interop.files import read_splats, write_splats
from stgs.interop.sh import C0
from stgs.interop.splats import InteropError, Splats, from_static, to_static
from stgs.interop.static import import_static
from tests.conftest import run_stgs
from tests.interop.conftest import random_splats
from tests.web.conftest import NODE


@pytest.mark.parametrize("codec", [ply, gltf], ids=["ply", "glb"])
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_a_file_read_back_and_written_again_has_the_same_bytes(codec, degree):
    first = codec.encode(random_splats(500, degree))
    back = codec.decode(first, "test")
    assert back.count == 500 and back.sh_degree == degree
    assert codec.encode(back) == first


@pytest.mark.parametrize("codec", [ply, gltf], ids=["ply", "glb"])
def test_a_static_layer_written_read_into_a_layer_and_written_again_has_the_same_bytes(codec):
    layer = to_static(random_splats(400, 1, seed=3))
    first = codec.encode(from_static(layer))
    again = codec.encode(from_static(to_static(codec.decode(first, "test"))))
    assert again == first


def hard_splats(n: int = 4000) -> Splats:
    """Random Gaussians where the parameterisations are least injective or overflow: log-scales near 0 and past
    float32's exp range, logits near 0 and past the sigmoid's saturation, quaternions far from unit norm."""
    s = random_splats(n, 1, seed=11)
    rng = np.random.default_rng(12)
    s.log_scales[: n // 4] *= np.float32(1e-4)
    s.log_scales[n // 4: n // 2] *= np.float32(80.0)
    s.opacity_logits[: n // 4] *= np.float32(1e-5)
    s.opacity_logits[n // 4: n // 2] *= np.float32(60.0)
    s.quats *= rng.uniform(0.5, 2.0, (n, 1)).astype(np.float32)
    return s


@pytest.mark.parametrize("codec", [ply, gltf], ids=["ply", "glb"])
def test_canonical_gaussians_read_back_as_the_same_values(codec):
    # What an exported frame is (Splats.canonical): every lossless format gives back exactly these float32
    # values, so the file renders bit for bit as what was exported, whatever the CPU's float32 arithmetic.
    s = hard_splats().canonical()
    back = codec.decode(codec.encode(s), "test")
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(back, name), getattr(s, name)), name
    again = s.canonical()
    assert all(np.array_equal(getattr(again, f), getattr(s, f)) for f in ("log_scales", "quats", "opacity_logits"))


def test_ply_keeps_the_inria_values_exactly():
    s = random_splats(300, 3)
    back = ply.decode(ply.encode(s), "test")
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(back, name), getattr(s, name)), name


def test_spz_round_trip_is_within_its_quantisation():
    s = random_splats(2000, 1)
    s.sh = np.clip(s.sh, -0.9, 0.9)
    back = spz.decode(spz.encode(s), "test")
    assert np.abs(back.means - s.means).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(back.log_scales - s.log_scales).max() <= 0.5 / 16 + 1e-6
    assert np.abs(back.sh[:, 0] - s.sh[:, 0]).max() <= 0.5 / (0.15 * 255) + 1e-6
    assert np.abs(back.sh[:, 1:] - s.sh[:, 1:]).max() <= 4.5 / 128 + 1e-6  # rounded to 1/128, then to buckets of 8
    o, ob = (1 / (1 + np.exp(-x.astype(np.float64))) for x in (s.opacity_logits, back.opacity_logits))
    assert np.abs(ob - o).max() <= 0.5 / 255 + 1e-6
    q = s.quats / np.linalg.norm(s.quats, axis=1, keepdims=True)
    angle = 2 * np.arccos(np.clip(np.abs((q * back.quats).sum(1)), 0, 1))
    assert angle.max() < math.radians(0.5)  # 9 bits over 1/sqrt(2) per component
    again = spz.decode(spz.encode(back), "test")  # quantised values come back to themselves
    assert np.array_equal(again.means, back.means) and np.array_equal(again.sh, back.sh)
    assert np.array_equal(again.log_scales, back.log_scales)


def node_json(script: str, path) -> dict:
    run = subprocess.run([NODE, str(WEB / "tools" / script), str(path)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.fixture
def need_node_modules():
    if NODE is None or not (WEB / "node_modules" / "@spz-loader").is_dir():
        pytest.skip("Node.js and web/'s packages are not installed")


def test_niantics_reference_loader_reads_our_spz_as_we_do(tmp_path, need_node_modules):
    s = random_splats(700, 1, seed=5)
    write_splats(tmp_path / "a.spz", s)
    ours = read_splats(tmp_path / "a.spz")
    ref = node_json("spz-reference.mjs", tmp_path / "a.spz")
    n = ours.count
    assert ref["numPoints"] == n and ref["shDegree"] == 1
    arr = lambda key, width: np.asarray(ref[key], dtype=np.float64).reshape(n, width)  # noqa: E731
    assert np.abs(arr("positions", 3) - ours.means).max() == 0
    assert np.abs(arr("scales", 3) - np.exp(ours.log_scales.astype(np.float64))).max() < 1e-5
    assert np.abs(arr("rotations", 4)[:, [3, 0, 1, 2]] - ours.quats).max() < 1e-6
    assert np.abs(arr("colors", 3) - (0.5 + C0 * ours.sh[:, 0])).max() < 1e-6
    # alpha bytes 0 and 255 are 0 and 1 for the reference; we keep their logits finite (opacity 0.5/255 from them)
    assert np.abs(arr("alphas", 1)[:, 0] - 1 / (1 + np.exp(-ours.opacity_logits.astype(np.float64)))).max() \
        <= 0.5 / 255 + 1e-6
    assert np.abs(arr("sh", 9).reshape(n, 3, 3) - ours.sh[:, 1:]).max() < 1e-6


def test_the_glb_passes_the_khronos_validator(tmp_path, need_node_modules):
    write_splats(tmp_path / "a.glb", random_splats(200, 1))
    report = node_json("gltf-validate.mjs", tmp_path / "a.glb")["issues"]
    errors = [m for m in report["messages"] if m["severity"] == 0]
    # The validator (its newest release, 2.0.0-dev.3.10) predates KHR_gaussian_splatting: it knows neither the
    # extension nor the attribute semantics it defines, and calls exactly those invalid names. Nothing else fails.
    prefix = "/meshes/0/primitives/0/attributes/KHR_gaussian_splatting:"
    assert all(m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" and m["pointer"].startswith(prefix) for m in errors)
    assert len(errors) == 7 and report["numWarnings"] == 0
    doc, _ = gltf._chunks((tmp_path / "a.glb").read_bytes(), "a.glb")
    primitive = doc["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0 and doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
    assert primitive["extensions"]["KHR_gaussian_splatting"] == {"kernel": "ellipse",
                                                                 "colorSpace": "srgb_rec709_display"}
    kinds = {name: doc["accessors"][i]["type"] for name, i in primitive["attributes"].items()}
    assert kinds == {"POSITION": "VEC3", "KHR_gaussian_splatting:ROTATION": "VEC4", "KHR_gaussian_splatting:SCALE":
                     "VEC3", "KHR_gaussian_splatting:OPACITY": "SCALAR",
                     **{f"KHR_gaussian_splatting:SH_DEGREE_{d}_COEF_{c}": "VEC3" for d, c in
                        ((0, 0), (1, 0), (1, 1), (1, 2))}}


def reference_ply(path, n: int, seed: int = 7) -> dict[str, np.ndarray]:
    """An INRIA PLY of degree 3 as the reference 3DGS code writes it (its attribute list, in its order)."""
    rng = np.random.default_rng(seed)
    names = ["x", "y", "z", "nx", "ny", "nz", *(f"f_dc_{i}" for i in range(3)), *(f"f_rest_{i}" for i in range(45)),
             "opacity", *(f"scale_{i}" for i in range(3)), *(f"rot_{i}" for i in range(4))]
    table = np.zeros(n, dtype=[(name, "f4") for name in names])
    values = {name: rng.normal(size=n).astype(np.float32) * (0.2 if name.startswith("f_rest") else 1.0)
              for name in names if name not in ("nx", "ny", "nz")}
    for name, v in values.items():
        table[name] = v
    PlyData([PlyElement.describe(table, "vertex")]).write(str(path))
    return values


def test_a_foreign_degree_3_ply_imports_with_its_higher_degrees_folded(tmp_path):
    values = reference_ply(tmp_path / "point_cloud.ply", 150)
    splats = read_splats(tmp_path / "point_cloud.ply")
    assert splats.sh_degree == 3
    assert np.array_equal(splats.means[:, 1], values["y"]) and np.array_equal(splats.quats[:, 3], values["rot_3"])
    # f_rest is channel-major: red's 15 higher coefficients, then green's, then blue's
    assert np.array_equal(splats.sh[:, 1:, 1], np.stack([values[f"f_rest_{15 + k}"] for k in range(15)], 1))
    layer, report = import_static(tmp_path / "point_cloud.ply")
    assert (report["grid_side"], report["padded"], report["file_sh_degree"]) == (13, 19, 3)
    assert layer.capacity == 169 and layer.sh_degree == 1
    back = from_static(layer).select(np.arange(150))
    assert np.allclose(back.sh, splats.sh[:, :4], atol=1e-6)  # without cameras: degrees 2 and 3 dropped
    assert np.array_equal(back.means, splats.means)


def truncated(data: bytes) -> bytes:
    return data[:len(data) - 37]


def wrong_properties(data: bytes) -> bytes:
    return data.replace(b"property float f_rest_8\n", b"", 1)


def with_nan(data: bytes) -> bytes:
    head = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:head] + np.float32(np.nan).tobytes() + data[head + 4:]


def too_many(data: bytes) -> bytes:
    return data.replace(b"element vertex 50\n", b"element vertex 99999999\n", 1)


@pytest.mark.parametrize("spoil", [truncated, wrong_properties, with_nan, too_many])
def test_a_bad_ply_is_one_clear_line_and_nothing_is_written(tmp_path, spoil):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(spoil(ply.encode(random_splats(50, 1))))
    with pytest.raises(InteropError):
        read_splats(bad)
    out = tmp_path / "model"
    run = run_stgs("train", str(tmp_path / "nowhere"), str(out), "--static-from", str(bad))
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and run.stderr.startswith("stgs: ")
    assert "Traceback" not in run.stderr and not out.exists()
    assert "bad.ply" in run.stderr


def test_a_file_larger_than_the_grid_asked_for_keeps_its_most_visible_gaussians(tmp_path):
    s = random_splats(30, 0, seed=11)
    write_splats(tmp_path / "big.ply", s)
    layer, report = import_static(tmp_path / "big.ply", side=5)
    assert (report["grid_side"], report["dropped"], report["padded"], layer.capacity) == (5, 5, 0, 25)
    o = 1 / (1 + np.exp(-s.opacity_logits.astype(np.float64)))
    visibility = o * np.exp(s.log_scales.astype(np.float64).sum(1))
    kept = np.sort(np.argsort(-visibility)[:25])  # the 25 most visible, in file order
    assert np.array_equal(layer.xyz.detach().numpy(), s.means[kept])
