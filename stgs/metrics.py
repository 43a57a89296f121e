"""Image quality metrics."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from stgs.errors import StgsError
from stgs.native.abi import ptr
from stgs.native.library import available, load


def psnr(image: torch.Tensor, reference: torch.Tensor, peak: float = 1.0, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of (H, W, C) image vs reference (values in [0, peak]), over the pixels of an (H, W) bool `mask`
    when given; inf when identical, nan when the mask is empty."""
    if image.shape != reference.shape:
        raise ValueError(f"psnr: shapes differ {tuple(image.shape)} vs {tuple(reference.shape)}")
    error = (image.double() - reference.double()).square()
    if mask is not None:
        if mask.shape != image.shape[:2]:
            raise ValueError(f"psnr: mask {tuple(mask.shape)} does not cover the image {tuple(image.shape[:2])}")
        if not mask.any():
            return math.nan
        error = error[mask]
    mse = error.mean().item()
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def _gaussian_taps(dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=dtype) - (SSIM_WINDOW - 1) / 2
    g = torch.exp(-x.square() / (2 * SSIM_SIGMA ** 2))
    return g / g.sum()


def _blur(stack: torch.Tensor) -> torch.Tensor:
    """The 11x11 Gaussian window on every channel of (1, C, H, W), zero padded. The window is an outer
    product, so a row pass then a column pass give the 2-D result at a fifth of the arithmetic."""
    taps, c, pad = _gaussian_taps(stack.dtype), stack.shape[1], SSIM_WINDOW // 2
    # Channels-last: oneDNN's depthwise convolution is faster on it than on planes of each channel.
    stack = stack.contiguous(memory_format=torch.channels_last)
    rows = torch.nn.functional.conv2d(stack, taps.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, pad), groups=c)
    return torch.nn.functional.conv2d(rows, taps.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(pad, 0), groups=c)


def ssim_map(image: torch.Tensor, reference: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Per-pixel SSIM (Wang et al. 2004; 11x11 Gaussian window, σ 1.5, zero padding as in 3DGS) of (H, W, 3)
    images in [0, 1], averaged over channels: (H, W). Differentiable in both; in `image` alone (the training
    loss) by a written-out gradient: `backend` "auto" runs float32 CPU images through the native kernel
    (csrc/ssim.cpp) and others through _SSIMMap in torch, "torch" the latter always; a `reference` that needs
    a gradient goes through autograd's graph of the same formula."""
    if image.shape != reference.shape or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"ssim: need two (H, W, 3) images, got {tuple(image.shape)} and {tuple(reference.shape)}")
    if backend not in ("auto", "torch"):
        raise ValueError(f"ssim: unknown backend {backend!r}; use 'auto' or 'torch'")
    reference = reference.to(image.dtype)
    grad = torch.is_grad_enabled()
    if grad and reference.requires_grad:
        return _ssim_parts(image.permute(2, 0, 1), reference.permute(2, 0, 1))[0].mean(0)
    if backend == "auto" and image.dtype == torch.float32 and image.device.type == "cpu" and available():
        if grad and image.requires_grad:
            return _NativeSSIMMap.apply(image, reference)
        return _native_ssim(image.detach().contiguous(), reference.detach().contiguous(), partials=False)[0]
    return _SSIMMap.apply(image.permute(2, 0, 1), reference.permute(2, 0, 1))


