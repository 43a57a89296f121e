"""Multi-view video datasets behind one reader interface (`open_dataset`).

A dataset is synchronized frames from calibrated cameras: `cameras(frame)`
(OpenCV pinhole, world-to-camera), `image(frame, camera)` as (H, W, 3)
float32 RGB in [0, 1], `mask(frame, camera)` (foreground, (H, W) bool) where
the dataset has masks; `pixels(frame, camera)` is the image as stored, uint8. Readers:

- `PanopticReader`: the Panoptic / Dynamic 3D Gaussians layout
  (`train_meta.json`, `ims/<cam>/<frame>.jpg`, `seg/<cam>/<frame>.png`);
- `N3DVReader`: Neural 3D Video (LLFF `poses_bounds.npy` + `cam*.mp4`),
  frames decoded once (PyAV) and downscaled by 2 (the custom);
- `SynthReader`: the ground truth inside a `stgs synth` model dir;
- `NerfstudioReader`: a nerfstudio `transforms.json` whose images say their camera and time;
- `ColmapReader`: a COLMAP model beside per-frame folders, per-camera folders or per-camera videos
  (stgs.data.capture; docs/CAPTURE.md).

`split(dataset, holdout)` gives the train / validation camera names.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from stgs.errors import StgsError

if TYPE_CHECKING:  # the package's names load no torch: the command line's parsers read KINDS
    import numpy as np
    import torch

    from stgs.camera import Camera


class Dataset(Protocol):
    name: str
    fps: float
    num_frames: int
    camera_names: list[str]
    default_holdout: list[str]
    """Validation cameras by convention (N3DV: cam00)."""

    def cameras(self, frame: int) -> list[Camera]:
        """Every camera at `frame`, in camera_names order."""

    def image(self, frame: int, camera: str) -> torch.Tensor:
        """(H, W, 3) float32 RGB in [0, 1]."""

    def pixels(self, frame: int, camera: str) -> np.ndarray:
        """The same view as (H, W, 3) uint8 RGB, as stored (what training's view cache decodes: no float copy)."""

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        """(H, W) bool foreground mask, or None when the dataset has none."""

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Reconstructed 3D points at `frame` ((P, 3) float32 positions, (P, 3) colours in [0, 1]) that seed
        training instead of triangulating, or None where the dataset has none (a COLMAP model's points3D)."""

    def check_views(self, frames: list[int], cameras: list[str]) -> None:
        """Raise StgsError (one line) unless every view of `frames` x `cameras` is present and of its camera's
        size, looking at no more than the files' headers: what a run checks before it trains."""


def check_frame(ds: Dataset, frame: int) -> None:
    if not 0 <= frame < ds.num_frames:
        raise StgsError(f"{ds.name}: frame {frame} is outside 0..{ds.num_frames - 1}")


def split(ds: Dataset, holdout: list[str] | None = None) -> tuple[list[str], list[str]]:
    """(train, validation) camera names; `holdout` names the validation cameras (None: the dataset's default)."""
    val = list(ds.default_holdout if holdout is None else holdout)
    unknown = sorted(set(val) - set(ds.camera_names))
    if unknown:
        raise StgsError(f"{ds.name}: no camera(s) {unknown} to hold out; cameras are {', '.join(ds.camera_names)}")
    train = [c for c in ds.camera_names if c not in val]
    if not train:
        raise StgsError(f"{ds.name}: holding out {val} leaves no training camera")
    return train, val


KINDS = ("panoptic", "n3dv", "synth", "nerfstudio", "colmap-frames", "colmap-images", "colmap-videos")
"""Dataset layouts, in the order `--kind auto` tries them."""


def detect_kind(path: Path) -> str | None:
    """The first of KINDS whose layout `path` has, or None."""
    from stgs.data.capture import detect_layout
    from stgs.data.n3dv import N3DVReader
    from stgs.data.nerfstudio import NerfstudioReader
    from stgs.data.panoptic import PanopticReader
    from stgs.data.synth import SynthReader

    path = Path(path)
    for kind, reader in (("panoptic", PanopticReader), ("n3dv", N3DVReader), ("synth", SynthReader),
                         ("nerfstudio", NerfstudioReader)):
        if reader.recognises(path):
            return kind
    layout = detect_layout(path)
    return f"colmap-{layout}" if layout else None


def open_dataset(path: Path, kind: str = "auto", **options) -> Dataset:
    """The reader for `path` (kind: auto or one of KINDS); `options` go to the reader (holdout, fps: a frame rate
    for captures whose files do not say it, None for the reader's own, ...)."""
    from stgs.data.capture import ColmapReader
    from stgs.data.n3dv import N3DVReader
    from stgs.data.nerfstudio import NerfstudioReader
    from stgs.data.panoptic import PanopticReader
    from stgs.data.synth import SynthReader

    path = Path(path)
    if kind == "auto":
        if not path.exists():
            raise StgsError(f"{path}: no such file or folder")
        kind = detect_kind(path) or ""
        if not kind:
            raise StgsError(f"{path}: not a dataset this version reads (Panoptic train_meta.json, N3DV "
                            "poses_bounds.npy + cam*.mp4, a stgs synth model dir, a nerfstudio transforms.json, "
                            "or a COLMAP sparse/0 beside frameNNNNNN/images, images/<cam> or videos/; "
                            "docs/CAPTURE.md)")
    if kind not in KINDS:
        raise StgsError(f"unknown dataset kind {kind!r}; known: auto, {', '.join(KINDS)}")
    if options.get("fps") is None:
        options.pop("fps", None)
    elif kind in ("panoptic", "synth"):
        raise StgsError(f"{path}: a {kind} capture says its own frame rate; fps is for captures of image files")
    if kind.startswith("colmap-"):
        return ColmapReader(path, layout=kind.removeprefix("colmap-"), **options)
    readers = {"panoptic": PanopticReader, "n3dv": N3DVReader, "synth": SynthReader, "nerfstudio": NerfstudioReader}
    return readers[kind](path, **options)
