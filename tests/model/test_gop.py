"""GOP model: shapes, the deformation field's architecture, and the native deform vs torch."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from stgs.camera import Camera, intrinsics, look_at
from stgs.model.gop import FEATURE_DIM, HIDDEN, Gaussians, GOPModel, GOPShape, frame_time, positional_encoding
from stgs.model.native_deform import (
    BF16_BACKENDS,
    PackedWeights,
    bf16_available,
    bf16_backends,
    check_precision,
    deform_native,
    int16_available,
)
from stgs.model.precision_oracles import deform_bf16_reference, deform_int16_reference
from stgs.model.renderer import FrameRenderer, in_guard_band, splat
from stgs.native.library import NativeUnavailableError, available


def random_model(n=300, gop_size=10, window=3, seed=0) -> GOPModel:
    torch.manual_seed(seed)
    model = GOPModel(GOPShape(capacity=n, gop_size=gop_size, window=window))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.4)
        model.xyz.normal_(0, 0.5)
        model.log_scale.normal_(-3, 0.3)
        model.opacity_logit.normal_(0, 2)
    return model


def test_shapes_follow_gop_size_and_window():
    shape = GOPShape(capacity=64, gop_size=60, window=3)
    model = GOPModel(shape)
    assert shape.num_features == 62 and shape.grid_side == 8
    assert model.features.shape == (62, 64, FEATURE_DIM)
    assert GOPShape(capacity=50).grid_side == 0


def test_frame_uses_its_window_of_features():
    model = GOPModel(GOPShape(capacity=5, gop_size=4, window=3))
    with torch.no_grad():
        for e in range(model.shape.num_features):
            model.features[e] = e
    for i in range(4):
        window = model.window_features(i).reshape(5, 3, FEATURE_DIM)
        assert torch.equal(window[:, :, 0], torch.tensor([i, i + 1, i + 2]).float().expand(5, 3))
    with pytest.raises(ValueError, match="outside the GOP"):
        model.window_features(4)


def test_deformation_field_architecture():
    field = GOPModel(GOPShape(capacity=1, window=3, pe_freqs=4)).field
    linears = [m for m in field.modules() if isinstance(m, nn.Linear)]
    assert all(m.bias is None for m in linears), "no biases anywhere"
    assert field.temporal.in_features == 3 * FEATURE_DIM + 8 and field.temporal.out_features == HIDDEN
    for decoder, in_dim, out_dim in [(field.d_pos, HIDDEN, 3), (field.d_cov, HIDDEN, 7),
                                     (field.d_opacity, HIDDEN + 3, 1), (field.d_color, HIDDEN + 3, 3)]:
        first, last = decoder[0], decoder[2]
        assert (first.in_features, first.out_features) == (in_dim, HIDDEN)
        assert (last.in_features, last.out_features) == (HIDDEN, out_dim)


def test_time_normalised_per_gop_and_encoding():
    assert frame_time(0, 60) == 0.0 and frame_time(59, 60) == 1.0
    pe = positional_encoding(0.5, 2)  # sin(pi/2), sin(pi), cos(pi/2), cos(pi)
    assert torch.allclose(pe, torch.tensor([1.0, 0.0, 0.0, -1.0]), atol=1e-6)


def test_zero_field_gives_canonical_gaussians():
    model = random_model()
    with torch.no_grad():
        for p in model.field.parameters():
            p.zero_()
    g = model.deform(3, torch.tensor([0.0, 0.0, -3.0]))
    assert torch.equal(g.means, model.xyz)
    assert torch.allclose(g.scales, model.log_scale.exp())
    assert torch.allclose(g.opacities, torch.sigmoid(model.opacity_logit))
    assert torch.allclose(g.colors, torch.relu(model.color))


def test_view_direction_reaches_only_opacity_and_colour():
    model = random_model()
    a = model.deform(2, torch.tensor([0.0, 0.0, -3.0]))
    b = model.deform(2, torch.tensor([3.0, 1.0, 0.0]))
    assert torch.equal(a.means, b.means) and torch.equal(a.scales, b.scales)
    assert torch.equal(a.quats, b.quats)
    assert not torch.allclose(a.colors, b.colors) and not torch.allclose(a.opacities, b.opacities)
    assert (a.opacities >= 0).all() and (a.opacities <= 1).all()


def test_delta_opacity_is_bounded_by_tanh():
    model = random_model()
    with torch.no_grad():
        model.field.d_opacity[2].weight.mul_(1e4)  # saturate the tanh
    base = torch.sigmoid(model.opacity_logit)
    g = model.deform(1, torch.zeros(3))
    assert ((g.opacities - base.clamp(0, 1)).abs() <= 1.0 + 1e-6).all()


@pytest.mark.parametrize("window", [1, 3, 5])
def test_native_deform_matches_torch(window):
    model = random_model(n=777, window=window)
    center = torch.tensor([0.3, -0.2, -4.0])
    with torch.no_grad():
        ref = model.deform(5, center)
        nat = deform_native(model, 5, center, PackedWeights(model))
    for name in ("means", "quats", "scales", "opacities", "colors"):
        a, b = getattr(ref, name), getattr(nat, name)
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5), name


def test_native_culling_does_not_change_the_image():
    model = random_model(n=2000)
    cam = Camera("c", intrinsics(64, 48, 40.0), look_at((0.0, 0.0, -3.0), (0.8, 0.0, 0.0)), 64, 48)
    renderer = FrameRenderer(model, native=True)
    culled = renderer.gaussians(4, cam)
    with torch.no_grad():
        full = deform_native(model, 4, cam.center.float(), PackedWeights(model))
    assert renderer.guarded
    outside = ~in_guard_band(full.means, cam)
    assert outside.any() and (culled.opacities[outside] == 0).all()  # the guard band, applied natively
    args = (cam.viewmat.float(), cam.K.float(), 64, 48)
    from stgs.render import rasterize

    a = rasterize(culled.means, culled.quats, culled.scales, culled.opacities, culled.colors, *args)
    # the frame of the guard band applied in torch (the decoders, run on fewer Gaussians, round differently)
    assert (a - splat(full, cam)).abs().max() <= 1e-6 * a.abs().max()
    assert torch.equal(renderer.render(4, cam), a)
    slow = FrameRenderer(model, native=False).render(4, cam)  # the frame path: the guard band applies
    assert (slow.double() - a.double()).abs().max() < 1e-4 * a.abs().max()  # this random field's colours reach ~6


def attributes(kernel: Gaussians, oracle: Gaussians, float32: Gaussians):
    """(name, kernel's, oracle's, float32 deformation's, the float32 one's peak |value|) per attribute, scales
    as their logs."""
    for name in ("means", "quats", "opacities", "colors", "scales"):
        g, w, f = (getattr(x, name) for x in (kernel, oracle, float32))
        if name == "scales":
            g, w, f = g.log(), w.log(), f.log()
        yield name, g, w, f, f.abs().max()


BF16_NEEDS = "the bf16 deformation needs a CPU with AVX512-BF16 or AMX-BF16"
needs_bf16 = pytest.mark.skipif(not bf16_available(), reason=BF16_NEEDS)


@pytest.mark.parametrize("backend", list(BF16_BACKENDS))
@pytest.mark.parametrize("window, n", [(3, 1000), (8, 333), (1, 17)])
def test_bf16_deform_matches_its_torch_oracle(window, n, backend):
    if backend not in bf16_backends():
        pytest.skip(f"the {backend} back end cannot run on this CPU")
    model = random_model(n=n, window=window)
    center = torch.tensor([0.3, -0.2, -4.0])
    with torch.no_grad():
        got = deform_native(model, 5, center, precision="bf16", bf16_backend=backend)
        want = deform_bf16_reference(model, 5, center)
        full = model.deform(5, center)
    for name, g, w, f, peak in attributes(got, want, full):
        # Summation order differs from torch's, so a value can round to the neighbouring bf16 now and then.
        assert (g - w).abs().max() <= 2e-2 * peak, name
        assert (g - w).abs().mean() <= 1e-4 * peak, name
        # ... and bf16 is not float32: the oracle is a different function from the float32 deformation.
        assert (w - f).abs().max() > 1e-5 * peak, name
        assert (g - f).abs().max() <= 1e-1 * peak, name  # bf16's 8-bit mantissa, large random weights


INT16_NEEDS = "the int16 deformation needs the native build on a CPU with AVX2"
needs_int16 = pytest.mark.skipif(not int16_available(), reason=INT16_NEEDS)


def int16_parity_case() -> dict[str, torch.Tensor]:
    """The int16 deformation of a fixed model, whole and culled by a camera, at two frames: the AVX-512 and AVX2
    kernels must give it bit for bit (tests/render/test_portable_build.py). 1,001 rows and the culling leave
    blocks and kept appearance rows of every remainder the kernels' strips handle."""
    model = random_model(n=1001, seed=3)
    cam = Camera("c", intrinsics(64, 48, 60.0), look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), (0.0, -1.0, 0.0)), 64, 48)
    out = {}
    with torch.no_grad():
        model.features[:, 100:120] *= 1000.0  # per-row scales far apart
        for frame in (0, 5):
            for culled in (False, True):
                kw = {"viewmat": cam.viewmat, "K": cam.K, "width": 64, "height": 48} if culled else {}
                g = deform_native(model, frame, cam.center.float(), precision="int16", **kw)
                for name in ("means", "quats", "scales", "opacities", "colors"):
                    out[f"{frame}-{culled}-{name}"] = getattr(g, name)
    return out


