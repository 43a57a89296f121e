"""The canonical stages: format 1's coarse stage and layered training's stage A, which fits the static layer on
the pixels that do not move (stgs.train.trainer's step 3). Each is a function of the run it is part of (a
`StageContext`: the Trainer is one) that returns what it made; the trainer keeps the results."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from tqdm import tqdm

from stgs.data import Dataset
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.renderer import splat
from stgs.model.static import STATIC_TENSORS, StaticLayer
from stgs.picks import spread
from stgs.train import losses
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.checkpoint import Checkpoints
from stgs.train.config import TrainConfig
from stgs.train.images import Views, view_draws
from stgs.train.objective import canonical_regularisers, drop_gaussians
from stgs.train.ops import Optimizer, relocate, sort
from stgs.train.seeding import init_canonical, initial_points

STAGE_A = "static"
"""Stage A's name (its seed, checkpoints and regularisers): the static layer of a layered or still scene."""


class StageContext(Protocol):
    """What a canonical stage reads of its run."""

    cfg: TrainConfig
    ds: Dataset
    train_names: list[str]
    extent: float
    world_scale: float
    checkpoints: Checkpoints
    gen: torch.Generator
    progress: bool

    def seed_stage(self, stage: str) -> None: ...

    def step(self, opt: Optimizer, loss: torch.Tensor, stage: str, it: int, model: GOPModel) -> None: ...


@dataclass
class CanonicalFit:
    """What a canonical stage made."""

    model: GOPModel
    colour: CameraColour | None
    """The training cameras' colour responses, frozen (None: TrainConfig.camera_colour off)."""
    triangulated: int | None
    """Initial points triangulated (None: the stage started from a model)."""
    background_points: int | None
    """Of those, the points placed on the rig's walls and floor."""


@dataclass
class ImportedStatic:
    """Stage A's model brought in from a 3DGS file (TrainConfig.static_from)."""

    model: GOPModel
    layer: StaticLayer
    """The file's layer as read (before any refinement)."""
    report: dict[str, Any]
    """How the file was brought in (the trainer's layer facts)."""
    refined: CanonicalFit | None
    """The fine-tuning on the pixels that do not move (TrainConfig.static_refine), if any."""


