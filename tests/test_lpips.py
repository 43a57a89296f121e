"""LPIPS: computed only from backbone weights already on the machine, never downloaded."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from stgs.errors import StgsError
from stgs.metrics import LPIPS, lpips_backbone_file


@pytest.fixture
def torch_home(tmp_path, monkeypatch) -> Path:
    """An empty torch cache, and any download attempt fails the test."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))

    def no_download(*args, **kwargs):
        raise AssertionError(f"LPIPS tried to download {args[:1]}")

    monkeypatch.setattr(torch.hub, "download_url_to_file", no_download)
    return tmp_path / "torch"


def place_random_backbone(torch_home: Path, net: str = "alex") -> dict[str, torch.Tensor]:
    """A stand-in for torchvision's ImageNet backbone file (random weights, its key names) in the cache; the
    classifier layers, which LPIPS does not use, are left out to keep it small."""
    from torchvision import models

    torch.manual_seed(0)
    backbone = models.alexnet() if net == "alex" else models.vgg16()
    state = {f"features.{k}": v for k, v in backbone.features.state_dict().items()}
    path = lpips_backbone_file(net)
    assert path.parent == torch_home / "hub" / "checkpoints"
    path.parent.mkdir(parents=True)
    torch.save(state, path)
    return state


def test_no_local_weights_means_no_lpips_and_no_download(torch_home):
    assert LPIPS.load("alex") is None and LPIPS.load("vgg") is None
    assert lpips_backbone_file("alex") == torch_home / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    assert lpips_backbone_file("vgg") == torch_home / "hub" / "checkpoints" / "vgg16-397923af.pth"


@pytest.mark.parametrize(("net", "last"), [("alex", "slice5.10"), ("vgg", "slice5.28")])
def test_local_backbone_weights_are_used(torch_home, net, last):
    state = place_random_backbone(torch_home, net)
    metric = LPIPS.load(net)
    assert metric is not None and metric.backbone == lpips_backbone_file(net)
    layers = metric.model.net.state_dict()
    assert torch.equal(layers["slice1.0.weight"], state["features.0.weight"])
    index = last.split(".")[1]
    assert torch.equal(layers[f"{last}.weight"], state[f"features.{index}.weight"])
    gen = torch.Generator().manual_seed(1)
    a, b = torch.rand(48, 64, 3, generator=gen), torch.rand(48, 64, 3, generator=gen)
    assert metric(a, a) == 0.0
    # (H, W, 3) in [0, 1] becomes the package's NCHW input: the same as its own [0, 1] normalisation.
    expected = metric.model(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], normalize=True).item()
    assert metric(a, b) == pytest.approx(expected, rel=1e-6) and metric(a, b) > 0
    with pytest.raises(ValueError, match="lpips"):
        metric(a, b[:10])


def test_a_corrupt_backbone_file_is_a_clear_error(torch_home):
    path = lpips_backbone_file("alex")
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not a tensor file")
    with pytest.raises(StgsError, match="not usable as the LPIPS alex backbone"):
        LPIPS.load("alex")