@needs_int16
@pytest.mark.parametrize("window, n", [(3, 1000), (5, 333), (1, 17), (16, 40)])
def test_int16_deform_matches_its_torch_oracle(window, n):
    """The kernel's integer sums are exact, so it differs from its oracle only where float32 rounding (its fast
    tanh and exp, the order of the last products) moves a value across a rounding boundary of the next
    layer's integers. Rows of zeros and rows 1000 times larger than the rest exercise the per-row scales."""
    model = random_model(n=n, window=window)
    with torch.no_grad():
        model.features[:, : n // 7] = 0.0
        model.features[:, n // 2: n // 2 + 3] *= 1000.0
    center = torch.tensor([0.3, -0.2, -4.0])
    with torch.no_grad():
        got = deform_native(model, 5, center, precision="int16")
        want = deform_int16_reference(model, 5, center)
        full = model.deform(5, center)
    for name, g, w, f, peak in attributes(got, want, full):
        assert torch.isfinite(g).all(), name
        assert (g - w).abs().max() <= 2e-3 * peak, name
        assert (g - w).abs().mean() <= 2e-5 * peak, name
        # int16 is not float32 (the oracle is another function), but it is close: 12-14 bits per value.
        assert (w - f).abs().max() > 1e-6 * peak, name
        assert (g - f).abs().max() <= 1e-2 * peak, name


@pytest.mark.parametrize("precision", ["fp32", pytest.param("bf16", marks=needs_bf16),
                                       pytest.param("int16", marks=needs_int16)])
def test_a_nan_feature_is_refused_not_drawn(precision):
    """NaN must come out of the native deformation as NaN (its fast tanh clamps its input and its relu
    compares, and both let NaN pass, as torch does), so that the splatter refuses the frame instead of
    drawing a plausible Gaussian."""
    model = random_model(n=40)
    with torch.no_grad():
        model.features[:, 7, 3] = float("nan")
        got = deform_native(model, 2, torch.tensor([0.3, -0.2, -4.0]), precision=precision)
    assert torch.isnan(got.means[7]).all()
    assert torch.isfinite(got.means[torch.arange(40) != 7]).all()
    cam = Camera("c", intrinsics(32, 24, 20.0), look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0)), 32, 24)
    with pytest.raises(ValueError, match="NaN or Inf"):
        FrameRenderer(model, native=True, precision=precision).render(2, cam)