def fit_canonical(ctx: StageContext, views: Views, shape: GOPShape, stage: str = "coarse",
                  start_model: GOPModel | None = None, iterations: int | None = None) -> CanonicalFit:
    """Canonical 3DGS (no deformation) on frames from all times, with each training camera's colour response
    (TrainConfig.camera_colour); on views with moving-pixel masks, on the pixels that do not move only, with the
    GOP stage's regularisers (stage A). Starts from triangulated points, or fine-tunes `start_model` for
    `iterations` (default: the config's coarse iterations). Resumes from and saves the run's checkpoints."""
    trainer = ctx
    cfg = trainer.cfg
    trainer.seed_stage(stage)
    total = cfg.coarse_iterations if iterations is None else iterations
    model = start_model if start_model is not None else GOPModel(shape)
    colour = CameraColour(len(views.cameras)) if cfg.camera_colour else None
    opt = Optimizer(model, cfg, trainer.extent, None, canonical_only=True, colour=colour)
    resumed = trainer.checkpoints.load(stage, model, opt, trainer.gen, {"colour": colour})
    start = resumed[0]["iteration"] if resumed else 0
    triangulated: int | None = None
    background: int | None = None
    if resumed:  # the counts the interrupted run found, for the report
        triangulated, background = resumed[0].get("triangulated"), resumed[0].get("background")
    elif start_model is None:
        region = "background" if views.masked and cfg.static_triangulation else "foreground"
        init = initial_points(trainer.ds, trainer.train_names, spread(views.frames, cfg.init_frames),
                              shape.capacity, trainer.gen, cfg.init_points, cfg.background_share, region=region)
        triangulated, background = init.triangulated, init.background
        init_canonical(model, init)

    def state(iteration: int) -> dict:
        """A checkpoint's JSON: the iteration and the initial points' counts, for the report."""
        return {"iteration": iteration, "triangulated": triangulated, "background": background}

    # Stage A's layer is final (no GOP stage refines it): it gets the GOP stage's regularisers, which
    # measurably generalise better to cameras not trained on (docs/BENCHMARKS.md, "Layered scenes"). A layered
    # scene's stage A draws masked views; a still's draws every pixel (nothing moves in one moment).
    regularised = stage == STAGE_A
    sorting = regularised and cfg.smooth_weight > 0
    if sorting and start == 0:
        sort(model, opt, torch.zeros(2, shape.capacity), cfg.seed)
    desc = "stage A: static layer" if regularised else "coarse canonical"
    low_until = round(cfg.coarse_low_res * total)
    drop_until = round(cfg.static_drop_until * total) if regularised else 0
    draws = view_draws(cfg.seed, stage, total, *views.counts, low_until)
    views.plan(draws[start:])
    bar = tqdm(range(start, total), desc=desc, unit="it", disable=not trainer.progress)
    for it in bar:
        opt.set_progress(it / max(1, total))
        f, c, level = draws[it]
        view = views.at(level).sample(f, c)
        g = model.canonical()
        drawn = drop_gaussians(g, cfg.static_drop_rate, trainer.gen) if it < drop_until else g
        img = as_recorded(colour, splat(drawn, view.cam), c)
        mask = ~view.dynamic if view.dynamic is not None else None
        loss = losses.photometric(img, view.target, cfg.lambda_ssim, mask)
        if regularised:
            loss = loss + canonical_regularisers(cfg, model, g.opacities)
        trainer.step(opt, loss, stage, it, model)
        if sorting and (it + 1) % cfg.sort_every == 0 and it + 1 < total:
            sort(model, opt, torch.zeros(2, shape.capacity), cfg.seed)
        if cfg.relocate and (it + 1) % cfg.relocate_every == 0 and it < cfg.relocate_until * total:
            relocate(model, opt, torch.sigmoid(model.opacity_logit.detach()), cfg.dead_opacity, trainer.gen)
        if (it + 1) % cfg.checkpoint_every == 0:
            trainer.checkpoints.save(stage, model, opt, trainer.gen, state(it + 1), {"colour": colour})
    if total:
        trainer.checkpoints.save(stage, model, opt, trainer.gen, state(total), {"colour": colour})
    return CanonicalFit(model, colour.requires_grad_(False) if colour is not None else None, triangulated, background)


def imported_static_model(ctx: StageContext, views: Views) -> ImportedStatic:
    """Stage A's model from TrainConfig.static_from (stgs.interop.static), fine-tuned for static_refine
    iterations on the pixels that do not move."""
    from stgs.interop.static import import_static

    trainer = ctx
    cfg = trainer.cfg
    if cfg.static_from is None:
        raise ValueError("static_from: no 3DGS file given")
    matrix = None if cfg.static_transform is None else np.asarray(cfg.static_transform, dtype=np.float64).reshape(4, 4)
    if trainer.world_scale != 1.0 and cfg.static_cameras is None:  # the file is in the capture's unit of length
        units = np.diag([trainer.world_scale] * 3 + [1.0])
        matrix = units if matrix is None else units @ matrix
    layer, report = import_static(Path(cfg.static_from), matrix, None if cfg.static_cameras is None else
                                  Path(cfg.static_cameras), trainer.ds.cameras(cfg.start_frame), cfg.static_import_side)
    model = GOPModel(GOPShape(layer.capacity, 2, 1, 0))
    with torch.no_grad():
        for name in STATIC_TENSORS:
            getattr(model, name).copy_(getattr(layer, name))
    refined = fit_canonical(trainer, views, model.shape, STAGE_A, model, cfg.static_refine) if cfg.static_refine \
        else None
    return ImportedStatic(refined.model if refined is not None else model, layer, report, refined)
