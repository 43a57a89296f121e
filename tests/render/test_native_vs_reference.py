"""The native splatter against the pure-torch reference (the oracle), gsplat style."""

from __future__ import annotations

import math

import pytest
import torch

from stgs.render import rasterize
from stgs.render.native import project_native
from stgs.render.project import project
from stgs.render.reference import composite_reference
from tests.conftest import pinhole, random_scene

NAMES = ("means", "quats", "scales", "opacities", "colors", "background")
SCENES = [  # (N Gaussians, seed, width, height, focal, log scale)
    (1, 0, 24, 16, 20.0, -2.0),
    (60, 1, 48, 32, 40.0, -3.0),
    (400, 2, 96, 64, 80.0, -3.0),
    (1500, 3, 128, 80, 100.0, -3.5),
    (300, 4, 33, 47, 30.0, -2.5),  # odd size: partial tiles on both axes
]


def render_both(n, seed, width, height, focal, log_scale, grad_out=None):
    args64 = random_scene(n, seed, log_scale=log_scale)
    bg64 = torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64)
    view, K = pinhole(width, height, focal)
    ref_in = [a.clone().requires_grad_() for a in [*args64, bg64]]
    nat_in = [a.float().clone().requires_grad_() for a in [*args64, bg64]]
    ref = rasterize(*ref_in[:5], view, K, width, height, ref_in[5], backend="reference")
    nat = rasterize(*nat_in[:5], view.float(), K.float(), width, height, nat_in[5], backend="native")
    if grad_out is not None:
        g = grad_out(ref.shape)
        (ref * g).sum().backward()
        (nat * g.float()).sum().backward()
    return ref, nat, ref_in, nat_in


@pytest.mark.parametrize("scene", SCENES)
def test_forward_matches_reference(scene):
    ref, nat, _, _ = render_both(*scene)
    assert nat.dtype == torch.float32 and ref.dtype == torch.float64
    assert nat.shape == ref.shape == (scene[3], scene[2], 3)
    assert (nat.double() - ref).abs().max().item() <= 1e-4
    assert ref.std() > 0.01  # the scene actually shows something


@pytest.mark.parametrize("scene", SCENES)
def test_inference_forward_matches_reference(scene):
    """Without autograd the native compositor takes its inference path (its own arithmetic, no
    backward bookkeeping): it meets the same bound against the oracle."""
    n, seed, width, height, focal, log_scale = scene
    args64 = random_scene(n, seed, log_scale=log_scale)
    bg64 = torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64)
    view, K = pinhole(width, height, focal)
    ref = rasterize(*args64, view, K, width, height, bg64, backend="reference")
    with torch.no_grad():
        fast = rasterize(*[a.float() for a in args64], view.float(), K.float(), width, height,
                         bg64.float(), backend="native")
    assert (fast.double() - ref).abs().max().item() <= 1e-4


@pytest.mark.parametrize("scene", SCENES)
def test_gradients_match_reference(scene):
    gen = torch.Generator().manual_seed(99)
    _, _, ref_in, nat_in = render_both(*scene, grad_out=lambda s: torch.randn(*s, generator=gen,
                                                                               dtype=torch.float64))
    for name, r, q in zip(NAMES, ref_in, nat_in, strict=True):
        a, b = r.grad, q.grad.double()
        peak = a.abs().max().item()
        assert peak > 0, f"{name}: reference gradient is all zero"
        big = a.abs() > 1e-2 * peak  # "not tiny"
        rel = ((a - b).abs() / a.abs())[big]
        assert rel.max().item() <= 1e-3, f"{name}: relative gradient error {rel.max().item():.2e}"
        assert (a - b).abs().max().item() <= 1e-3 * peak, f"{name}: absolute gradient error"


