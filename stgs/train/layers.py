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

from stgs.codec.attributes import OPACITY_LOGIT_RANGE
from stgs.data import Dataset
from stgs.errors import StgsError
from stgs.metrics import psnr
from stgs.model.gop import GOPModel
from stgs.model.static import STATIC_TENSORS, StaticLayer
from stgs.model.view import splat, static_view
from stgs.train import losses
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.dynamic import dynamic_mask
from stgs.train.init import grown, in_view
from stgs.train.seeding import InitialPoints, init_canonical
from stgs.train.views import Views

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


def moving_masks(ds: Dataset, views: Views, theta: float) -> MovingMasks:
    """The moving pixels of every view in `views` (see the module docstring)."""
    f, c, h, w = views.images.shape[:4]
    masks = torch.zeros(f, c, h, w, dtype=torch.bool)
    sources = set()
    for j, cam in enumerate(views.cameras):
        found = [ds.mask(frame, cam.name) for frame in views.frames]
        if all(m is not None for m in found):
            for i, m in enumerate(found):
                masks[i, j] = grown_mask(m, w, h)
            sources.add("dataset foreground masks")
        elif f >= 2:
            masks[:, j] = dynamic_mask(views.images[:, j].float().div_(255.0), theta)
            sources.add("temporal variance")
    return MovingMasks(masks, " and ".join(sorted(sources)) or "none (one frame)")


@torch.no_grad()
def motion_scores(model: GOPModel, views: Views, moving: torch.Tensor) -> torch.Tensor:
    """(N,) the least, over the cameras that see a Gaussian's mean, of the share of frames that put it on a
    moving pixel (0 for a Gaussian fewer than MIN_SCORE_CAMERAS cameras see)."""
    n = model.shape.capacity
    least = torch.ones(n)
    seen = torch.zeros(n)
    xyz = model.xyz.detach().double().numpy()
    for j, cam in enumerate(views.cameras):
        uv, inside = in_view(cam, xyz)
        idx = torch.from_numpy(inside.nonzero()[0])
        if len(idx) == 0:
            continue
        u, v = (torch.from_numpy(np.floor(uv[inside, k])).long() for k in (0, 1))
        share = moving[:, j, v, u].float().mean(0)  # over frames, per visible Gaussian
        least[idx] = torch.minimum(least[idx], share)
        seen[idx] += 1
    return torch.where(seen >= MIN_SCORE_CAMERAS, least, torch.zeros_like(least))


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
    model.field.d_opacity[-1].weight.zero_()
    if migrated is None or len(migrated.index) == 0:
        return 0
    m = min(len(migrated.index), model.shape.capacity)
    for name, values in migrated.attributes.items():
        getattr(model, name)[:m] = values[:m]
    return m


def fit_view_dependent(static: StaticLayer, views: Views, moving: torch.Tensor, iterations: int, lr: float,
                       lambda_ssim: float, gen: torch.Generator, progress: bool = False,
                       colour: CameraColour | None = None) -> StaticLayer:
    """A degree-1 copy of `static` whose colour and sh1 are fitted for `iterations` on the pixels that do not
    move (one random training view per iteration); positions, scales, rotations and opacities stay."""
    layer = StaticLayer.from_canonical(static, sh_degree=1)
    for name in STATIC_TENSORS:
        getattr(layer, name).requires_grad_(name == "color")
    opt = torch.optim.Adam([layer.color, layer.sh1], lr=lr, eps=1e-15)
    for _ in tqdm(range(iterations), desc="static layer: view-dependent colour", unit="it", disable=not progress):
        f = int(torch.randint(len(views.frames), (1,), generator=gen))
        c = int(torch.randint(len(views.cameras), (1,), generator=gen))
        cam = views.cameras[c]
        img = splat(layer.gaussians(cam.center.float()), cam)
        img = as_recorded(colour, img, c)
        loss = losses.photometric(img, views.target(f, c), lambda_ssim, ~moving[f, c])
        if not torch.isfinite(loss):
            raise StgsError(f"the static layer's view-dependent colour fit diverged (loss {loss.item()}); "
                            "lower the colour learning rate or fit without it")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    layer.requires_grad_(True)
    return layer
