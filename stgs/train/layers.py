"""Layered training (model format 2): what moves, which static Gaussians move to the dynamic layer, and where
each GOP's dynamic layer starts.

- `moving_masks`: per training view, the pixels stage A (the static layer) must not explain: the dataset's
  foreground masks where it has them (dilated), otherwise a per-pixel temporal-variance mask of the camera's
  images over the trained span (the dynamic-density test of stgs.train.dynamic).
- `motion_scores` (measured, where Swift4D's decomposition is learned): for each static Gaussian and each
  camera that sees its mean, the share of the frames in which it lands on a moving pixel; its score is the
  least of those over the cameras. Something that moves is on moving pixels from every side; a wall is
  behind a player from some cameras only (from those the player may hide it all the time), so one camera
  that sees it clear keeps it static. A Gaussian fewer than MIN_SCORE_CAMERAS cameras see scores 0.
- `migrate`: Gaussians above the score leave the static layer (their slots are parked, as pruning parks)
  and seed every GOP's dynamic layer, with their attributes.
- `fit_view_dependent` (optional, `static_sh_degree` 1): after stage A, the static layer's colour and its
  degree-1 view-dependent term are fitted on the same pixels, geometry and opacity frozen (so migration's
  parked slots stay parked).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from tqdm import tqdm

from stgs.camera import Camera
from stgs.codec.attributes import OPACITY_LOGIT_RANGE
from stgs.data import Dataset
from stgs.errors import StgsError
from stgs.metrics import psnr
from stgs.model.gop import GOPModel
from stgs.model.renderer import splat, static_view
from stgs.model.static import STATIC_TENSORS, StaticLayer
from stgs.train import losses
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.dynamic import variance_mask
from stgs.train.images import Views
from stgs.train.seeding import InitialPoints, init_canonical
from stgs.train.triangulate import grown, in_view

MIN_SCORE_CAMERAS = 2
"""Cameras that must see a Gaussian before its motion can be told from occlusion."""
MASK_DILATE_PX = 5
"""Foreground masks grow by this many pixels (at the training scale): a mask's edge is rarely exact and a
player's shadow moves with the player."""


@dataclass
class MovingMasks:
    """(F, C, H, W) bool: the pixels of each training view that move, and where that came from."""

    masks: torch.Tensor
    source: str
    """"dataset foreground masks", "temporal variance" or both (per camera, whichever it had)."""


