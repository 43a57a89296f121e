"""Model format 2: a static layer beside the per-GOP dynamic layers (docs/MODEL_FORMAT.md)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from stgs.camera import Camera, intrinsics, look_at
from stgs.errors import StgsError
from stgs.model.gop import Gaussians
from stgs.model.renderer import FrameRenderer
from stgs.model.static import StaticLayer, merge
from stgs.model.store import load_gop, load_model, load_static, read_meta, save_model
from stgs.native.library import available
from stgs.render import rasterize
from tests.model.test_gop import random_model

FORMAT1 = Path(__file__).parent / "fixtures" / "format1"
"""A format-1 model dir and its renders (frames 0 and 3 of both GOPs, torch path), written by the build before
format 2 existed."""
CAM = Camera("c", intrinsics(32, 24, 60.0), look_at((0.0, 0.3, -2.5), (0.0, 0.0, 0.0)), 32, 24)


def random_static(n: int = 64, seed: int = 0, sh_degree: int = 0) -> StaticLayer:
    gen = torch.Generator().manual_seed(seed)
    layer = StaticLayer(n, sh_degree)
    with torch.no_grad():
        layer.xyz.copy_(torch.randn(n, 3, generator=gen) * 0.6)
        layer.log_scale.copy_(torch.randn(n, 3, generator=gen) * 0.3 - 2.5)
        layer.rotation.copy_(torch.randn(n, 4, generator=gen))
        layer.opacity_logit.copy_(torch.randn(n, generator=gen))
        layer.color.copy_(torch.rand(n, 3, generator=gen))
        if sh_degree:
            layer.sh1.copy_(torch.randn(n, 3, 3, generator=gen) * 0.2)
    return layer


def test_format1_dirs_load_and_render_unchanged(tmp_path):
    meta, gops = load_model(FORMAT1)
    assert meta.version == 1 and meta.static is None and load_static(FORMAT1, meta) is None
    expected = load_file(str(FORMAT1 / "expected_renders.safetensors"))
    for name, image in expected.items():
        k, i = int(name[3]), int(name.split("frame")[1])
        # The bytes load unchanged (below); the render matches up to float32 rounding, whose last bits depend on
        # the CPU torch's kernels run on (an AVX-512 Xeon and an AVX2 EPYC differ by up to 1e-6).
        torch.testing.assert_close(FrameRenderer(gops[k], native=False).render(i, CAM), image, atol=1e-5, rtol=0,
                                   msg=name)
    # Saved again without a static layer: byte for byte the files the earlier build wrote.
    save_model(tmp_path / "again", gops, meta.fps, meta.extra)
    for name in ("model.json", "gop_0000.safetensors", "gop_0001.safetensors"):
        assert (tmp_path / "again" / name).read_bytes() == (FORMAT1 / name).read_bytes(), name


def test_format2_round_trip_is_bit_exact(tmp_path):
    gops = [random_model(n=36, gop_size=4, seed=s) for s in range(2)]
    for sh in (0, 1):
        static = random_static(100, seed=3, sh_degree=sh)
        meta = save_model(tmp_path / f"m{sh}", gops, 30.0, {"note": "layered"}, static=static)
        doc = json.loads((tmp_path / f"m{sh}" / "model.json").read_text())
        assert doc["version"] == 2 and doc["static"]["grid_side"] == 10 and doc["static"]["sh_degree"] == sh
        read = read_meta(tmp_path / f"m{sh}")
        assert read.static == meta.static and read.shape == gops[0].shape
        loaded = load_static(tmp_path / f"m{sh}", read)
        assert all(torch.equal(a, b) for a, b in zip(static.state_dict().values(),
                                                     loaded.state_dict().values(), strict=True))


@pytest.mark.parametrize("native", [False, True])
def test_an_empty_static_layer_renders_exactly_as_format1(native):
    if native and not available():
        pytest.skip("native splatter not built")
    _, gops = load_model(FORMAT1)
    empty = random_static(49)
    with torch.no_grad():
        empty.opacity_logit.fill_(-10.0)  # opacity 4.5e-5: below 1/255, never drawn
    for i in (0, 2):
        alone = FrameRenderer(gops[0], native=native).render(i, CAM)
        layered = FrameRenderer(gops[0], native=native, static=empty).render(i, CAM)
        assert torch.equal(alone, layered)


def _raster(g: Gaussians, backend: str) -> torch.Tensor:
    return rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, CAM.viewmat.float(), CAM.K.float(),
                     CAM.width, CAM.height, backend=backend)


def test_static_and_dynamic_in_one_call_are_depth_merged():
    static = random_static(64, seed=1)
    renderer = FrameRenderer(random_model(n=36, gop_size=4, seed=2), native=False, static=static)
    g = renderer.gaussians(1, CAM)
    assert g.means.shape[0] == 64 + 36
    n_s = 64
    flipped = Gaussians(*(torch.cat([t[n_s:], t[:n_s]]) for t in (g.means, g.quats, g.scales, g.opacities,
                                                                  g.colors)))
    reference = _raster(g, "reference")
    # Layer order in the arrays does not matter: one depth order for both layers.
    assert torch.allclose(reference, _raster(flipped, "reference"), atol=1e-6)
    assert reference.std() > 0.01
    if available():
        assert torch.allclose(_raster(g, "native"), reference, atol=5e-3)
        native = FrameRenderer(renderer.model, native=True, static=static)
        assert torch.allclose(native.render(1, CAM), renderer.render(1, CAM), atol=5e-3)
    # A static Gaussian in front of a dynamic one hides it; behind it, it is hidden.
    one = Gaussians(torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.3),
                    torch.tensor([0.99]), torch.tensor([[1.0, 0.0, 0.0]]))
    for z, seen in ((-1.0, 1), (1.0, 0)):  # the camera looks along +z from z = -2.5: z = -1 is in front
        other = Gaussians(torch.tensor([[0.0, 0.0, z]]), one.quats, one.scales, one.opacities,
                          torch.tensor([[0.0, 1.0, 0.0]]))
        centre = _raster(merge(other, one), "reference")[12, 16]
        assert int(centre.argmax()) == seen


def test_static_view_is_reused_while_the_camera_stays():
    static = random_static(64, seed=1, sh_degree=1)
    renderer = FrameRenderer(random_model(n=36, gop_size=4, seed=2), native=False, static=static)
    first = renderer.static_gaussians(CAM)
    assert renderer.static_gaussians(CAM) is first
    moved = Camera("c", CAM.K, look_at((0.5, 0.3, -2.5), (0.0, 0.0, 0.0)), 32, 24)
    other = renderer.static_gaussians(moved)
    assert other is not first and not torch.equal(other.colors, first.colors)  # sh1: colour follows the view


def test_bad_layers_are_clear_errors(tmp_path):
    gops = [random_model(n=36, gop_size=4, seed=0)]
    with pytest.raises(StgsError, match="square"):
        save_model(tmp_path / "a", gops, 30.0, static=random_static(50))
    nan = random_static(49)
    with torch.no_grad():
        nan.color[3, 1] = float("nan")
    with pytest.raises(StgsError, match="NaN"):
        save_model(tmp_path / "b", gops, 30.0, static=nan)
    assert not (tmp_path / "b" / "model.json").exists()
    path = tmp_path / "c"
    save_model(path, gops, 30.0, static=random_static(49))
    doc = json.loads((path / "model.json").read_text())
    for static, message in [(dict(doc["static"], capacity=50), "square"), (dict(doc["static"], sh_degree=3),
                                                                             "sh_degree"),
                            (dict(doc["static"], file="../x"), "plain file name"), ([1], "object")]:
        (path / "model.json").write_text(json.dumps(dict(doc, static=static)))
        with pytest.raises(StgsError, match=message):
            read_meta(path)
    (path / "model.json").write_text(json.dumps(doc))
    tensors = load_file(str(path / "static.safetensors"))
    tensors["opacity_logit"][0] = float("inf")
    save_file(tensors, str(path / "static.safetensors"))
    with pytest.raises(StgsError, match="NaN or Inf"):
        load_static(path, read_meta(path))
    # A dynamic layer of another capacity than the scene's.
    save_model(tmp_path / "d", [random_model(n=25, gop_size=4)], 30.0)
    shutil.copy(tmp_path / "d" / "gop_0000.safetensors", path / "gop_0000.safetensors")
    with pytest.raises(StgsError, match=r"model\.json implies"):
        load_gop(path, read_meta(path), 0)
