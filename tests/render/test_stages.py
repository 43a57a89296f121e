"""Each native splatter stage against its torch twin (stgs.render.stages), on the same inputs, as gsplat's
per-stage tests do: projection, binning (the tile lists id for id), forward (image and per-pixel bookkeeping),
backward (gradients); and the typed C ABI every call goes through."""

from __future__ import annotations

import shutil
import subprocess

import pytest
import torch

from stgs.native.build import CSRC
from stgs.native.library import available
from stgs.render.project import Projected, project
from stgs.render.stages import bin_tiles, composite_tiles
from tests.conftest import pinhole, random_scene

pytestmark = pytest.mark.skipif(not available(), reason="the native library could not be built here")

SCENES = [  # (N Gaussians, seed, width, height, focal, log scale, needles)
    (1, 0, 24, 16, 20.0, -2.0, False),
    (400, 2, 96, 64, 80.0, -3.0, False),
    (300, 4, 33, 47, 30.0, -2.5, False),  # partial tiles on both axes
    (120, 21, 160, 112, 120.0, -4.0, True),  # long thin rotated Gaussians: ellipse culling at work
    (2000, 9, 64, 48, 60.0, -2.0, False),  # large ones: many saturated pixels
]


def projected(n, seed, width, height, focal, log_scale, needles) -> tuple[Projected, torch.Tensor, torch.Tensor]:
    """The native projection of a random scene (float32), its opacities and colours."""
    from stgs.render.native import project_native

    args = [a.float() for a in random_scene(n, seed, log_scale=log_scale)]
    if needles:
        args[2][:, 0] *= 60.0
        args[3] = args[3] * 0.8 + 0.2
    args[0][: n // 10, 2] = -1.0  # some behind the camera
    view, K = pinhole(width, height, focal)
    return project_native(*args[:4], view, K), args[3], args[4]


def test_projection_stage_matches_its_twin():
    from stgs.render.native import project_native

    args = [a.float() for a in random_scene(500, 5)]
    args[1][:9] = 0.0  # zero quaternions: identity rotation
    args[1][9:20] *= 1e30  # huge ones: normalised without overflow
    args[0][20:31, 2] = -1.0  # behind the camera
    args[3][31:40] = 0.001  # alpha below 1/255 everywhere: no extent
    view, K = pinhole(64, 48, 50.0)
    ref = project(*[a.double() for a in args[:4]], view, K)  # same float32 inputs, in float64
    nat = project_native(*args[:4], view, K)
    assert torch.allclose(nat.means2d.double(), ref.means2d, rtol=1e-6, atol=1e-5)
    assert torch.allclose(nat.conics.double(), ref.conics, rtol=1e-6, atol=1e-6)
    assert torch.equal(nat.depths < 0, ref.depths < 0)
    assert torch.equal(nat.extents[:, 0] < 0, ref.extents[:, 0] < 0)
    assert torch.allclose(nat.extents.double(), ref.extents, rtol=1e-5, atol=1e-4)


def test_projection_gradient_matches_autograd_through_its_twin():
    """stgs_project_backward (NativeProjection) against autograd through the float64 torch projection, on the
    same float32 inputs, with the hard cases the forward test uses, a rotated camera and a skewed K."""
    from stgs.render.native import project_trainable

    args = [a.float() for a in random_scene(500, 6)]
    args[1][:9] = 0.0  # zero quaternions: identity rotation, no gradient
    args[1][9:20] *= 1e30  # huge ones
    args[1][20:25] *= 1e-30  # tiny ones
    args[0][30:41, 2] = -1.0  # behind the camera: culled, no gradient
    args[2][41:50, 0] *= 1e4  # needles
    args[2][50:60, 1] *= 1e-5  # flat discs
    view, K = pinhole(64, 48, 50.0)
    angle = torch.tensor(0.3, dtype=torch.float64)
    view[:3, :3] = torch.tensor([[angle.cos(), 0, angle.sin()], [0, 1, 0], [-angle.sin(), 0, angle.cos()]])
    view[:3, 3] = torch.tensor([0.2, -0.1, 0.4])
    K[0, 1] = 0.7
    gen = torch.Generator().manual_seed(1)
    grad_xy, grad_conic = torch.randn(500, 2, generator=gen), torch.randn(500, 3, generator=gen)
    ref_in = [a.double().requires_grad_() for a in args[:3]]
    ref = project(*ref_in, args[3].double(), view, K)
    nat_in = [a.clone().requires_grad_() for a in args[:3]]
    nat = project_trainable(*nat_in, args[3], view, K)
    live = nat.depths > 0
    assert torch.equal(live, ref.depths > 0) and (~live).sum() >= 11
    for out, dtype in ((ref, torch.float64), (nat, torch.float32)):
        xy, conic = grad_xy.to(dtype)[live], grad_conic.to(dtype)[live]
        ((out.means2d[live] * xy).sum() + (out.conics[live] * conic).sum()).backward()
    for name, r, n in zip(("means", "quats", "scales"), ref_in, nat_in, strict=True):
        assert torch.isfinite(n.grad).all(), name
        scale = r.grad.abs().amax(dim=1, keepdim=True) + 1e-12
        assert ((n.grad.double() - r.grad).abs() / scale).max() < 1e-5, name
        assert not n.grad[~live].any(), name  # nothing drawn, nothing learnt
    assert not nat_in[1].grad[:9].any()  # the zero quaternion stays the identity
    assert nat_in[0].grad[live].abs().sum() > 0


def test_native_ssim_matches_its_torch_twin_and_autograd():
    """csrc/ssim.cpp against _SSIMMap in torch and against autograd through the formula in float64: the map and
    its gradient in the image, on sizes below, at and above the 11-pixel window."""
    from stgs.metrics import _ssim_parts, ssim_map

    gen = torch.Generator().manual_seed(2)
    for height, width in ((1, 1), (3, 2), (11, 11), (20, 37), (64, 48)):
        image = torch.rand(height, width, 3, generator=gen, dtype=torch.float64)
        reference = (image + 0.2 * torch.randn(height, width, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)
        weight = torch.rand(height, width, generator=gen, dtype=torch.float64)
        exact_in = image.clone().requires_grad_()
        exact = _ssim_parts(exact_in.permute(2, 0, 1), reference.permute(2, 0, 1))[0].mean(0)
        (exact * weight).sum().backward()
        for backend in ("auto", "torch"):
            x = image.float().requires_grad_()
            values = ssim_map(x, reference.float(), backend=backend)
            (values * weight.float()).sum().backward()
            assert (values.double() - exact).abs().max() < 1e-5, (backend, height, width)
            assert (x.grad.double() - exact_in.grad).abs().max() < 1e-5 * (1 + exact_in.grad.abs().max()), backend
    with torch.no_grad():
        assert ssim_map(image.float(), image.float()).min() > 1 - 1e-5


@pytest.mark.parametrize("scene", SCENES)
def test_binning_stage_gives_the_same_tile_lists_id_for_id(scene):
    from stgs.render.native import bin_native

    proj, opacities, _ = projected(*scene)
    width, height = scene[2], scene[3]
    native = bin_native(proj.means2d, proj.conics, opacities, proj.depths, proj.extents, width, height).bins()
    twin = bin_tiles(proj.means2d, proj.conics, opacities, proj.depths, proj.extents, width, height)
    assert (native.tiles_x, native.tiles_y) == (twin.tiles_x, twin.tiles_y)
    assert torch.equal(native.tile_start, twin.tile_start)
    assert torch.equal(native.ids, twin.ids)
    assert len(native.ids) > 0


def test_binning_of_nothing_on_screen_is_empty():
    from stgs.render.native import bin_native

    proj, opacities, _ = projected(50, 3, 32, 32, 30.0, -3.0, False)
    proj.extents.fill_(-1.0)  # every Gaussian culled
    native = bin_native(proj.means2d, proj.conics, opacities, proj.depths, proj.extents, 32, 32).bins()
    twin = bin_tiles(proj.means2d, proj.conics, opacities, proj.depths, proj.extents, 32, 32)
    assert len(native.ids) == len(twin.ids) == 0
    assert torch.equal(native.tile_start, torch.zeros(5, dtype=torch.int64)) and torch.equal(
        twin.tile_start, native.tile_start)


def forward_both(scene):
    from stgs.render.native import raster_forward

    proj, opacities, colors = projected(*scene)
    width, height = scene[2], scene[3]
    background = torch.tensor([0.2, 0.1, 0.3])
    image, handle = raster_forward(proj.means2d, proj.conics, opacities, colors, background, proj.depths,
                                   proj.extents, width, height, for_backward=True)
    bins = handle.bins()
    inputs = [t.double().requires_grad_() for t in (proj.means2d, proj.conics, opacities, colors, background)]
    twin = composite_tiles(*inputs, proj.extents, bins, width, height)
    return image, handle, twin, inputs, proj


@pytest.mark.parametrize("scene", SCENES)
def test_forward_stage_matches_its_twin_on_the_same_tile_lists(scene):
    image, handle, twin, _, _ = forward_both(scene)
    trans_final, n_contrib = handle.pixels()
    # float32 against float64 arithmetic: the bound the whole-image tests hold the kernel to
    assert (image.double() - twin.image).abs().max() <= 1e-4
    assert (trans_final.double() - twin.trans_final).abs().max() <= 1e-4
    # The kernel's exp is a polynomial (2e-7 relative): a contribution right at alpha = 1/255 or at the
    # transmittance floor may fall the other way, on a few pixels at most.
    differ = (n_contrib != twin.n_contrib).float().mean().item()
    assert differ <= 1e-3, f"last contributor differs on {differ:.2%} of pixels"
    assert n_contrib.max() >= min(scene[0], 2)  # Gaussians were composited, several deep where there are several


@pytest.mark.parametrize("scene", SCENES)
def test_backward_stage_matches_autograd_through_its_twin(scene):
    from stgs.render.native import NativeComposite

    _, _, twin, inputs, proj = forward_both(scene)
    width, height = scene[2], scene[3]
    grad_out = torch.randn(height, width, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    (twin.image * grad_out).sum().backward()
    native_in = [t.detach().float().requires_grad_() for t in inputs]
    image = NativeComposite.apply(*native_in, proj.depths, proj.extents, width, height)
    (image * grad_out.float()).sum().backward()
    for name, a, b in zip(("means2d", "conics", "opacities", "colors", "background"), inputs, native_in,
                          strict=True):
        ref, got = a.grad, b.grad.double()
        peak = ref.abs().max().item()
        assert peak > 0, name
        assert (ref - got).abs().max().item() <= 2e-3 * peak, f"{name}: {(ref - got).abs().max().item():.3e}"


def test_the_library_exports_exactly_the_abi_header():
    from stgs.native.abi import declarations
    from stgs.native.library import library_path, load

    declared = {name for name in dir(load()) if name.startswith("stgs_")}
    assert declared == {line.split("(")[0].split()[-1].lstrip("*") for line in declarations().splitlines()
                        if "stgs_" in line and "(" in line and not line.lstrip().startswith("//")}
    if shutil.which("nm"):
        out = subprocess.run(["nm", "-D", "--defined-only", str(library_path())], capture_output=True, text=True,
                             check=True).stdout
        exported = {line.split()[-1] for line in out.splitlines() if line.split()[1] == "T"}
        assert exported == declared  # -fvisibility=hidden: nothing internal leaks


def test_a_call_with_a_wrong_dtype_or_arity_fails_before_running():
    from stgs.native.abi import ptr
    from stgs.native.library import load

    lib = load()
    n = 4
    f32 = [torch.zeros(n, k) for k in (3, 4, 3)] + [torch.zeros(n)]
    view, K = torch.eye(4, dtype=torch.float64), torch.eye(3, dtype=torch.float64)
    outs = [torch.zeros(n, 2), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, 2)]
    lib.stgs_project(n, *(ptr(t) for t in f32), ptr(view), ptr(K), *(ptr(t) for t in outs), 1)  # well typed
    with pytest.raises(TypeError):  # a float64 tensor where the header says float *
        lib.stgs_project(n, ptr(f32[0].double()), *(ptr(t) for t in f32[1:]), ptr(view), ptr(K),
                         *(ptr(t) for t in outs), 1)
    with pytest.raises(TypeError):  # float32 intrinsics where it says double *
        lib.stgs_project(n, *(ptr(t) for t in f32), ptr(view), ptr(K.float()), *(ptr(t) for t in outs), 1)
    with pytest.raises(TypeError):  # one argument short
        lib.stgs_project(n, *(ptr(t) for t in f32), ptr(view), ptr(K), *(ptr(t) for t in outs))
    with pytest.raises(ValueError, match="contiguous"):
        ptr(torch.zeros(4, 3).T)


@pytest.mark.skipif(shutil.which("g++") is None, reason="no C++ compiler")
def test_a_definition_that_drifts_from_the_header_does_not_compile(tmp_path):
    for source in CSRC.iterdir():
        shutil.copy(source, tmp_path / source.name)
    header = tmp_path / "stgs_abi.h"
    text = header.read_text()
    drifted = text.replace("float* depths, float* extents, int nthreads);", "float* depths, float* extents);")
    assert drifted != text
    header.write_text(drifted)
    proc = subprocess.run(["g++", "-std=c++17", "-fopenmp", "-fsyntax-only", "-I", str(tmp_path),
                           str(tmp_path / "project.cpp")], capture_output=True, text=True, check=False)
    assert proc.returncode != 0 and "conflicting declaration" in proc.stderr
