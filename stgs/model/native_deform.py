"""Native (C++) evaluation of GOPModel.deform for inference.

The torch `GOPModel.deform` is the oracle; this path evaluates every MLP layer
per block of Gaussians while the block sits in cache, and (given a camera)
skips the view-dependent decoders of Gaussians that cannot reach the image.
Three precisions: float32 (AVX-512, AVX2 or portable); bf16 inputs and
weights with float32 accumulation, on AMX tiles or AVX512-BF16 vectors where
the CPU (and, for AMX, the kernel) allow it; and int16 inputs and weights with
exact int32 sums (AVX2 `vpmaddwd`, or AVX512-VNNI `vpdpwssd`), for CPUs without bf16 arithmetic. The
reduced precisions are accuracy knobs (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from stgs.limits import MAX_BF16_WINDOW, MAX_WINDOW
from stgs.model.gop import (
    FEATURE_DIM,
    HIDDEN,
    Gaussians,
    GOPModel,
    frame_time,
    positional_encoding,
)
from stgs.model.precision import PRECISIONS
from stgs.native.abi import ffi, ptr
from stgs.native.library import NativeUnavailableError, available, load

BF16_BACKENDS = {"amx": 2, "avx512-bf16": 1}
"""The bf16 deformation's back ends, preferred first, with their bit in stgs_deform_bf16_backends: AMX tiles
(Intel Sapphire Rapids and later; Linux must grant AMX state) and AVX512-BF16 vectors (vdpbf16ps: AMD Zen 4
and later, Intel Cooper Lake and later)."""


def bf16_backends() -> list[str]:
    """The bf16 back ends that can run here, preferred first (empty without the native build)."""
    if not available():
        return []
    mask = load().stgs_deform_bf16_backends()
    return [name for name, bit in BF16_BACKENDS.items() if mask & bit]


def bf16_available() -> bool:
    """True when the native bf16 deformation can run here on some back end."""
    return bool(bf16_backends())


INT16_KERNELS = {1: "avx2", 2: "avx512bw", 3: "avx512-vnni"}
"""The int16 deformation's kernels by stgs_deform_int16_available's value: the widest the native build's
-march allows. They give the same bits (exact int32 sums, the same float epilogue)."""


def int16_kernel() -> str | None:
    """The kernel the native int16 deformation runs here, or None where it cannot run."""
    return INT16_KERNELS.get(load().stgs_deform_int16_available()) if available() else None


def int16_available() -> bool:
    """True when the native int16 deformation can run here (the native build targets AVX2)."""
    return int16_kernel() is not None


def runnable_precisions() -> list[str]:
    """The precisions of PRECISIONS that can run here (fp32 always: native or torch)."""
    return ["fp32"] + (["bf16"] if bf16_available() else []) + (["int16"] if int16_available() else [])


def check_precision(precision: str) -> None:
    """Raise ValueError for an unknown precision, NativeUnavailableError for one that cannot run here."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown deform precision {precision!r}; choose from {', '.join(PRECISIONS)}")
    if precision == "bf16" and not bf16_available():
        raise NativeUnavailableError("bf16 deformation needs the native build on a CPU with AVX512-BF16 or "
                                     "AMX-BF16 (e.g. AMD Zen 4, Intel Sapphire Rapids); use fp32 or int16")
    if precision == "int16" and not int16_available():
        raise NativeUnavailableError("int16 deformation needs the native build on a CPU with AVX2; use fp32")


def _c(t: torch.Tensor | torch.nn.Module) -> torch.Tensor:
    """A weight or tensor as a contiguous detached float32 copy (a layer's `weight` types as either)."""
    assert isinstance(t, torch.Tensor)
    return t.detach().to(torch.float32).contiguous()


OUT_WIDTH = 16
"""Padded output width of the packed second layers."""


TILE_K = 32
"""bf16 values of K per tile row (an AMX A-tile row; 16 pairs for vdpbf16ps)."""


