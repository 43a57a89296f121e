"""Image quality metrics."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from stgs.errors import StgsError


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
    rows = torch.nn.functional.conv2d(stack, taps.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, pad), groups=c)
    return torch.nn.functional.conv2d(rows, taps.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(pad, 0), groups=c)


def ssim_map(image: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (Wang et al. 2004; 11x11 Gaussian window, σ 1.5, zero padding as in 3DGS) of (H, W, 3)
    images in [0, 1], averaged over channels: (H, W). Differentiable."""
    if image.shape != reference.shape or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"ssim: need two (H, W, 3) images, got {tuple(image.shape)} and {tuple(reference.shape)}")
    x = image.permute(2, 0, 1)
    y = reference.to(image.dtype).permute(2, 0, 1)
    mu_x, mu_y, xx, yy, xy = _blur(torch.cat([x, y, x * x, y * y, x * y])[None])[0].split(3)
    var_x = xx - mu_x.square()
    var_y = yy - mu_y.square()
    cov = xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x.square() + mu_y.square() + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (num / den).mean(0)


def ssim(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None,
         values: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM (a 0-d tensor), over the pixels of `mask` ((H, W) bool) when given; `values` is
    ssim_map(image, reference) when the caller already has it."""
    values = ssim_map(image, reference) if values is None else values
    if mask is None:
        return values.mean()
    if mask.sum() == 0:
        return values.new_ones(())
    return values[mask].mean()


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
