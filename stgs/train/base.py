"""The base stage's result: what every GOP's training starts from, saved so that GOPs can train anywhere.

Single-layer training (format 1): the coarse canonical model. Layered training (format 2): the static layer and
the Gaussians that migrated out of it. Either: the training cameras' colour responses (stgs.train.camera_colour),
which every GOP's images go through. All go into one safetensors file in the run's state folder, with the
stage's counts and timing as JSON metadata (no pickle); a GOP task, in this process or on a Ray worker, loads it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from stgs.model.gop import GOPModel, GOPShape
from stgs.model.static import StaticLayer
from stgs.train.camera_colour import CameraColour
from stgs.train.checkpoint import module_tensors, under
from stgs.train.layers import MIGRATED_ATTRIBUTES, Migrated

BASE_FILE = "base.safetensors"
"""The base stage's result in the run's state folder."""


@dataclass
class BaseStage:
    coarse: GOPModel | None = None
    """The coarse canonical model every GOP starts from (single-layer training)."""
    static: StaticLayer | None = None
    """The static layer (layered training)."""
    migrated: Migrated | None = None
    """The static Gaussians the data shows moving (layered training)."""
    colour: CameraColour | None = None
    """The training cameras' colour responses (TrainConfig.camera_colour)."""
    info: dict = field(default_factory=dict)
    """Counts and seconds for the training report (triangulated and background points, layer facts)."""

    def save(self, path: Path) -> None:
        tensors: dict[str, torch.Tensor] = {}
        if self.coarse is not None:
            tensors |= module_tensors("coarse", self.coarse)
        if self.static is not None:
            tensors |= module_tensors("static", self.static)
        if self.migrated is not None:
            tensors |= {"migrated.index": self.migrated.index.contiguous(),
                        "migrated.scores": self.migrated.scores.contiguous()}
            tensors |= {f"migrated.{k}": v.contiguous() for k, v in self.migrated.attributes.items()}
        if self.colour is not None:
            tensors |= module_tensors("colour", self.colour)
        meta = {"info": self.info, "static_sh_degree": self.static.sh_degree if self.static is not None else None}
        tmp = path.with_suffix(".tmp")
        save_file(tensors, str(tmp), metadata={"base": json.dumps(meta)})
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path, shape: GOPShape) -> BaseStage:
        """The base stage saved at `path`; `shape`: the GOP models' shape (the coarse model has it)."""
        with safe_open(str(path), "pt") as f:
            meta = json.loads(f.metadata()["base"])
        tensors = load_file(str(path))
        base = cls(info=meta["info"])
        if coarse := under(tensors, "coarse"):
            base.coarse = GOPModel(shape)
            base.coarse.load_state_dict(coarse)
        if static := under(tensors, "static"):
            base.static = StaticLayer(static["xyz"].shape[0], meta["static_sh_degree"])
            base.static.load_state_dict(static)
        if "migrated.index" in tensors:
            base.migrated = Migrated(tensors["migrated.index"], {k: tensors[f"migrated.{k}"] for k in
                                                                 MIGRATED_ATTRIBUTES}, tensors["migrated.scores"])
        if colour := under(tensors, "colour"):
            base.colour = CameraColour(colour["log_gain"].shape[0]).requires_grad_(False)
            base.colour.load_state_dict(colour)
        return base
