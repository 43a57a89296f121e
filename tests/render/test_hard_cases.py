"""Hard cases of the splatter: degenerate and extreme inputs stay finite, or fail clearly.

Every case runs on both backends (native float32, reference float64); each
image and every gradient must be finite, and cases with a closed form check
the value.
"""

from __future__ import annotations

import functools
import math
import operator

import pytest
import torch

from stgs.render import rasterize
from tests.conftest import pinhole, random_scene

BACKENDS = [("native", torch.float32), ("reference", torch.float64)]
W, H, F = 32, 24, 30.0


def run(args, backend, dtype, width=W, height=H, focal=F, bg=None, paths_agree=True):
    """Render with gradients; returns (image, list of input grads). On the native backend the
    inference path (no autograd) renders too: finite always, and within 1e-4 of the autograd
    image unless `paths_agree` is off."""
    view, K = pinhole(width, height, focal, dtype)
    inputs = [torch.as_tensor(a, dtype=dtype).clone().requires_grad_() for a in args]
    img = rasterize(*inputs, view, K, width, height,
                    None if bg is None else torch.as_tensor(bg, dtype=dtype), backend=backend)
    weights = torch.linspace(-1, 1, img.numel(), dtype=dtype).reshape(img.shape)
    (img * weights).sum().backward()
    if backend == "native":  # the inference path (no autograd) has arithmetic of its own
        with torch.no_grad():
            fast = rasterize(*[i.detach() for i in inputs], view, K, width, height,
                             None if bg is None else torch.as_tensor(bg, dtype=dtype), backend=backend)
        assert torch.isfinite(fast).all(), "inference image has NaN/Inf"
        if paths_agree:
            assert (fast - img).abs().max().item() <= 1e-4, "inference and autograd images differ"
    return img.detach(), [i.grad for i in inputs]


def assert_finite(img, grads):
    assert torch.isfinite(img).all(), "image has NaN/Inf"
    for g in grads:
        assert g is not None and torch.isfinite(g).all(), "gradient has NaN/Inf"


def gaussian(mean, scale=0.1, opacity=0.8, color=(1.0, 0.5, 0.25), quat=(1.0, 0, 0, 0)):
    """Args of a one-Gaussian scene."""
    scale = scale if isinstance(scale, (tuple, list)) else (scale,) * 3
    return [[list(mean)], [list(quat)], [list(scale)], [opacity], [list(color)]]


def stack(*scenes):
    return [functools.reduce(operator.iadd, (s[i] for s in scenes), []) for i in range(5)]