def grown_mask(mask: torch.Tensor, width: int, height: int, px: int = MASK_DILATE_PX) -> torch.Tensor:
    """(height, width) bool: a foreground `mask` at that size (nearest pixel), grown by `px` pixels."""
    small = cv2.resize(mask.numpy().astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(grown(small, px) > 0)


def static_background_psnr(static: StaticLayer, ds: Dataset, names: list[str], frames: list[int], grow: int = 0,
                           colour: CameraColour | None = None, indices: list[int] | None = None) -> float:
    """Mean PSNR of the static layer drawn alone, from cameras `names` at `frames`, over the pixels outside each
    view's foreground mask grown by `grow` pixels; with `colour`, drawn through the colour responses of the
    training cameras at `indices` (each name's place among them)."""
    values = []
    for frame in frames:
        cams = {c.name: c for c in ds.cameras(frame)}
        for k, name in enumerate(names):
            cam, mask = cams[name], ds.mask(frame, name)
            if mask is None:
                raise StgsError(f"{ds.name}: camera {name} has no foreground mask at frame {frame}")
            with torch.no_grad():
                image = splat(static_view(static, cam), cam, guarded=True)
                if colour is not None and indices is not None:
                    image = as_recorded(colour, image, indices[k])
            keep = ~grown_mask(mask, cam.width, cam.height, grow)
            values.append(psnr(image.clamp(0, 1), ds.image(frame, name), mask=keep))
    return sum(values) / len(values)


@dataclass
class MovingPixels:
    """The moving pixels of the training views (a stgs.train.images.MaskSource): the dataset's foreground masks,
    grown, for a camera that has one at the span's first frame (then it must have one at every frame); one
    temporal-variance mask over the span for a camera that has none."""

    ds: Dataset
    cameras: list[Camera]
    """The training cameras at the training scale."""
    fixed: dict[int, np.ndarray]
    """Temporal-variance masks, by camera position."""
    source: str
    """"dataset foreground masks", "temporal variance" or both (per camera, whichever it had)."""

    def __call__(self, frame: int, c: int) -> np.ndarray:
        if c in self.fixed:
            return self.fixed[c]
        cam = self.cameras[c]
        mask = self.ds.mask(frame, cam.name)
        if mask is None:
            raise StgsError(f"{self.ds.name}: camera {cam.name} has foreground masks, but none at frame {frame}")
        return grown_mask(mask, cam.width, cam.height).numpy()


def moving_pixels(ds: Dataset, views: Views, theta: float) -> MovingPixels:
    """The moving pixels of every view in `views` (see the module docstring), reading one view at a time."""
    fixed, sources = {}, set()
    for j, cam in enumerate(views.cameras):
        if ds.mask(views.frames[0], cam.name) is not None:
            sources.add("dataset foreground masks")
        elif len(views.frames) >= 2:
            fixed[j] = variance_mask((views.decoded(i, j) for i in range(len(views.frames))), theta)
            sources.add("temporal variance")
        else:
            fixed[j] = np.zeros((cam.height, cam.width), dtype=bool)
    return MovingPixels(ds, views.cameras, fixed, " and ".join(sorted(sources)) or "none (one frame)")


@torch.no_grad()
def motion_scores(model: GOPModel, views: Views, moving: MovingPixels) -> tuple[torch.Tensor, float]:
    """(N,) the least, over the cameras that see a Gaussian's mean, of the share of frames that put it on a
    moving pixel (0 for a Gaussian fewer than MIN_SCORE_CAMERAS cameras see); and the share of all the views'
    pixels that move. One mask at a time."""
    n, frames = model.shape.capacity, views.frames
    least = torch.ones(n)
    seen = torch.zeros(n)
    xyz = model.xyz.detach().double().numpy()
    moved = pixels = 0
    for j, cam in enumerate(views.cameras):
        uv, inside = in_view(cam, xyz)
        idx = torch.from_numpy(inside.nonzero()[0])
        u, v = (np.floor(uv[inside, k]).astype(np.int64) for k in (0, 1))
        hits, fixed = np.zeros(len(idx)), j in moving.fixed
        for frame in frames[:1] if fixed else frames:  # a fixed mask is the same at every frame
            mask = moving(frame, j)
            hits += mask[v, u]
            weight = len(frames) if fixed else 1
            moved, pixels = moved + weight * int(mask.sum()), pixels + weight * mask.size
        share = hits if fixed else hits / len(frames)
        if len(idx):
            least[idx] = torch.minimum(least[idx], torch.from_numpy(share).float())
            seen[idx] += 1
    return torch.where(seen >= MIN_SCORE_CAMERAS, least, torch.zeros_like(least)), moved / max(1, pixels)


@dataclass
class Migrated:
    """Static Gaussians that the data shows moving, handed to the dynamic layers."""

    index: torch.Tensor
    """(M,) their slots in the static layer (parked there)."""
    attributes: dict[str, torch.Tensor]
    """Their canonical attributes (xyz, log_scale, rotation, opacity_logit, color), (M, ...) each."""
    scores: torch.Tensor
    """(N,) every static Gaussian's motion score."""


MIGRATED_ATTRIBUTES = ("xyz", "log_scale", "rotation", "opacity_logit", "color")


@torch.no_grad()
def migrate(model: GOPModel, scores: torch.Tensor, threshold: float, limit: int, dead_opacity: float) -> Migrated:
    """Move the live Gaussians scoring above `threshold` (at most `limit`, highest first) out of the static
    layer: their attributes are returned and their slots parked at the stream's floor opacity."""
    alive = torch.sigmoid(model.opacity_logit) >= dead_opacity
    candidates = ((scores > threshold) & alive).nonzero().squeeze(1)
    order = scores[candidates].argsort(descending=True, stable=True)
    index = candidates[order][:limit].sort().values
    attributes = {name: getattr(model, name)[index].clone() for name in MIGRATED_ATTRIBUTES}
    if len(index):
        model.opacity_logit[index] = OPACITY_LOGIT_RANGE[0]
        keep = torch.ones(model.shape.capacity, dtype=torch.bool)
        keep[index] = False
        if keep.any():
            model.log_scale[index] = model.log_scale[keep].amin(0)
    return Migrated(index, attributes, scores)


@torch.no_grad()
def init_dynamic(model: GOPModel, init: InitialPoints, migrated: Migrated | None) -> int:
    """A GOP's dynamic layer at its start: the migrated Gaussians first (as they were in the static layer),
    then `init`'s points (3DGS-style attributes) in the remaining slots, and no opacity offset (ΔO = 0: the
    opacity decoder's output layer starts at zero). Returns how many were migrated in.

    The seeded opacities (0.02–0.1) are as small as a randomly initialised ΔO; where ΔO is negative the
    opacity clamps at 0 and neither it nor ΔO gets a gradient again: a whole layer can start dead."""
    init_canonical(model, init)
    last = model.field.d_opacity[-1]
    assert isinstance(last, torch.nn.Linear)
    last.weight.zero_()
    if migrated is None or len(migrated.index) == 0:
        return 0
    m = min(len(migrated.index), model.shape.capacity)
    for name, values in migrated.attributes.items():
        getattr(model, name)[:m] = values[:m]
    return m


def fit_view_dependent(static: StaticLayer, views: Views, draws: list[tuple[int, int, int]], lr: float,
                       lambda_ssim: float, progress: bool = False, colour: CameraColour | None = None
                       ) -> StaticLayer:
    """A degree-1 copy of `static` whose colour and sh1 are fitted on the pixels that do not move, one view per
    iteration (`draws`: stgs.train.images.view_draws); positions, scales, rotations and opacities stay."""
    layer = StaticLayer.from_canonical(static, 1, static.sh1 if static.sh_degree else None)
    for name in STATIC_TENSORS:
        getattr(layer, name).requires_grad_(name == "color")
    opt = torch.optim.Adam([layer.color, layer.sh1], lr=lr, eps=1e-15)
    views.plan(draws)
    for f, c, level in tqdm(draws, desc="static layer: view-dependent colour", unit="it", disable=not progress):
        view = views.at(level).sample(f, c)
        img = as_recorded(colour, splat(layer.gaussians(view.cam.center.float()), view.cam), c)
        moving = view.dynamic
        loss = losses.photometric(img, view.target, lambda_ssim, ~moving if moving is not None else None)
        if not torch.isfinite(loss):
            raise StgsError(f"the static layer's view-dependent colour fit diverged (loss {loss.item()}); "
                            "lower the colour learning rate or fit without it")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    layer.requires_grad_(True)
    return layer
