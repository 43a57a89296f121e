"""The unit of length a model is trained in, whatever the capture's.

Captures come in metres, centimetres or COLMAP's arbitrary units. Some of what training does is not invariant to
the unit: the deformation field's position offsets are in world units, with learning rates and an initialisation
that are not; the splatter's near plane (stgs.render.project.NEAR_Z), triangulation's minimum depth and the seeds'
smallest jitter are fixed lengths. And training is chaotic: a capture scaled by a hair trains to a visibly
different model (docs/CAPTURE.md, "Units"), so invariance has to be exact to hold at all.

So the trainer reads a capture scaled about the origin by `world_scale`: 1 where the rig's size
(stgs.camera.rig_size) is within a factor √2 of REFERENCE_SIZE, the size its fixed lengths were set for (a capture
of about that size trains exactly as it always did: Panoptic, the synthetic scenes), and REFERENCE_SIZE / size
otherwise, so that the same capture in metres, centimetres or millimetres trains to the same model. The model dir
is in the scaled frame (its cameras.json too) and records the factor; `stgs eval` reads the capture through it.
"""

from __future__ import annotations

import math

import torch

from stgs.camera import Camera, rig_size
from stgs.data import Dataset

REFERENCE_SIZE = 3.5
"""The rig size the trainer's fixed lengths were set for: about Panoptic's dome and the synthetic orbit
(docs/CAPTURE.md, "Units")."""


def world_scale(cameras: list[Camera]) -> float:
    """The factor from the capture's lengths to the model's: 1 for a rig within a factor √2 of REFERENCE_SIZE
    (or one whose cameras stand at one point), else REFERENCE_SIZE / its size."""
    size = rig_size(cameras)
    if not size > 0 or not math.isfinite(size):
        return 1.0
    ratio = REFERENCE_SIZE / size
    return 1.0 if 1 / math.sqrt(2) <= ratio < math.sqrt(2) else ratio


def scale_view(cam: Camera, factor: float) -> Camera:
    """The camera in a world scaled by `factor` about the origin (its translation scaled; K and rotation kept)."""
    view = cam.viewmat.clone()
    view[:3, 3] *= factor
    return Camera(cam.name, cam.K, view, cam.width, cam.height)


class Rescaled:
    """A dataset read in a world scaled by `factor` about the origin: its cameras and points; the rest as it is."""

    def __init__(self, ds: Dataset, factor: float):
        self.ds, self.factor = ds, float(factor)

    def __getattr__(self, name: str):
        if name == "ds":  # not set yet (an unpickled copy): no recursion
            raise AttributeError(name)
        return getattr(self.ds, name)

    def cameras(self, frame: int) -> list[Camera]:
        return [scale_view(c, self.factor) for c in self.ds.cameras(frame)]

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        found = self.ds.points(frame)
        if found is None:
            return None
        xyz, rgb = found
        return xyz * self.factor, rgb


def in_model_units(ds: Dataset, factor: float) -> Dataset:
    """`ds` in the model's unit of length (`factor`: world_scale, as the trainer found it or a model records it);
    `ds` itself where the factor is 1."""
    return ds if factor == 1.0 else Rescaled(ds, factor)