def _bf16_tiles(weight: torch.Tensor) -> torch.Tensor:
    """(K, M) in x out float32 weights as bf16 B tiles: K zero-padded to a multiple of 32, then for each
    K chunk and each 16-column tile, 16 rows of (column, pair of consecutive K) bf16 values. Both back ends
    read this: a row is an AMX B-tile row and the weight operand of one vdpbf16ps."""
    k, m = weight.shape
    chunks = -(-k // TILE_K)
    padded = torch.zeros(chunks * TILE_K, m)
    padded[:k] = weight
    tiles = padded.reshape(chunks, TILE_K // 2, 2, m // 16, 16).permute(0, 3, 1, 4, 2)
    return tiles.contiguous().to(torch.bfloat16)


INT32_LIMIT = 2**31 - 1


@dataclass(frozen=True)
class Int16Layer:
    """One layer (K inputs, M outputs) for the int16 kernel."""

    weight: torch.Tensor
    """(K/2 pairs, M, 2) int16: K zero-padded to even, each weight column scaled to integers of at most q."""
    col_scale: torch.Tensor
    """(M,) float32: max |w| of the column / q (0 for an all-zero column)."""
    q: float
    """The bound of the weights and of the layer's quantised inputs: K·q² < 2^31, so the int32 sums are exact."""


def _int16_layer(weight: torch.Tensor) -> Int16Layer:
    """(K, M) in x out float32 weights for the int16 kernel."""
    k, m = weight.shape
    padded = torch.zeros(k + k % 2, m)
    padded[:k] = weight
    q = float(min(32767, math.isqrt(INT32_LIMIT // padded.shape[0])))
    peak = padded.abs().amax(0)
    inv = torch.where(peak > 0, q / peak, torch.zeros_like(peak))
    quantised = (padded * inv).round().clamp(-q, q).to(torch.int16)
    pairs = quantised.reshape(-1, 2, m).permute(0, 2, 1).contiguous()
    return Int16Layer(pairs, (peak / q).contiguous(), q)


def _pack_second(first: torch.Tensor, second: torch.Tensor, col0: int,
                 col1: int) -> torch.Tensor:
    """(128, 16) block-diagonal second layer: hidden[:64] -> cols [0, col0), hidden[64:] -> [col0, col1)."""
    packed = torch.zeros(2 * HIDDEN, OUT_WIDTH)
    packed[:HIDDEN, :col0] = first.T
    packed[HIDDEN:, col0:col1] = second.T
    return packed.contiguous()


class PackedWeights:
    """The deformation field's weights arranged for the kernel (in x out, decoders side by side)."""

    def __init__(self, model: GOPModel):
        field = model.field
        in_feat = model.shape.window * FEATURE_DIM
        temporal = _c(field.temporal.weight)
        self.temporal_feat = temporal[:, :in_feat].T.contiguous()
        self.temporal_pe = temporal[:, in_feat:]
        self.geo1 = torch.cat([_c(field.d_pos[0].weight), _c(field.d_cov[0].weight)], 0).T.contiguous()
        self.geo2 = _pack_second(_c(field.d_pos[2].weight), _c(field.d_cov[2].weight), 3, 10)
        self.app1 = torch.cat([_c(field.d_opacity[0].weight), _c(field.d_color[0].weight)],
                              0).T.contiguous()
        self.app2 = _pack_second(_c(field.d_opacity[2].weight), _c(field.d_color[2].weight), 1, 4)

        self._bf16: list[torch.Tensor] | None = None
        self._int16: list[Int16Layer] | None = None

    def bf16(self) -> list[torch.Tensor]:
        """temporal, geo1, geo2, app1, app2 as bf16 tiles (packed on first use)."""
        if self._bf16 is None:
            self._bf16 = [_bf16_tiles(w) for w in (self.temporal_feat, self.geo1, self.geo2, self.app1, self.app2)]
        return self._bf16

    def int16(self) -> list[Int16Layer]:
        """temporal, geo1, geo2, app1, app2 for the int16 kernel (packed on first use)."""
        if self._int16 is None:
            self._int16 = [_int16_layer(w) for w in (self.temporal_feat, self.geo1, self.geo2, self.app1, self.app2)]
        return self._int16

    def pe_bias(self, frame: int, model: GOPModel) -> torch.Tensor:
        """The γ(t) part of D_t's input, folded into a per-frame bias."""
        pe = positional_encoding(frame_time(frame, model.shape.gop_size), model.shape.pe_freqs)
        return (self.temporal_pe @ pe).contiguous()


def deform_native(model: GOPModel, frame: int, camera_center: torch.Tensor,
                  weights: PackedWeights | None = None, viewmat: torch.Tensor | None = None,
                  K: torch.Tensor | None = None, width: int = 0, height: int = 0,
                  precision: str = "fp32", guard: tuple[float, float, float] | None = None,
                  window: list[torch.Tensor] | None = None, bf16_backend: str | None = None) -> Gaussians:
    """GOPModel.deform in C++ (no autograd), in float32, bf16 or int16 (`precision`, see PRECISIONS; bf16 on
    `bf16_backend`, one of bf16_backends(), by default the first).

    `window`: the frame's W feature frames e_i ... e_{i+W-1}, (N, 16) each, where the model does not hold
    its features (a GOP streamed frame by frame, stgs.codec.stream); None reads them from model.features.

    With viewmat/K/width/height, Gaussians that cannot put alpha >= 1/255 on
    the image get opacity 0 (the splatter would skip them anyway), and so do
    those outside `guard` = (near, x limit, y limit), the guard band of
    stgs.model.renderer.guard_limits.
    """
    model.check_frame(frame)
    check_precision(precision)
    if model.shape.window > (MAX_BF16_WINDOW if precision == "bf16" else MAX_WINDOW):
        raise ValueError(f"native {precision} deform supports windows up to "
                         f"{MAX_BF16_WINDOW if precision == 'bf16' else MAX_WINDOW}")
    weights = weights or PackedWeights(model)
    n = model.shape.capacity
    frames = model.feature_window(frame, window)
    canon = [_c(t) for t in (model.xyz, model.log_scale, model.rotation, model.opacity_logit,
                             model.color)]
    center = _c(camera_center.reshape(3))
    pe_bias = weights.pe_bias(frame, model)
    out = Gaussians(torch.empty(n, 3), torch.empty(n, 4), torch.empty(n, 3), torch.empty(n),
                    torch.empty(n, 3))
    view = intr = limits = None
    if viewmat is not None:
        if K is None:
            raise ValueError("a viewmat needs its K")
        view = viewmat.detach().to(torch.float64).contiguous()
        intr = K.detach().to(torch.float64).contiguous()
        if guard is not None:
            limits = torch.tensor(guard, dtype=torch.float64)
    outputs = [ptr(out.means), ptr(out.quats), ptr(out.scales), ptr(out.opacities), ptr(out.colors), ptr(limits)]
    threads = torch.get_num_threads()
    window_ptrs = ffi().new("float *[]", [ptr(f) for f in frames])
    inputs = [n, model.shape.window, window_ptrs, *(ptr(t) for t in canon)]
    camera = [ptr(center), ptr(view), ptr(intr), width, height]
    lib = load()
    if precision == "fp32":
        lib.stgs_deform(*inputs, ptr(weights.temporal_feat), ptr(pe_bias), ptr(weights.geo1), ptr(weights.geo2),
                        ptr(weights.app1), ptr(weights.app2), *camera, *outputs, threads)
        return out
    if precision == "int16":
        layers = weights.int16()
        layer_ptrs = ffi().new("int16_t *[]", [ptr(layer.weight) for layer in layers])
        scale_ptrs = ffi().new("float *[]", [ptr(layer.col_scale) for layer in layers])
        bounds = torch.tensor([layer.q for layer in layers], dtype=torch.float32)
        if lib.stgs_deform_int16(*inputs, layer_ptrs, scale_ptrs, ptr(bounds), ptr(pe_bias), *camera, *outputs,
                                 threads) != 0:
            raise NativeUnavailableError("the int16 deformation cannot run here (the native build lacks AVX2)")
        return out
    backend = bf16_backend or bf16_backends()[0]
    if backend not in BF16_BACKENDS:
        raise ValueError(f"unknown bf16 back end {backend!r}; choose from {', '.join(BF16_BACKENDS)}")
    temporal, geo1, geo2, app1, app2 = weights.bf16()
    status = lib.stgs_deform_bf16(*inputs, ptr(temporal), temporal.shape[0], ptr(pe_bias), ptr(geo1), ptr(geo2),
                                  ptr(app1), ptr(app2), *camera, *outputs, BF16_BACKENDS[backend], threads)
    if status != 0:
        raise NativeUnavailableError(f"the bf16 deformation's {backend} back end cannot run here "
                                     f"(available: {', '.join(bf16_backends()) or 'none'})")
    return out
