"""Each training camera's colour response, learnt beside the scene and never shipped.

The cameras of a real rig do not agree on colour: white balance and gain differ from one to the next. A scene
fitted to all of them at once has only one way to please each: view-dependent colour made of geometry, Gaussians
in front of the walls tinted for the cameras that see them, which a camera not trained on then sees as coloured
blotches. So, as Dynamic 3D Gaussians does on the
same captures, each training camera c gets a per-channel gain and offset applied to the drawn image before the
loss: image · exp(g_c) + o_c. The gains and offsets are zero-mean over the cameras, so the scene keeps the colour
of the average training camera, which is what held-out cameras and the stream render (no transform at all).
"""

from __future__ import annotations

import torch


class CameraColour(torch.nn.Module):
    """Per-channel log-gains and offsets of `cameras` training cameras, zero at the start (the identity)."""

    def __init__(self, cameras: int):
        super().__init__()
        if cameras < 1:
            raise ValueError(f"CameraColour needs at least one camera, got {cameras}")
        self.log_gain = torch.nn.Parameter(torch.zeros(cameras, 3))
        self.offset = torch.nn.Parameter(torch.zeros(cameras, 3))

    def centred(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(log-gains, offsets) less their means over the cameras: the transforms applied."""
        return self.log_gain - self.log_gain.mean(0), self.offset - self.offset.mean(0)

    def forward(self, image: torch.Tensor, camera: int) -> torch.Tensor:
        """(H, W, 3) `image` as training camera `camera` records it."""
        log_gain, offset = self.centred()
        return image * torch.exp(log_gain[camera]) + offset[camera]

    def summary(self, names: list[str]) -> dict[str, list[float]]:
        """Per camera name: its three gains and three offsets (for the training report)."""
        with torch.no_grad():
            log_gain, offset = self.centred()
            return {name: [round(float(v), 4) for v in (*torch.exp(g), *o)]
                    for name, g, o in zip(names, log_gain, offset, strict=True)}


def as_recorded(colour: CameraColour | None, image: torch.Tensor, camera: int) -> torch.Tensor:
    """`image` through training camera `camera`'s colour response; `image` itself when no colours are learnt."""
    return image if colour is None else colour(image, camera)