@pytest.mark.parametrize("backend,dtype", BACKENDS)
@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1e-2, 1.0, 1e2, 1e4])
def test_scales_across_twelve_decades(backend, dtype, scale):
    img, grads = run(gaussian((0.05, -0.03, 2.0), scale), backend, dtype)
    assert_finite(img, grads)
    if scale >= 1e2:  # covers the whole view: every pixel at 0.8 * exp(~0) of the colour
        assert torch.allclose(img[..., 0], torch.full_like(img[..., 0], 0.8), atol=1e-3)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_extremely_anisotropic(backend, dtype):
    q = (math.cos(0.3), math.sin(0.3) * 0.6, 0.0, math.sin(0.3) * 0.8)
    scenes = [gaussian((0.0, 0.0, 2.0), (1e3, 1e-6, 1e-6), 0.9, quat=q),
              gaussian((0.1, 0.1, 2.5), (1e-7, 2.0, 1e-7), 0.7),
              gaussian((-0.1, 0.0, 3.0), (1e4, 1e4, 1e-8), 0.5, quat=(0.3, 0.2, 0.9, -0.4))]
    img, grads = run(stack(*scenes), backend, dtype)
    assert_finite(img, grads)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_near_plane_straddling_and_behind(backend, dtype):
    visible = gaussian((0.0, 0.0, 2.0), 0.2, 0.7)
    behind = stack(gaussian((0.0, 0.0, -1.0), 0.5, 0.9), gaussian((0.0, 0.0, 0.0), 0.5, 0.9),
                   gaussian((0.0, 0.0, 0.0099), 0.5, 0.9))
    straddling = gaussian((0.0, 0.0, 0.0101), 0.5, 0.9, color=(0.0, 1.0, 0.0))
    img_vis, _ = run(visible, backend, dtype)
    img, grads = run(stack(visible, behind), backend, dtype)
    assert_finite(img, grads)
    assert torch.equal(img, img_vis)  # culled (z < 0.01) Gaussians contribute nothing
    for g in grads:
        assert (g[1:] == 0).all()
    img, grads = run(stack(visible, straddling), backend, dtype)
    assert_finite(img, grads)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_image_border_and_far_outside(backend, dtype):
    scenes = [gaussian((0.0, 0.0, 1e-2 * 1.5), 1e-3, 0.9),          # near, projects close to centre
              gaussian((-W / 2 / F * 2.0, 0.0, 2.0), 0.05, 0.9),     # exactly on the left border
              gaussian((1e6, -1e6, 2.0), 0.1, 0.9),                  # far outside, small
              gaussian((50.0, 0.0, 1.0), 60.0, 0.5),                 # far outside, reaches in
              gaussian((1e3, 1e3, 0.02), 1e-2, 0.9)]                 # huge off-axis Jacobian
    # The last one lands 1.5e6 px away with a near-singular conic (a = c = -b): its float32 power
    # cancels terms of ~5e9, so the two native paths' different operation orders disagree there.
    img, grads = run(stack(*scenes), backend, dtype, paths_agree=False)
    assert_finite(img, grads)
    assert img.abs().max() > 0


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_opacity_exactly_zero_and_one(backend, dtype):
    img0, grads0 = run(gaussian((0.0, 0.0, 2.0), 0.2, 0.0), backend, dtype, bg=(0.1, 0.2, 0.3))
    assert_finite(img0, grads0)
    assert torch.allclose(img0, torch.tensor([0.1, 0.2, 0.3], dtype=dtype).expand_as(img0))
    img1, grads1 = run(gaussian((0.0, 0.0, 2.0), 0.2, 1.0), backend, dtype)
    assert_finite(img1, grads1)
    assert img1.max() <= 0.99 + 1e-6  # alpha is clamped to 0.99


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_closed_form_single_isotropic_gaussian(backend, dtype):
    """One isotropic Gaussian: pixel = alpha c + (1 - alpha) bg with alpha = o exp(-d²/(2σ'²)),
    σ'² = (f s/z)² + 0.3, and alpha = 0 where it falls below 1/255."""
    s, z, o = 0.05, 2.0, 0.6
    # On the optical axis the mean projects to the principal point (16, 12), a pixel corner.
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    img, grads = run(gaussian((0.0, 0.0, z), s, o, color=(1.0, 0.5, 0.0)), backend, dtype, bg=bg)
    assert_finite(img, grads)
    var = (F * s / z) ** 2 + 0.3
    for u, v in [(16, 12), (15, 11), (17, 12), (16, 14), (19, 9), (25, 20)]:
        d2 = (u + 0.5 - 16) ** 2 + (v + 0.5 - 12) ** 2
        alpha = o * math.exp(-0.5 * d2 / var)
        alpha = alpha if alpha >= 1 / 255 else 0.0  # skipped below 1/255
        want = alpha * torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64) + (1 - alpha) * bg
        assert torch.allclose(img[v, u].double(), want, atol=2e-6), (u, v)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_closed_form_fully_opaque_front_layer(backend, dtype):
    """An opacity-1 Gaussian over the pixel hides what is behind it up to the 0.99 clamp."""
    x = 0.5 * 2.0 / F
    front = gaussian((x, x, 2.0), 0.2, 1.0, color=(0.0, 1.0, 0.0))
    back = gaussian((x, x, 4.0), 5.0, 0.5, color=(1.0, 0.0, 0.0))  # alpha ~0.5 everywhere
    img, grads = run(stack(back, front), backend, dtype)
    assert_finite(img, grads)
    want = torch.tensor([0.01 * 0.5, 0.99, 0.0], dtype=torch.float64)
    assert torch.allclose(img[12, 16].double(), want, atol=1e-5)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_zero_norm_and_huge_quaternions(backend, dtype):
    base = gaussian((0.0, 0.0, 2.0), (0.3, 0.05, 0.05), 0.8)
    identity, _ = run(base, backend, dtype)
    base[1] = [[0.0, 0.0, 0.0, 0.0]]
    zero, grads = run(base, backend, dtype)
    assert_finite(zero, grads)
    assert torch.allclose(zero, identity, atol=1e-6)
    q = torch.tensor([0.8, 0.1, -0.3, 0.5], dtype=torch.float64)
    base[1] = [(q / q.norm()).tolist()]
    unit, _ = run(base, backend, dtype)
    big = 1e30 if dtype == torch.float32 else 1e200
    base[1] = [(q * big).tolist()]
    huge, grads = run(base, backend, dtype)
    assert_finite(huge, grads)
    assert torch.allclose(huge, unit, atol=1e-5)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_thousands_on_one_pixel(backend, dtype):
    """5000 Gaussians at one spot: compositing stops when T would drop below 1e-4.

    At the centre pixel every alpha is 0.5, so exactly 13 contributions are
    added (0.5^13 >= 1e-4 > 0.5^14): pixel = c (1 - 0.5^13) + bg 0.5^13.
    """
    n = 5000
    x = 0.5 * 2.0 / F
    args = [[[x, x, 2.0 + 1e-4 * i] for i in range(n)], [[1.0, 0, 0, 0]] * n, [[0.05] * 3] * n,
            [0.5] * n, [[0.2, 0.4, 0.6]] * n]
    bg = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    img, grads = run(args, backend, dtype, bg=bg)
    assert_finite(img, grads)
    t = 0.5 ** 13
    want = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64) * (1 - t) + bg * t
    assert torch.allclose(img[12, 16].double(), want, atol=1e-5)
    # Any pixel with alpha >= 1/255 saturates within ln(1e-4)/ln(1 - 1/255) < 2350 layers:
    # nothing behind that contributes, at any pixel.
    assert (grads[4][2350:] == 0).all() and (grads[4][:13] != 0).all()


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_coincident_depths_are_ordered_by_index(backend, dtype):
    x = 0.5 * 2.0 / F
    red = gaussian((x, x, 2.0), 0.1, 0.5, color=(1.0, 0.0, 0.0))
    blue = gaussian((x, x, 2.0), 0.1, 0.5, color=(0.0, 0.0, 1.0))
    rb, grads = run(stack(red, blue), backend, dtype)
    br, _ = run(stack(blue, red), backend, dtype)
    assert_finite(rb, grads)
    assert torch.allclose(rb[12, 16].double(), torch.tensor([0.5, 0.0, 0.25], dtype=torch.float64), atol=1e-6)
    assert torch.allclose(br[12, 16].double(), torch.tensor([0.25, 0.0, 0.5], dtype=torch.float64), atol=1e-6)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
