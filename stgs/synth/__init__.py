"""Synthetic scenes (`stgs synth`): ground-truth multi-view images + a fitted StreamSTGS model dir.

The output is a model dir (docs/MODEL_FORMAT.md) that `stgs pack` accepts as
it is, with the ground truth inside it under `gt/`:

    OUT/model.json, OUT/gop_0000.safetensors, ...
    OUT/gt/cameras.json, OUT/gt/<camera>/<frame:05d>.png
    OUT/gt/masks/<camera>/<frame:05d>.png   foreground masks (the ring, the blob, the sparks)
    OUT/synth_report.json   fit errors and rendered fidelity vs the ground truth

With the static_background effect the scene is layered (model format 2): the
backdrop is the static layer, taken exactly from the truth (it never moves, so
there is nothing to fit), and the GOPs fit the rest as before. With `fold` the
same scene is written as format 1 instead: every GOP fits the backdrop too
(stgs.synth.scene.FoldedScene), the single-layer model to compare with.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from stgs.lazy import lazy_attributes
from stgs.synth.config import DEFAULT_EFFECTS, EFFECTS, PRESETS, SCENE_TARGET, SynthConfig, config_from_toml

if TYPE_CHECKING:
    from stgs.synth.generate import (
        SynthReport,
        ground_truth_cameras,
        load_ground_truth,
        measure_fidelity,
        synthesize,
        truth_static_layer,
    )

__all__ = ["DEFAULT_EFFECTS", "EFFECTS", "PRESETS", "SCENE_TARGET", "SynthConfig", "SynthReport", "config_from_toml",
           "ground_truth_cameras", "load_ground_truth", "measure_fidelity", "synthesize", "truth_static_layer"]
# The generator (torch) loads on first use, so that the presets and effects stay light.
__getattr__ = lazy_attributes(__name__, dict.fromkeys(("SynthReport", "ground_truth_cameras", "load_ground_truth",
                                                       "measure_fidelity", "synthesize", "truth_static_layer"),
                                                      "stgs.synth.generate"))