def _ssim_parts(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """SSIM of (3, H, W) images per channel, and the windowed means and the four terms of its fraction
    (A1·A2) / (B1·B2) that its gradient needs."""
    mu_x, mu_y, xx, yy, xy = _blur(torch.cat([x, y, x * x, y * y, x * y])[None])[0].split(3)
    a1 = 2 * mu_x * mu_y + SSIM_C1
    a2 = 2 * (xy - mu_x * mu_y) + SSIM_C2
    b1 = mu_x.square() + mu_y.square() + SSIM_C1
    b2 = (xx - mu_x.square()) + (yy - mu_y.square()) + SSIM_C2
    return a1 * a2 / (b1 * b2), mu_x, mu_y, a1, a2, b1, b2


class _SSIMMap(torch.autograd.Function):
    """ssim_map's channel-mean SSIM of (3, H, W) images with its gradient in the first written out. Autograd's
    graph blurs all fifteen windowed channels backwards, the reference's six included; this backward blurs the
    nine partial derivatives in the image's windowed mean, mean square and product with the reference by the
    forward blur: the window is symmetric and zero padded, so the blur is its own adjoint."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        s, mu_x, mu_y, a1, a2, b1, b2 = _ssim_parts(x, y)
        ctx.save_for_backward(x, y, s, mu_x, mu_y, a1, a2, b1, b2)
        return s.mean(0)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        x, y, s, mu_x, mu_y, a1, a2, b1, b2 = ctx.saved_tensors
        g = grad / 3  # the mean over the channels
        den = b1 * b2
        d_mu = g * (2 * mu_y * (a2 - a1) / den + 2 * mu_x * s * (1 / b2 - 1 / b1))
        d_xx = g * (-s / b2)
        d_xy = g * (2 * a1 / den)
        blurred = _blur(torch.cat([d_mu, d_xx, d_xy])[None])[0].split(3)
        return blurred[0] + 2 * x * blurred[1] + y * blurred[2], None


def _native_ssim(image: torch.Tensor, reference: torch.Tensor, partials: bool
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """csrc/ssim.cpp's forward on contiguous (H, W, 3) float32 images: the map, the window's taps and, when
    `partials`, the (9, H, W) partial derivatives its backward reads."""
    h, w = image.shape[:2]
    taps = _gaussian_taps(torch.float32)
    out = torch.empty(h, w)
    kept = torch.empty(9, h, w) if partials else None
    load().stgs_ssim_forward(h, w, ptr(image), ptr(reference), ptr(taps), ptr(out), ptr(kept), torch.get_num_threads())
    return out, taps, kept


class _NativeSSIMMap(torch.autograd.Function):
    """_SSIMMap's formula and gradient on (H, W, 3) float32 images in one native pass each way (csrc/ssim.cpp),
    without a full-size intermediate (bench.training.loss_terms times the three versions)."""

    @staticmethod
    def forward(ctx, image: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
        image, reference = image.detach().contiguous(), reference.detach().contiguous()
        out, taps, partials = _native_ssim(image, reference, partials=True)
        ctx.save_for_backward(image, reference, taps, partials)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        image, reference, taps, partials = ctx.saved_tensors
        h, w = image.shape[:2]
        out = torch.empty(h, w, 3)
        grad = grad.float().contiguous()  # held through the call
        load().stgs_ssim_backward(h, w, ptr(image), ptr(reference), ptr(taps), ptr(partials), ptr(grad), ptr(out),
                                  torch.get_num_threads())
        return out, None


def ssim(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None,
         values: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM (a 0-d tensor), over the pixels of `mask` ((H, W) bool) when given; `values` is
    ssim_map(image, reference) when the caller already has it."""
    values = ssim_map(image, reference) if values is None else values
    if mask is None:
        return values.mean()
    if not mask.any():
        return values.new_ones(())
    return masked_mean(values, mask)


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (H, W) `values` over the pixels of a non-empty (H, W) bool `mask`, as a weighted sum: boolean
    indexing's gather and its scattering backward cost a training step several milliseconds at 640x360."""
    return (values * mask.to(values.dtype)).sum() / mask.sum()


LPIPS_BACKBONES = {"alex": "AlexNet_Weights", "vgg": "VGG16_Weights"}
"""LPIPS network -> the torchvision weights enum of its ImageNet backbone."""


def lpips_backbone_file(net: str = "alex") -> Path:
    """Where torchvision's cache keeps LPIPS's ImageNet backbone ($TORCH_HOME/hub/checkpoints/...)."""
    from torchvision import models

    url = getattr(models, LPIPS_BACKBONES[net]).IMAGENET1K_V1.url
    return Path(torch.hub.get_dir()) / "checkpoints" / url.rsplit("/", 1)[1]


class LPIPS:
    """LPIPS v0.1 (Zhang et al. 2018, the `lpips` package) of (H, W, 3) images in [0, 1]; lower is closer.

    The linear heads ship with the package; the backbone's ImageNet weights are read from torchvision's cache
    (`lpips_backbone_file`) as plain tensors and never downloaded: `LPIPS.load` returns None without them.
    """

    def __init__(self, net: str, backbone: Path):
        import warnings

        import lpips

        with warnings.catch_warnings():  # lpips 0.1.4 passes torchvision's deprecated `pretrained=False`
            warnings.simplefilter("ignore", UserWarning)
            self.model = lpips.LPIPS(net=net, pnet_rand=True, verbose=False).eval()
        try:
            state = torch.load(backbone, map_location="cpu", weights_only=True)
            # lpips keeps torchvision's `features.<i>` layers as `slice<k>.<i>`.
            own = self.model.net.state_dict()
            self.model.net.load_state_dict({key: state["features." + key.split(".", 1)[1]] for key in own})
        except Exception as exc:  # a corrupt or foreign file: any loader error means the same to the user
            raise StgsError(f"{backbone}: not usable as the LPIPS {net} backbone ({exc})") from None
        self.net, self.backbone = net, backbone

    @classmethod
    def load(cls, net: str = "alex") -> LPIPS | None:
        path = lpips_backbone_file(net)
        return cls(net, path) if path.is_file() else None

    @torch.no_grad()
    def __call__(self, image: torch.Tensor, reference: torch.Tensor) -> float:
        if image.shape != reference.shape or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"lpips: need two (H, W, 3) images, got {tuple(image.shape)} and "
                             f"{tuple(reference.shape)}")
        x, y = (t.float().permute(2, 0, 1)[None] * 2 - 1 for t in (image, reference))
        return float(self.model(x, y))


def mse_psnr(mse: list[float]) -> float:
    """PSNR (signal peak 1) of the mean of squared errors; 99 dB when identical."""
    m = sum(mse) / len(mse)
    return 99.0 if m == 0 else 10 * math.log10(1.0 / m)