@pytest.mark.parametrize("precision, bound", [pytest.param("bf16", 1e-4, marks=needs_bf16),
                                              pytest.param("int16", 1e-6, marks=needs_int16)])
def test_reduced_precision_renders_close_to_fp32(precision, bound):
    """Image MSE against the float32 deformation's: below `bound` (PSNR above 40 dB for bf16, 60 dB for
    int16), and not the float32 image."""
    model = random_model(n=3000)
    with torch.no_grad():
        for p in model.field.parameters():
            p.mul_(0.25)  # offsets of a realistic size (fitted fields), not saturated
    cam = Camera("c", intrinsics(96, 72, 50.0), look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0)), 96, 72)
    a = FrameRenderer(model, native=True).render(4, cam)
    b = FrameRenderer(model, native=True, precision=precision).render(4, cam)
    mse = (a.double() - b.double()).square().mean().item()
    assert 0 < mse < bound


def test_precision_errors_are_clear():
    with pytest.raises(ValueError, match="unknown deform precision"):
        check_precision("fp16")
    with pytest.raises(ValueError, match="needs the native build"):
        FrameRenderer(random_model(n=10), native=False, precision="bf16")
    if not bf16_available():
        with pytest.raises(NativeUnavailableError, match="AVX512-BF16 or AMX-BF16"):
            check_precision("bf16")
    if not int16_available():
        with pytest.raises(NativeUnavailableError, match="AVX2"):
            check_precision("int16")


