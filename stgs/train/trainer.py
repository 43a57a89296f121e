"""Per-GOP StreamSTGS training on the CPU (`stgs train DATASET OUT`).

1. Open the training views through a bounded cache (stgs.train.images); their dynamic or moving-pixel masks.
2. Initial points: triangulated from the calibrated views of a few frames
   spread over the trained span (stgs.train.triangulate), topped up with jittered
   copies and random frustum points to the capacity N = S².
3. Coarse stage: canonical 3DGS (no deformation) on frames from all times (the first `coarse_low_res` share of
   its iterations at half resolution), and each training camera's colour response (stgs.train.camera_colour),
   which every later stage's images go through.
4. Per GOP, from the coarse canonical Gaussians: canonical Gaussians + temporal features + deformation field, one
   drawn (frame, camera) per iteration, feature noise λ·U(−0.5, 0.5), losses of stgs.train.losses, periodic PLAS
   sorting (for the grid smoothness term), MCMC-style relocation of dead Gaussians, pruning at the end.
5. Write a model dir (docs/MODEL_FORMAT.md) + cameras.json + train_report.json.

Layered (cfg.layers, model format 2): step 3 is stage A, which fits the static
layer on the pixels that do not move (stgs.train.layers); Gaussians the data
shows moving migrate out of it; step 4 is stage B, which fits each GOP's
smaller dynamic layer, started from the migrated Gaussians and the GOP's
triangulated points, drawn over the frozen static layer in one splat (the
layer kept per training camera: stgs.model.renderer.static_backdrops).
A still scene (cfg.layers = "still": a capture of one frame, or a static 3DGS
brought in) is stage A alone: no Gaussian migrates, no GOP trains, and the
model dir holds the static layer only.

Checkpoints (safetensors + JSON, no pickle) under OUT/.train/ allow --resume;
a non-finite loss stops the run with the last good checkpoint kept. Each stage
seeds its own generators, so GOPs are independent tasks (stgs.train.run runs
them here or on Ray and writes the model dir).

This module holds the stages; the parts: `views` (training images, read through `viewcache`), `seeding`
(initial points and attributes; geometry in `init`), `losses`, `ops`
(relocation, sorting, pruning and the Adam-state surgery they need),
`checkpoint`, `aux` (the auxiliary transformer), `camera_colour`, `dynamic` (dynamic masks),
`objective` (what a GOP-stage iteration minimises), `validation` (the report's running scores), `gop_report`
(a GOP's report), `canonical` (the coarse stage and stage A).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import time
from pathlib import Path

import torch
from tqdm import tqdm

from stgs.camera import scene_extent
from stgs.codec.attributes import OPACITY_LOGIT_RANGE
from stgs.data import open_dataset, split
from stgs.data.units import in_model_units, world_scale
from stgs.errors import FieldError, StgsError
from stgs.memory import reuse_large_allocations
from stgs.metrics import psnr
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.renderer import Backdrop, static_backdrops
from stgs.model.static import StaticLayer
from stgs.picks import spread
from stgs.train.aux import AuxTransformer
from stgs.train.base import BaseStage
from stgs.train.camera_colour import CameraColour
from stgs.train.canonical import STAGE_A, CanonicalFit, fit_canonical, imported_static_model
from stgs.train.checkpoint import Checkpoints
from stgs.train.config import TrainConfig, stage_seed
from stgs.train.gop_report import DivergedError, GOPReport
from stgs.train.hull import HullConfig
from stgs.train.images import Sample, Views, view_draws
from stgs.train.layers import Migrated, fit_view_dependent, init_dynamic, migrate, motion_scores, moving_pixels
from stgs.train.objective import GOPLoss, gop_loss
from stgs.train.ops import Optimizer, opacity_level, prune, relocate, sort, track_opacities
from stgs.train.seeding import initial_points
from stgs.train.validation import mean_scores
from stgs.tree import CAMERAS, MODEL_META, TRAIN_REPORT, gop_stem

STATE_DIR = ".train"


class Trainer:
    def __init__(self, dataset: Path, out: Path, cfg: TrainConfig, progress: bool = True, resume: bool = False,
                 kind: str = "auto"):
        cfg.validate()
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        reuse_large_allocations()
        self.ds = open_dataset(dataset, kind, fps=cfg.fps)
        self.world_scale = world_scale(self.ds.cameras(cfg.start_frame))
        """The capture's lengths × this are the model's (stgs.data.units): 1 for a rig of about Panoptic's size."""
        self.ds = in_model_units(self.ds, self.world_scale)
        self.out, self.cfg, self.progress, self.resume = Path(out), cfg, progress, resume
        self.train_names, self.val_names = split(self.ds, cfg.holdout)
        usable = self.ds.num_frames - cfg.start_frame
        self.still = cfg.layers == "still"
        """A still scene: stage A alone, the static layer and no GOP."""
        self.num_gops = 0 if self.still else usable // cfg.gop_size
        self.tail_frames = None if self.still else cfg.untrained_tail(self.ds.num_frames)
        """Frames after the last whole GOP, which no GOP holds (TrainConfig.untrained_tail)."""
        if cfg.max_gops is not None:
            self.num_gops = min(self.num_gops, cfg.max_gops)
        if usable < 1:
            raise FieldError("start_frame", f"{self.ds.name} has {self.ds.num_frames} frame(s), none from frame "
                             f"{cfg.start_frame} on")
        if usable == 1 and not self.still:
            raise FieldError("layers", f"{self.ds.name} has one frame from frame {cfg.start_frame}: a still scene, "
                             "which trains with layers = still (no GOP)")
        if self.num_gops < 1 and not self.still:
            raise StgsError(f"{self.ds.name}: {usable} frame(s) from frame {cfg.start_frame} do not fill one "
                            f"GOP of {cfg.gop_size}")
        self.shape = GOPShape(cfg.grid_side ** 2, cfg.gop_size, cfg.window, cfg.pe_freqs)
        """The GOPs' sizes (a still scene's model.json records them, for no file)."""
        self.layered = cfg.layers == "layered"
        # Stage A fits the static layer as a GOP model without time (its features are never used).
        self.static_shape = GOPShape(cfg.static_grid_side ** 2, 2, 1, 0) if self.layered or self.still else None
        self.static: StaticLayer | None = None
        self.imported: StaticLayer | None = None  # TrainConfig.static_from's layer, as read
        self.migrated: Migrated | None = None
        self.colour: CameraColour | None = None
        """The training cameras' colour responses, fitted in the base stage (TrainConfig.camera_colour)."""
        self.layer_info: dict = {}
        self.base: BaseStage | None = None
        self.state = self.out / STATE_DIR
        self.checkpoints = Checkpoints(self.state, resume)
        self.seed_stage("setup")
        self.extent = scene_extent(self.ds.cameras(cfg.start_frame))
        self.triangulated: int | None = None
        self.background_points: int | None = None

    def prepare_output(self) -> None:
        """Check the output folder (a model dir or ours to create) and, unless resuming, clear the run's state.
        Done once, by the run's driver (never by a task)."""
        if self.out.exists() and not self.out.is_dir():
            raise StgsError(f"{self.out}: exists and is not a folder")
        ours = {STATE_DIR, MODEL_META, CAMERAS, TRAIN_REPORT}
        if self.out.is_dir() and not (self.out / MODEL_META).is_file() and \
                any(p.name not in ours for p in self.out.iterdir()):
            raise StgsError(f"{self.out}: folder is not empty and not a model dir; refusing to write into it")
        if not self.resume and self.state.exists():
            shutil.rmtree(self.state)
        self.state.mkdir(parents=True, exist_ok=True)

    def seed_stage(self, stage: str) -> None:
        """Each stage (the base stage, each GOP) draws from its own generators, seeded from the run's seed and the
        stage's name: a GOP trains to the same bytes wherever and in whatever order it runs."""
        seed = stage_seed(self.cfg.seed, stage)
        self.gen = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)

    def gop_frames(self, k: int) -> list[int]:
        start = self.cfg.start_frame + k * self.cfg.gop_size
        return list(range(start, start + self.cfg.gop_size))

    # --- stages ---

    def coarse(self, views: Views, shape: GOPShape, stage: str = "coarse") -> GOPModel:
        """Canonical 3DGS (no deformation) on frames from all times; on views with moving-pixel masks, on the
        pixels that do not move only (stage A of layered training). Sets the cameras' colour responses."""
        return self.keep(fit_canonical(self, views, shape, stage))

    def keep(self, fit: CanonicalFit) -> GOPModel:
        """A canonical stage's results kept for the stages after it and the report; its model."""
        self.colour, self.triangulated, self.background_points = fit.colour, fit.triangulated, fit.background_points
        return fit.model

    def stage_a(self, views: Views) -> GOPModel:
        """The static layer (layered training): fitted on the pixels that do not move, then the Gaussians the
        data shows moving leave it for the dynamic layers."""
        cfg = self.cfg
        # a still is one moment: nothing moves, every pixel is the static layer's (a layered scene's stage A draws the
        # pixels that do not move)
        moving = None if self.still else moving_pixels(self.ds, views, cfg.dynamic_theta)
        views.set_masks(moving)
        if self.static_shape is None:
            raise ValueError("stage A trains the static layer of a layered run")
        imported = cfg.static_from is not None
        if imported:
            brought = imported_static_model(self, views)
            self.imported = brought.layer
            self.layer_info["static_import"] = brought.report
            model = self.keep(brought.refined) if brought.refined is not None else brought.model
        else:
            model = self.coarse(views, self.static_shape, STAGE_A)
        if moving is not None:
            scores, share = motion_scores(model, views, moving)
            limit = int(cfg.migrate_share * self.shape.capacity) if cfg.migrate else 0
            self.migrated = migrate(model, scores, cfg.migrate_score, limit, cfg.dead_opacity)
            self.layer_info |= {"moving_mask_source": moving.source, "migrated": len(self.migrated.index),
                                "moving_pixel_share": share}
        sh1 = self.imported.sh1 if self.imported is not None and self.imported.sh_degree and not cfg.static_refine \
            else None  # refining re-sorts the slots
        self.static = StaticLayer.from_canonical(model, sh1=sh1)
        if cfg.static_sh_degree:
            start = time.perf_counter()
            draws = view_draws(cfg.seed, "static/sh1", cfg.static_sh_iterations, *views.counts)
            self.static = fit_view_dependent(self.static, views, draws, cfg.lr.color, cfg.lambda_ssim,
                                             self.progress, self.colour)
            self.layer_info["view_dependent_seconds"] = time.perf_counter() - start
        return model

    def start_model(self, k: int, coarse: GOPModel | None) -> GOPModel:
        """GOP k's model before its training: a copy of the coarse stage (single), or the dynamic layer seeded
        from the migrated Gaussians and the GOP's triangulated points (layered)."""
        model = GOPModel(self.shape)
        if coarse is not None:
            model.load_state_dict(coarse.state_dict())
        else:
            frames = spread(self.gop_frames(k), self.cfg.init_frames)
            init = initial_points(self.ds, self.train_names, frames, self.shape.capacity, self.gen,
                                  self.cfg.init_points, 0.0, HullConfig() if self.cfg.hull_seeds else None)
            init_dynamic(model, init, self.migrated)
        return model

    def step(self, opt: Optimizer, loss: torch.Tensor, stage: str, it: int, model: GOPModel) -> None:
        """One optimiser step on `loss` (a non-finite loss stops the run: DivergedError), then the model's
        rotations normalised and its opacities clipped to the stream's range."""
        if not torch.isfinite(loss):
            raise DivergedError(f"the {stage} loss became {loss.item()} at iteration {it}; the last good "
                                f"checkpoint is in {self.state} (a resumed run continues from it; lower the "
                                "learning rates or the feature noise)")
        opt.opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.opt.step()
        with torch.no_grad():
            model.rotation.div_(model.rotation.norm(dim=1, keepdim=True).clamp_min(1e-8))
            # Train the model the stream carries: the keyframe clips the opacity logit to this range.
            model.opacity_logit.clamp_(*OPACITY_LOGIT_RANGE)

    def train_gop(self, k: int, coarse: GOPModel | None, views: Views, val: Views | None
                  ) -> tuple[GOPModel, GOPReport]:
        cfg = self.cfg
        setup = time.perf_counter()
        self.seed_stage(gop_stem(k))
        model = self.start_model(k, coarse)
        static = static_backdrops(self.static, views.cameras) if self.static is not None else None
        with torch.no_grad():
            model.features.zero_()
            model.features.add_(torch.randn(model.features.shape, generator=self.gen) * 1e-2)
        aux = AuxTransformer(cfg.pe_freqs) if cfg.aux else None
        opt = Optimizer(model, cfg, self.extent, aux)
        report = GOPReport(k)
        accum = torch.zeros(2, self.shape.capacity)  # drawn opacities: sum or peak, and count (track_opacities)
        resumed = self.checkpoints.load(gop_stem(k), model, opt, self.gen, {"aux": aux})
        start = 0
        if resumed:
            extra, saved_accum = resumed
            start, report = extra["iteration"], GOPReport(**extra["report"])
            accum = saved_accum if saved_accum is not None else accum
        low_until = round(cfg.gop_low_res * cfg.iterations)
        low = (static_backdrops(self.static, views.at(1).cameras)
               if start < low_until and self.static is not None else None)
        draws = view_draws(cfg.seed, gop_stem(k), cfg.iterations, *views.counts, low_until)
        views.plan(draws[start:])
        clock = setup - report.seconds  # the dynamic layer's seeding counts as the GOP's training time
        bar = tqdm(range(start, cfg.iterations), desc=f"GOP {k}", unit="it", disable=not self.progress)
        loss_value = math.nan
        window = []  # losses since the last curve point: one view's loss is too noisy to show a trend
        warmup = cfg.dynamic_warmup * cfg.iterations if self.layered else 0
        # A dynamic layer's Gaussian may be drawn in a few of the GOP's frames only (it fades in and out): dead is
        # when it is faint at its peak, not on average over frames it is rightly absent from (docs/TRAINING.md).
        peak = self.layered
        for it in bar:
            opt.set_progress(it / cfg.iterations)
            f, c, level = draws[it]
            if it == low_until:
                low = None  # the half-size backdrops are not drawn again
            at_static = low if level else static
            loss, img, target, opac = self.gop_loss(model, aux, views.at(level).sample(f, c), at_static,
                                                    deform=it >= warmup)
            self.step(opt, loss, f"GOP {k}", it, model)
            loss_value = loss.item()
            window.append(loss_value)
            track_opacities(accum, opac, peak)
            if cfg.relocate and (it + 1) % cfg.relocate_every == 0 and it < cfg.relocate_until * cfg.iterations:
                report.relocated += relocate(model, opt, opacity_level(accum, peak), cfg.dead_opacity, self.gen)
                accum.zero_()
            if cfg.smooth_weight and (it + 1) % cfg.sort_every == 0 and it + 1 < cfg.iterations:
                sort(model, opt, accum, cfg.seed)
            if (it + 1) % max(1, cfg.iterations // 10) == 0 or it + 1 == cfg.iterations:
                paused = time.perf_counter()
                seconds = paused - clock
                vp, vs = mean_scores(model, self.static, val) if val is not None else (None, None)
                clock += time.perf_counter() - paused  # validation does not count as training time
                report.curve.append({"iteration": it + 1, "seconds": seconds, "loss": sum(window) / len(window),
                                     "val_psnr": vp, "val_ssim": vs})
                window.clear()
                bar.set_postfix(loss=f"{report.curve[-1]['loss']:.4f}",
                                psnr=f"{psnr(img.detach().clamp(0, 1), target):.1f}")
            if (it + 1) % cfg.checkpoint_every == 0 and it + 1 < cfg.iterations:
                report.seconds = time.perf_counter() - clock
                self.checkpoints.save(gop_stem(k), model, opt, self.gen,
                                      {"iteration": it + 1, "report": dataclasses.asdict(report)}, {"aux": aux},
                                      accum)
        report.pruned = prune(model, accum, cfg.dead_opacity, peak)
        report.seconds = time.perf_counter() - clock
        report.iterations = cfg.iterations
        report.final_loss = loss_value
        report.train_psnr = mean_scores(model, self.static, views, limit=8, colour=self.colour)[0]
        if val is not None:
            report.val_psnr, report.val_ssim = mean_scores(model, self.static, val)
        return model, report

    def gop_loss(self, model: GOPModel, aux: AuxTransformer | None, view: Sample,
                 static: list[Backdrop] | None = None, deform: bool = True) -> GOPLoss:
        """One iteration's loss on the drawn `view` (stgs.train.objective), its noise from this run's generator."""
        return gop_loss(self.cfg, self.gen, model, aux, view, static, deform, self.colour)

    # --- the run ---

    def use_base(self, base: BaseStage) -> BaseStage:
        """Train GOPs from `base` (the base stage's result)."""
        self.base, self.static, self.migrated, self.colour = base, base.static, base.migrated, base.colour
        return base

    def coarse_frames(self) -> list[int]:
        """The base stage's frames: stage A's, every frame of the trained span (or TrainConfig.static_frames spread
        over it); a still scene's, start_frame alone (or static_frames spread from it to the capture's end); format
        1's coarse stage's, at most two GOPs' worth."""
        if self.still:  # one moment, start_frame's, unless static_frames asks for more of a scene that does not move
            all_frames = list(range(self.cfg.start_frame, self.ds.num_frames))
            count: int | None = self.cfg.static_frames or 1
        else:
            all_frames = [f for k in range(self.num_gops) for f in self.gop_frames(k)]
            count = self.cfg.static_frames if self.layered else 2 * self.cfg.gop_size
        step = max(1, len(all_frames) // max(1, min(len(all_frames), count or len(all_frames))))
        return all_frames[::step]