@pytest.mark.parametrize("which", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K",
                                   "background"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_inf_inputs_raise(backend, dtype, which, bad):
    args = [a.to(dtype) for a in random_scene(10, 0)]
    view, K = pinhole(W, H, F, dtype)
    bg = torch.zeros(3, dtype=dtype)
    named = dict(zip(["means", "quats", "scales", "opacities", "colors"], args, strict=True))
    named.update(viewmat=view, K=K, background=bg)
    named[which] = named[which].clone()
    named[which].view(-1)[0] = bad
    with pytest.raises(ValueError, match=f"{which} contains NaN or Inf"):
        rasterize(named["means"], named["quats"], named["scales"], named["opacities"],
                  named["colors"], named["viewmat"], named["K"], W, H, named["background"],
                  backend=backend)


def test_bad_shapes_and_ranges_raise():
    args = random_scene(4, 0)
    view, K = pinhole(W, H, F)
    with pytest.raises(ValueError, match="quats has shape"):
        rasterize(args[0], args[1][:3], *args[2:], view, K, W, H)
    with pytest.raises(ValueError, match=r"opacities must lie in \[0, 1\]"):
        rasterize(*args[:3], args[3] + 2, args[4], view, K, W, H)
    with pytest.raises(ValueError, match="width"):
        rasterize(*args, view, K, 0, H)
    with pytest.raises(ValueError, match="mix dtypes"):
        rasterize(args[0].float(), *args[1:], view, K, W, H)


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_random_extreme_mix_is_finite(backend, dtype):
    gen = torch.Generator().manual_seed(3)
    args = random_scene(400, 3, dtype=torch.float64)
    args[2] = torch.exp(torch.empty(400, 3, dtype=torch.float64).uniform_(-18, 9, generator=gen))
    args[0][:, 2] = torch.empty(400, dtype=torch.float64).uniform_(-1, 5, generator=gen)
    args[3] = torch.where(torch.rand(400, generator=gen, dtype=torch.float64) < 0.2,
                          torch.ones(400, dtype=torch.float64), args[3])
    img, grads = run(args, backend, dtype)
    assert_finite(img, grads)