@needs_bf16
def test_bf16_backend_errors_are_clear():
    model = random_model(n=10)
    center = torch.tensor([0.3, -0.2, -4.0])
    with pytest.raises(ValueError, match="unknown bf16 back end 'avx2'"):
        deform_native(model, 1, center, precision="bf16", bf16_backend="avx2")
    for backend in set(BF16_BACKENDS) - set(bf16_backends()):
        with pytest.raises(NativeUnavailableError, match=f"{backend} back end cannot run here"):
            deform_native(model, 1, center, precision="bf16", bf16_backend=backend)


@pytest.mark.parametrize("native", [False, True])
def test_a_model_without_features_deforms_from_a_given_window_exactly(native):
    """The player's streamed GOPs hold no features: the frame's window of feature frames, passed in, gives the
    same Gaussians, bit for bit, as the model that holds them all."""
    if native and not available():
        pytest.skip("native build unavailable")
    model = random_model(n=300, gop_size=10, window=3)
    bare = GOPModel(model.shape, features=False)
    bare.load_state_dict({k: v for k, v in model.state_dict().items() if k != "features"}, strict=False)
    assert bare.features.shape == (0, 300, FEATURE_DIM)
    center = torch.tensor([0.3, -0.2, 2.0])
    for frame in (0, 4, 9):
        window = [model.features.detach()[frame + j].clone() for j in range(3)]
        if native:
            whole, streamed = deform_native(model, frame, center), deform_native(bare, frame, center, window=window)
        else:
            with torch.no_grad():
                whole, streamed = model.deform(frame, center), bare.deform(frame, center, window)
        for name in ("means", "quats", "scales", "opacities", "colors"):
            assert torch.equal(getattr(whole, name), getattr(streamed, name)), (frame, name)


def test_a_missing_or_malformed_window_is_a_clear_error():
    model = random_model(n=30, gop_size=4, window=2)
    bare = GOPModel(model.shape, features=False)
    with pytest.raises(ValueError, match="holds no features"):
        bare.feature_window(0)
    with pytest.raises(ValueError, match=r"2 contiguous float32 \(30, 16\) frames"):
        bare.feature_window(0, [torch.zeros(30, 16)])
    with pytest.raises(ValueError, match=r"2 contiguous float32 \(30, 16\) frames"):
        bare.feature_window(0, [torch.zeros(30, 16), torch.zeros(30, 16, dtype=torch.float64)])
    with pytest.raises(ValueError, match="outside the GOP"):
        bare.feature_window(4, [torch.zeros(30, 16)] * 2)