def masked_upstream(shape, gen):
    """A masked loss's upstream gradient: zero over a block (whole tiles and part rows), on scattered pixels,
    and in two of three channels (either pair) on others, random elsewhere."""
    g = torch.randn(*shape, generator=gen, dtype=torch.float64)
    h, w = shape[0], shape[1]
    g[h // 4: h // 4 + 21, w // 5: w // 5 + 37] = 0.0
    g[torch.rand(h, w, generator=gen) < 0.2] = 0.0
    g[..., :2][torch.rand(h, w, generator=gen) < 0.2] = 0.0
    g[..., 1:][torch.rand(h, w, generator=gen) < 0.2] = 0.0
    return g


@pytest.mark.parametrize("scene", SCENES[2:])
def test_gradients_under_a_masked_loss_match_reference(scene):
    """The backward pass skips the pixels without upstream gradient: the gradients stay the reference's."""
    gen = torch.Generator().manual_seed(7)
    _, _, ref_in, nat_in = render_both(*scene, grad_out=lambda s: masked_upstream(s, gen))
    for name, r, q in zip(NAMES, ref_in, nat_in, strict=True):
        a, b = r.grad, q.grad.double()
        peak = a.abs().max().item()
        assert peak > 0, f"{name}: reference gradient is all zero"
        big = a.abs() > 1e-2 * peak
        assert ((a - b).abs() / a.abs())[big].max().item() <= 1e-3, name
        assert (a - b).abs().max().item() <= 1e-3 * peak, name


@pytest.mark.parametrize("seed", [0, 1])
def test_tiling_never_changes_the_image(seed):
    """Opacity-aware extents are conservative: culling by tile equals compositing everything everywhere."""
    args = random_scene(300, seed, log_scale=-2.5)
    view, K = pinhole(40, 40, 35.0)
    proj = project(*args[:4], view, K)
    bg = torch.zeros(3, dtype=torch.float64)
    tiled = composite_reference(proj, args[3], args[4], 40, 40, bg, tile=8)
    dense = composite_reference(proj, args[3], args[4], 40, 40, bg, tile=40, cull=False)
    assert (tiled - dense).abs().max().item() < 1e-12


def test_reference_float32_close_to_float64():
    args = random_scene(200, 7)
    view, K = pinhole(48, 32, 40.0)
    r64 = rasterize(*args, view, K, 48, 32, backend="reference")
    r32 = rasterize(*[a.float() for a in args], view.float(), K.float(), 48, 32, backend="reference")
    assert r32.dtype == torch.float32
    assert (r32.double() - r64).abs().max().item() <= 1e-4


def test_gradcheck_reference_tiny_scene():
    args = random_scene(3, 11, log_scale=-1.5)
    args[3] = args[3] * 0.5 + 0.25  # away from the alpha thresholds
    view, K = pinhole(8, 6, 6.0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    inputs = [a.clone().requires_grad_() for a in [*args, bg]]

    def fn(means, quats, scales, opacities, colors, background):
        return rasterize(means, quats, scales, opacities, colors, view, K, 8, 6, background,
                         backend="reference")

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_auto_backend_choice():
    from stgs.render import choose_backend

    cpu = torch.device("cpu")
    assert choose_backend(torch.float32, cpu) == "native"
    assert choose_backend(torch.float64, cpu) == "reference"
    with pytest.raises(ValueError, match="float32"):
        choose_backend(torch.float64, cpu, "native")


@pytest.mark.parametrize("backend,dtype", [("native", torch.float32), ("reference", torch.float64)])
def test_empty_scene_is_background(backend, dtype):
    view, K = pinhole(20, 10, 10.0, dtype)
    empty = [torch.zeros(0, 3, dtype=dtype), torch.zeros(0, 4, dtype=dtype),
             torch.zeros(0, 3, dtype=dtype), torch.zeros(0, dtype=dtype), torch.zeros(0, 3, dtype=dtype)]
    bg = torch.tensor([0.5, 0.25, 1.0], dtype=dtype)
    img = rasterize(*empty, view, K, 20, 10, bg, backend=backend)
    assert img.shape == (10, 20, 3) and torch.equal(img, bg.expand(10, 20, 3))


def test_needles_bin_to_fewer_tiles_than_their_boxes_and_render_the_same():
    """Long thin rotated Gaussians: their boxes cover many tiles the ellipse never reaches. The native
    binning skips those (fewer pairs than box tiles) and the image and gradients still match the oracle."""
    n, width, height = 120, 160, 112
    args = random_scene(n, 21, log_scale=-4.0)
    args[2][:, 0] *= 60.0  # one long axis; the random rotations lay it in every direction
    args[3] = args[3] * 0.8 + 0.2
    view, K = pinhole(width, height, 120.0)
    proj = project_native(*[a.float() for a in args[:4]], view.float(), K.float())
    from stgs.render.native import raster_forward

    _, handle = raster_forward(proj.means2d, proj.conics, args[3].float(), args[4].float(), torch.zeros(3),
                               proj.depths, proj.extents, width, height)
    box_tiles = 0
    for (mx, my), (ex, ey) in zip(proj.means2d.tolist(), proj.extents.tolist(), strict=True):
        if ex < 0:
            continue
        u0, u1 = max(0, math.ceil(mx - ex - 0.5)), min(width - 1, math.floor(mx + ex - 0.5))
        v0, v1 = max(0, math.ceil(my - ey - 0.5)), min(height - 1, math.floor(my + ey - 0.5))
        if u0 <= u1 and v0 <= v1:
            box_tiles += (u1 // 16 - u0 // 16 + 1) * (v1 // 16 - v0 // 16 + 1)
    assert handle.pairs() < 0.8 * box_tiles, (handle.pairs(), box_tiles)
    g = torch.randn(height, width, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    ref_in = [a.clone().requires_grad_() for a in args]
    nat_in = [a.float().clone().requires_grad_() for a in args]
    ref = rasterize(*ref_in, view, K, width, height, backend="reference")
    nat = rasterize(*nat_in, view.float(), K.float(), width, height, backend="native")
    assert ref.abs().max() > 0.1 and (nat.double() - ref).abs().max() <= 1e-4
    (ref * g).sum().backward()
    (nat * g.float()).sum().backward()
    for a, b in zip(ref_in, nat_in, strict=True):
        assert (a.grad - b.grad.double()).abs().max() <= 1e-3 * a.grad.abs().max()


def flat_grads(inputs: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([x.grad.flatten() for x in inputs])


def test_native_gradients_are_the_same_bytes_on_every_run():
    """Per-thread partial sums must not depend on which thread took which tile (training is seeded)."""
    args = [a.float() for a in random_scene(3000, 7, log_scale=-3.0)]
    view, K = pinhole(128, 96, 100.0)
    grad_out = torch.randn(96, 128, 3, generator=torch.Generator().manual_seed(3))
    threads = torch.get_num_threads()
    torch.set_num_threads(4)  # more threads than this machine's cores: scheduling varies between runs
    try:
        runs = []
        for _ in range(12):
            inputs = [a.clone().requires_grad_() for a in args]
            (rasterize(*inputs, view.float(), K.float(), 128, 96, backend="native") * grad_out).sum().backward()
            runs.append(flat_grads(inputs))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(runs[0], r) for r in runs[1:])


def test_thread_count_never_changes_the_image():
    """Enough Gaussians that the depth sort and the binning split across threads (plus a block at
    one exact depth, where only a stable sort keeps the order): 1 and 3 threads give the same bytes."""
    args = [a.float() for a in random_scene(40_000, 8, log_scale=-3.5)]
    args[0][:2000, 2] = 3.0
    view, K = pinhole(160, 120, 120.0)
    threads = torch.get_num_threads()
    images = []
    try:
        for count in (1, 3):
            torch.set_num_threads(count)
            with torch.no_grad():
                fast = rasterize(*args, view.float(), K.float(), 160, 120, backend="native")
            tracked = rasterize(*[a.clone().requires_grad_() for a in args], view.float(), K.float(),
                                160, 120, backend="native")
            images.append((fast, tracked.detach()))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(images[0][0], images[1][0]) and torch.equal(images[0][1], images[1][1])
    assert (images[0][0] - images[0][1]).abs().max().item() <= 1e-4


def test_reused_buffers_never_leak_between_frames():
    """The library keeps a freed context's buffers for the next frame: sizes and Gaussian counts that
    change between calls, and a forward whose backward is still pending, give the same bytes as before."""
    big = [a.float() for a in random_scene(2000, 11, log_scale=-3.0)]
    small = [a.float() for a in random_scene(40, 12, log_scale=-2.0)]
    view, K = pinhole(96, 64, 80.0)
    view_s, K_s = pinhole(33, 47, 30.0)

    def frame(args, v, k, w, h):
        return rasterize(*args, v.float(), k.float(), w, h, backend="native")

    def grads():
        inputs = [a.clone().requires_grad_() for a in big]
        image = frame(inputs, view, K, 96, 64)
        frame(small, view_s, K_s, 33, 47)  # a forward between this forward and its backward
        image.sum().backward()
        return flat_grads(inputs)

    first_big, first_small, first_grads = frame(big, view, K, 96, 64), frame(small, view_s, K_s, 33, 47), grads()
    for _ in range(3):
        assert torch.equal(frame(small, view_s, K_s, 33, 47), first_small)
        assert torch.equal(frame(big, view, K, 96, 64), first_big)
        assert torch.equal(grads(), first_grads)
