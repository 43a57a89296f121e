"""Training losses against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch

from stgs.camera import Camera, intrinsics
from stgs.metrics import SSIM_C1, SSIM_C2, psnr, ssim, ssim_map
from stgs.native.library import available
from stgs.train import losses
from stgs.train.dynamic import gop_dynamic_masks, variance_mask
from stgs.train.images import tensor_views


def test_temporal_huber_by_hand():
    # two features of one Gaussian, one channel: differences 0.005 (quadratic zone) and 0.03 (linear zone)
    f = torch.tensor([[[0.0]], [[0.005]], [[0.035]]])
    # huber(d) = 0.5 d² for |d| <= δ, δ (|d| - 0.5 δ) beyond; δ = 0.01
    expected = (0.5 * 0.005 ** 2 + 0.01 * (0.03 - 0.005)) / 2
    assert losses.temporal_huber(f, 0.01).item() == pytest.approx(expected, rel=1e-5)
    assert losses.temporal_huber(f[:1], 0.01).item() == 0.0


def test_temporal_huber_gradient_matches_autograd_through_torch_huber_loss():
    gen = torch.Generator().manual_seed(3)
    # steps from 0 to 0.05 either side of δ = 0.01: both zones and their joint
    f = (torch.rand(9, 40, 4, generator=gen, dtype=torch.float64) * 0.05).cumsum(0).requires_grad_()
    reference = torch.nn.functional.huber_loss(f[1:], f[:-1], delta=0.01)
    (expected,) = torch.autograd.grad(reference * 3.0, f)
    value = losses.temporal_huber(f, 0.01)
    (got,) = torch.autograd.grad(value * 3.0, f)
    assert value.item() == pytest.approx(reference.item(), rel=1e-12)
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-18)
    assert torch.autograd.gradcheck(lambda x: losses.temporal_huber(x, 0.01), (f,))
    two = f[:2].detach().clone().requires_grad_()
    (edge,) = torch.autograd.grad(losses.temporal_huber(two, 0.01), two)  # E = 2: the first and last frame only
    assert torch.allclose(edge[0], -edge[1]) and edge.abs().sum() > 0


@pytest.mark.skipif(not available(), reason="the native library could not be built here")
def test_native_window_and_temporal_huber_matches_the_slice_and_the_torch_term():
    gen = torch.Generator().manual_seed(5)
    # 2,500 columns: the kernel's 1,024-column blocks and a ragged last one; steps either side of δ = 0.01
    base = (torch.rand(7, 625, 4, generator=gen) * 0.05 - 0.02).cumsum(0)
    for first in (0, 2, 4):  # the window at the start, inside and at the end of the frames
        upstream = torch.randn(3, 625, 4, generator=gen)
        grads, values = [], []
        for backend in ("torch", "auto"):
            f = base.clone().requires_grad_()
            block, value = losses.window_and_temporal_huber(f, first, 3, 0.01, backend=backend)
            assert torch.equal(block.detach(), base[first:first + 3])
            ((block * upstream).sum() + 2.5 * value).backward()
            grads.append(f.grad)
            values.append(value.item())
        assert values[1] == pytest.approx(values[0], rel=1e-5)
        assert torch.allclose(grads[1], grads[0], rtol=1e-5, atol=1e-9)
    f = base.clone().requires_grad_()
    block, _ = losses.window_and_temporal_huber(f, 1, 3, 0.01)
    block.sum().backward()  # the window's gradient alone: ones on its rows, zeros elsewhere
    assert torch.equal(f.grad, torch.zeros_like(base).index_fill_(0, torch.arange(1, 4), 1.0))
    two = base[:2].clone().requires_grad_()
    (edge,) = torch.autograd.grad(losses.window_and_temporal_huber(two, 0, 1, 0.01)[1], two)
    assert torch.allclose(edge[0], -edge[1]) and edge.abs().sum() > 0


@pytest.mark.skipif(not available(), reason="the native library could not be built here")
def test_native_temporal_huber_value_does_not_depend_on_the_thread_count():
    f = (torch.rand(12, 3000, 16, generator=torch.Generator().manual_seed(1)) * 0.03).cumsum(0)
    threads = torch.get_num_threads()
    try:
        values = []
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            values.append(losses.window_and_temporal_huber(f, 0, 3, 0.01)[1].item())
    finally:
        torch.set_num_threads(threads)
    assert values[0] == values[1] == values[2]


def test_window_and_temporal_huber_refuses_a_window_outside_the_frames():
    f = torch.zeros(5, 4, 16)
    for first, window in ((-1, 3), (3, 3), (0, 0)):
        with pytest.raises(ValueError, match="outside the 5 frames"):
            losses.window_and_temporal_huber(f, first, window)
    with pytest.raises(ValueError, match="unknown backend"):
        losses.window_and_temporal_huber(f, 0, 3, backend="cuda")


def test_ssim_of_flat_images_by_hand():
    a = torch.full((30, 30, 3), 0.2, dtype=torch.float64)  # float64: no rounding in the variances
    b = torch.full((30, 30, 3), 0.6, dtype=torch.float64)
    # away from the zero-padded border: means 0.2 and 0.6, no variance
    expected = (2 * 0.2 * 0.6 + SSIM_C1) / (0.2 ** 2 + 0.6 ** 2 + SSIM_C1)
    assert ssim_map(a, b)[15, 15].item() == pytest.approx(expected, rel=1e-5)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-6)
    assert SSIM_C2 > 0


def test_masked_psnr_by_hand():
    truth = torch.zeros(2, 2, 3)
    image = torch.tensor([[[0.1] * 3, [0.0] * 3], [[0.0] * 3, [0.3] * 3]])
    mask = torch.tensor([[True, True], [False, False]])
    assert psnr(image, truth, mask=mask) == pytest.approx(10 * math.log10(1 / (0.01 / 2)))  # errors 0.1², 0
    assert psnr(image, truth, mask=~mask) == pytest.approx(10 * math.log10(1 / (0.09 / 2)))
    assert psnr(image, truth) == pytest.approx(10 * math.log10(1 / (0.1 / 4)))
    assert math.isnan(psnr(image, truth, mask=torch.zeros(2, 2, dtype=torch.bool)))
    with pytest.raises(ValueError, match="mask"):
        psnr(image, truth, mask=torch.ones(3, 2, dtype=torch.bool))


def test_masked_ssim_and_photometric_use_only_the_mask():
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(24, 24, 3, generator=gen)
    b = a.clone()
    b[:, 12:] = torch.rand(24, 12, 3, generator=gen)  # the right half differs
    left = torch.zeros(24, 24, dtype=torch.bool)
    left[:, :6] = True  # far from the right half (the 11x11 window reaches 5 pixels)
    assert ssim(a, b, left).item() == pytest.approx(1.0, abs=1e-6)
    assert losses.photometric(a, b, 0.2, left).item() == pytest.approx(0.0, abs=1e-6)
    right = ~left
    l1 = (a - b).abs()[right].mean().item()
    expected = 0.8 * l1 + 0.2 * (1 - ssim(a, b, right).item())
    assert losses.photometric(a, b, 0.2, right).item() == pytest.approx(expected, rel=1e-6)
    assert losses.photometric(a, b, 0.2, torch.zeros(24, 24, dtype=torch.bool)).item() == 0.0


def test_self_distillation_only_moves_the_student():
    student = torch.tensor([[0.5, -0.5]], requires_grad=True)
    teacher = torch.tensor([[0.0, 0.5]], requires_grad=True)
    loss = losses.self_distillation(student, teacher)
    assert loss.item() == pytest.approx((0.25 + 1.0) / 2)
    loss.backward()
    assert torch.allclose(student.grad, torch.tensor([[0.5, -1.0]]))  # d/ds mean((s - t)²) = (s - t)
    assert teacher.grad is None


def test_grid_smoothness_and_opacity_by_hand():
    v = torch.tensor([[0.0], [1.0], [0.0], [1.0]])  # 2x2 grid: [[0, 1], [0, 1]]
    # vertical neighbours equal (0), horizontal differ by 1: (0 + 1) / 2
    assert losses.grid_smoothness(v, 2).item() == pytest.approx(0.5)
    assert losses.opacity_l1(torch.tensor([0.0, 0.5, 1.0])).item() == pytest.approx(0.5)


def test_dynamic_mask_marks_moving_pixels():
    frames = torch.zeros(6, 4, 4, 3)
    frames[::2, 1, 2] = 1.0  # blinking pixel
    mask = variance_mask(frames, 0.05)
    assert mask[1, 2] and mask.sum() == 1
    assert not math.isnan(frames.std())


def test_gop_dynamic_masks_are_each_cameras_mask_of_the_first_frames():
    """Camera by camera, the mask of the GOP's first `count` frames: a pixel that changes at frame 10 of 60 is
    dynamic in its camera only; one that changes only after frame 40 is not seen by 30 frames."""
    images = torch.zeros(60, 2, 4, 4, 3, dtype=torch.uint8)
    images[10:, 1, 3, 0] = 255  # camera 1, pixel (3, 0) turns red at frame 10
    images[40:, 0, 1, 1] = 255  # camera 0, pixel (1, 1) turns red at frame 40
    cams = [Camera(str(c), intrinsics(4, 4, 60.0), torch.eye(4, dtype=torch.float64), 4, 4) for c in range(2)]
    views = tensor_views(cams, list(range(60)), images)
    masks = gop_dynamic_masks(views, 30, 0.05)
    assert masks.shape == (2, 4, 4) and masks[1, 3, 0] and masks.sum() == 1
    whole = torch.stack([torch.from_numpy(variance_mask(images[:30, c].float() / 255, 0.05)) for c in range(2)])
    assert torch.equal(masks, whole)
    assert gop_dynamic_masks(views, 100, 0.05)[0, 1, 1]  # count beyond the GOP: every frame


def test_the_running_variance_mask_matches_the_whole_stacks_std():
    frames = torch.rand(40, 8, 6, 3, generator=torch.Generator().manual_seed(3))
    luma = frames.double() @ torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    std = luma.std(dim=0)
    theta = float(std.median()) + 1e-9  # between two pixels' values
    assert torch.equal(torch.from_numpy(variance_mask(frames, theta)), std > theta)
    assert torch.equal(torch.from_numpy(variance_mask(iter(frames), theta)), std > theta)
    with pytest.raises(ValueError):
        variance_mask([frames[0]], theta)


def test_ssim_gradient_in_the_image_is_autograds():
    """ssim_map's written-out backward (_SSIMMap: the blur is its own adjoint) against gradcheck in float64, and
    a reference that needs a gradient goes through autograd's graph instead."""
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(13, 9, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    reference = torch.rand(13, 9, 3, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim_map(x, reference), (image,))
    both = reference.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x, y: ssim_map(x, y), (image, both))


def test_masked_terms_are_the_means_over_the_mask():
    gen = torch.Generator().manual_seed(1)
    image = torch.rand(12, 10, 3, generator=gen, dtype=torch.float64)
    target = torch.rand(12, 10, 3, generator=gen, dtype=torch.float64)
    mask = torch.rand(12, 10, generator=gen) > 0.3
    values = ssim_map(image, target)
    expected = 0.8 * (image - target).abs()[mask].mean() + 0.2 * (1 - values[mask].mean())
    assert losses.photometric(image, target, 0.2, mask).item() == pytest.approx(expected.item(), rel=1e-12)
    assert ssim(image, target, mask).item() == pytest.approx(values[mask].mean().item(), rel=1e-12)
    nothing = torch.zeros(12, 10, dtype=torch.bool)
    assert losses.photometric(image, target, 0.2, nothing).item() == 0.0
    assert ssim(image, target, nothing).item() == 1.0
