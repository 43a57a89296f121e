"""Training configuration: one dataclass flows through a run; named budgets set its size."""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

from stgs.errors import StgsError


@dataclass
class LearningRates:
    """Adam learning rates (3DGS / 4DGS defaults; position and MLP decay exponentially to `*_final`)."""

    position: float = 1.6e-4
    """× the scene extent."""
    position_final: float = 1.6e-6
    features: float = 2.5e-3
    opacity: float = 5e-2
    scale: float = 5e-3
    rotation: float = 1e-3
    color: float = 2.5e-3
    field: float = 1.6e-3
    field_final: float = 1.6e-4
    aux: float = 1e-3
    camera_colour: float = 1e-3
    """The training cameras' colour gains and offsets (stgs.train.camera_colour)."""

    def with_rates(self, rates: dict[str, float]) -> LearningRates:
        """These rates with `rates` set. A decaying rate (one with a `*_final`) set without its final rate keeps
        its decay: the final rate is scaled by the same factor."""
        names = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(rates) - set(names))
        if unknown:
            raise StgsError(f"unknown learning rate(s) {', '.join(unknown)}; known: {', '.join(names)}")
        values = dict(rates)
        for name, rate in rates.items():
            final = f"{name}_final"
            if final in names and final not in rates:
                values[final] = getattr(self, final) * rate / getattr(self, name)
        return dataclasses.replace(self, **values)


@dataclass
class TrainConfig:
    """Everything that determines a training run."""

    budget: str = "quick"
    """Named size this config started from (quick, cpu, paper)."""
    layers: str = "single"
    """single: every GOP holds every Gaussian (model format 1); layered: a static layer fitted once over the whole
    span (stage A) + per-GOP dynamic layers (stage B), model format 2; still: stage A alone, a still scene of the
    static layer and no GOP (a capture of one frame, or a static 3DGS brought in with static_from)."""
    grid_side: int = 24
    """S: the scene's capacity is N = S² Gaussians per GOP (layered: the dynamic layer's S_d)."""
    static_grid_side: int = 32
    """S_s of the static layer (layered)."""
    migrate: bool = True
    """Layered: static Gaussians the data shows moving seed the dynamic layers (stgs.train.layers)."""
    migrate_score: float = 0.5
    """Share of its views in which a static Gaussian lands on moving pixels above which it migrates."""
    migrate_share: float = 0.5
    """Most migrated Gaussians, as a share of the dynamic capacity (the rest start from triangulated points)."""
    static_drop_rate: float = 0.1
    """Layered: share of the static Gaussians left out of each stage-A draw at random, the rest's opacity divided
    by 1 − rate (DropGaussian; 0: off). Keeps the layer from fitting the training cameras only."""
    static_drop_until: float = 1.0
    """Layered: share of stage A's iterations that drop (the rest fit the layer as it is drawn, every Gaussian)."""
    static_sh_degree: int = 0
    """Layered: view-dependent colour of the static layer (0: none; 1: degree-1 term fitted after stage A)."""
    static_sh_iterations: int = 500
    """Layered, static_sh_degree 1: iterations of the colour + sh1 fit (geometry and opacity frozen)."""
    dynamic_warmup: float = 0.0
    """Layered: share of each GOP's iterations that fit the dynamic layer's canonical Gaussians before its
    deformation field is switched on (0: from the start; since relocation judges the layer by its peak opacity a
    warm-up no longer pays, docs/TRAINING.md)."""
    gop_size: int = 60
    """Frames per GOP (G)."""
    window: int = 3
    """Sliding window W."""
    pe_freqs: int = 4
    """Frequencies of γ(t)."""
    scale: float = 1.0
    """Image scale for training (0.5: half width and height)."""
    start_frame: int = 0
    """First dataset frame."""
    max_gops: int | None = None
    """Train at most this many GOPs (None: every whole GOP of the dataset)."""
    holdout: list[str] | None = None
    """Validation cameras (None: the dataset's convention)."""
    fps: float | None = None
    """Frame rate of a capture of image files, which do not say theirs (COLMAP layouts, nerfstudio; None: 30, or
    what transforms.json or the videos say). A Panoptic or synth capture, which says its own, refuses it."""
    coarse_iterations: int = 1000
    """Canonical 3DGS stage on frames from all times (layered: stage A, the static layer, on static pixels)."""
    coarse_low_res: float = 0.0
    """Share of the coarse stage's (stage A's) iterations drawn first at half the training resolution (a quarter
    of the pixels: cheaper iterations; docs/TRAINING.md has what they cost), before the rest at full resolution."""
    iterations: int = 600
    """Iterations per GOP."""
    gop_low_res: float = 0.0
    """Share of each GOP stage's iterations drawn first at half the training resolution (images, masks and, in a
    layered scene, the static backdrops halved), before the rest at full resolution: more iterations in the same
    time for a stage that is short of them (docs/TRAINING.md has what a step costs)."""
    feature_noise: float = 1e-3
    """λ of the feature noise λ·U(−0.5, 0.5) (simulates the video codec)."""
    lambda_ssim: float = 0.2
    """SSIM share of the photometric loss."""
    dynamic: bool = True
    """Dynamic-aware density: an extra photometric term on dynamic pixels (layered: on each frame's moving pixels,
    stgs.train.run.gop_views)."""
    dynamic_theta: float = 0.05
    """A pixel is dynamic when its luminance std over `dynamic_frames` frames exceeds this."""
    dynamic_frames: int = 30
    """The GOP's first frames, whose per-pixel std decides the dynamic mask (single layer)."""
    dynamic_weight: float = 1.0
    """Weight of the photometric term on dynamic pixels."""
    aux: bool = True
    """Transformer-guided auxiliary pass with self-distillation."""
    aux_ssim_weight: float = 0.2
    distill_weight: float = 0.005
    temporal_weight: float = 1.0
    """Huber temporal consistency of features (0: off)."""
    huber_delta: float = 0.01
    opacity_weight: float = 0.01
    smooth_weight: float = 0.01
    """Spatial smoothness of the PLAS-sorted attribute grids (0: off)."""
    sort_every: int = 1000
    """Iterations between PLAS sorts of the Gaussians (the smoothness term needs a sorted grid)."""
    relocate: bool = True
    """MCMC-style relocation of dead Gaussians to live ones (keeps the count at capacity)."""
    relocate_every: int = 100
    relocate_until: float = 0.8
    """Fraction of the iterations after which relocation stops."""
    dead_opacity: float = 0.02
    """Average opacity below which a Gaussian is dead (relocated; parked at the end). Just above the stream's
    floor sigmoid(-4) = 0.018, where training holds the faintest Gaussians (3DGS-MCMC's 0.005 is unreachable)."""
    lr: LearningRates = field(default_factory=LearningRates)
    seed: int = 0
    """Random seed: the same seed and threads give the same bytes, locally or on Ray."""
    checkpoint_every: int = 200
    """Iterations between checkpoints (what a resumed run starts from)."""
    init_points: int = 0
    """Use at most this many triangulated points (0: all)."""
    init_frames: int = 6
    """Frames, spread over the trained span, whose views are triangulated for the initial points (1: the
    first frame only; people who move are then seeded only where they start)."""
    camera_colour: bool = True
    """Learn each training camera's colour response (a per-channel gain and offset, zero-mean over the cameras) in
    the base stage, and draw every stage's images through it, so that the cameras' differing colours are not
    fitted as view-dependent geometry (stgs.train.camera_colour). Never shipped: the model keeps the colour of the
    average training camera."""
    hull_seeds: bool = True
    """Layered: seed each GOP's dynamic layer on the surface of the visual hull of the dataset's foreground masks,
    where it has them and the cameras surround the scene (stgs.train.hull), instead of filler points."""
    static_triangulation: bool = True
    """Layered: triangulate the static layer's seeds outside the foreground masks, matching along the epipolar
    lines (the walls' dots, seams and lamps; stgs.train.triangulate.BACKGROUND_MATCHING), instead of on the people, whom
    stage A does not fit."""
    background_share: float = 0.0
    """Share of the capacity first placed on the rig's walls and floor, for the background a rig that
    surrounds the action sees behind it (0: none; ignored for forward-facing rigs)."""
    threads: int | None = None
    """torch threads (None: torch's default)."""
    max_memory: int | None = None
    """Bytes of decoded views a stage holds (stgs.train.images; None: the machine's RAM / 16, at most 1 GiB).
    Only how often a view is decoded depends on it, never the model's bytes."""
    static_frames: int | None = None
    """Layered: the frames stage A draws from, spread over the trained span (None: every frame); still: from
    start_frame on (None: start_frame alone, one moment)."""
    static_from: str | None = None
    """Layered: a 3DGS file (PLY, SPZ, glb) made elsewhere that is the static layer instead of stage A's fit."""
    static_refine: int = 0
    """With static_from: iterations of stage A that fine-tune it (0: used as it is)."""
    static_transform: tuple[float, ...] | None = None
    """With static_from: the 4x4 similarity (16 numbers, row-major) from the file's frame to the cameras' (None:
    identity, or fitted from static_cameras)."""
    static_cameras: str | None = None
    """With static_from: the 3DGS cameras.json it was trained with, to fit static_transform from."""
    static_import_side: int | None = None
    """With static_from: the static layer's grid side (None: the smallest that holds the file)."""

    def untrained_tail(self, num_frames: int) -> tuple[int, int] | None:
        """First and last frame of a dataset of `num_frames` after the last whole GOP, which no GOP can hold
        (every GOP has gop_size frames); None when the GOPs cover the span, when max_gops stops them first, or when
        not one GOP fits (the trainer refuses that)."""
        usable = num_frames - self.start_frame
        whole = usable // self.gop_size
        if whole == 0 or usable % self.gop_size == 0 or (self.max_gops is not None and self.max_gops < whole):
            return None
        return self.start_frame + whole * self.gop_size, num_frames - 1

    def validate(self) -> None:
        checks = [(self.grid_side >= 2, "grid_side must be >= 2"), (self.gop_size >= 2, "gop_size must be >= 2"),
                  (1 <= self.window <= 8, "window must be in 1..8"), (0 < self.scale <= 1, "scale must be in (0, 1]"),
                  (self.coarse_iterations >= 0 and self.iterations >= 1, "iterations must be positive"),
                  (self.feature_noise >= 0, "feature_noise must be >= 0"),
                  (self.relocate_every >= 1 and self.checkpoint_every >= 1 and self.sort_every >= 1,
                   "every-N settings must be >= 1"),
                  (self.max_gops is None or self.max_gops >= 1, "max_gops must be >= 1"),
                  (0 <= self.background_share < 1, "background_share must be in [0, 1)"),
                  (self.init_frames >= 1, "init_frames must be >= 1"),
                  (self.fps is None or (math.isfinite(self.fps) and self.fps > 0), "fps must be a positive number"),
                  (self.max_memory is None or self.max_memory >= 0, "max_memory must be >= 0 bytes"),
                  (self.static_frames is None or self.static_frames >= 1, "static_frames must be >= 1"),
                  (self.layers in LAYERS, f"layers must be one of {', '.join(LAYERS)}"),
                  (self.static_grid_side >= 2, "static_grid_side must be >= 2"),
                  (0 <= self.migrate_score <= 1 and 0 <= self.migrate_share <= 1,
                   "migrate_score and migrate_share must be in [0, 1]"),
                  (0 <= self.static_drop_rate < 1, "static_drop_rate must be in [0, 1)"),
                  (0 <= self.static_drop_until <= 1, "static_drop_until must be in [0, 1]"),
                  (self.static_sh_degree in (0, 1), "static_sh_degree must be 0 or 1"),
                  (self.static_sh_iterations >= 0, "static_sh_iterations must be >= 0"),
                  (0 <= self.dynamic_warmup < 1, "dynamic_warmup must be in [0, 1)"),
                  (0 <= self.coarse_low_res < 1, "coarse_low_res must be in [0, 1)"),
                  (0 <= self.gop_low_res < 1, "gop_low_res must be in [0, 1)"),
                  (self.static_from is None or self.layers != "single", "static_from needs layers = layered or still"),
                  (self.static_refine >= 0, "static_refine must be >= 0"),
                  (self.static_transform is None or len(self.static_transform) == 16,
                   "static_transform must be 16 numbers (a 4x4 matrix)"),
                  (self.static_import_side is None or self.static_import_side >= 2,
                   "static_import_side must be >= 2")]
        checks += [(math.isfinite(rate) and rate > 0, f"lr.{name} must be a positive number, got {rate}")
                   for name, rate in dataclasses.asdict(self.lr).items()]
        for ok, message in checks:
            if not ok:
                raise StgsError(f"train config: {message}")


LAYERS = ("single", "layered", "still")
"""Training modes: model format 1, 2, or 2 without a GOP (a still scene)."""

BUDGETS = {
    "quick": TrainConfig(coarse_iterations=1000, iterations=600,
                         lr=LearningRates(position=8e-4, position_final=8e-6)),
    "cpu": TrainConfig(budget="cpu", grid_side=128, scale=1.0, coarse_iterations=1500, iterations=3000,
                       sort_every=1000, checkpoint_every=500, background_share=0.5),
    "paper": TrainConfig(budget="paper", grid_side=388, coarse_iterations=3000, iterations=12000,
                         sort_every=3000, checkpoint_every=1000, background_share=0.5),
}
"""quick: CI and smoke runs (tiny); cpu: a 60-frame Panoptic GOP at 640x360 on a CPU (its time and quality:
docs/BENCHMARKS.md, "Training on Panoptic basketball: the `cpu` budget"); paper: the paper's 12k iterations and
about 150k Gaussians, for a bigger machine."""

LAYERED: dict[str, dict[str, Any]] = {
    "quick": {"grid_side": 16, "static_grid_side": 24},
    "cpu": {"grid_side": 96, "static_grid_side": 160, "coarse_iterations": 3500, "coarse_low_res": 0.4,
            "iterations": 3700, "gop_low_res": 0.8},
    "paper": {"grid_side": 256, "static_grid_side": 448, "coarse_iterations": 5000, "iterations": 10000},
}
"""What layers = "layered" (and "still", whose stage A is the same) changes in each budget (unless set explicitly):
a smaller dynamic layer beside a static layer, and iterations moved from the per-GOP stage to stage A (which nothing
refines later); cpu: stage A's first 40 % and each GOP's first 80 % drawn at half resolution. What each costs and
buys is measured in docs/BENCHMARKS.md, "Layered scenes (model format 2) against format 1"; paper: not measured."""


def budget(name: str, **overrides: Any) -> TrainConfig:
    if name not in BUDGETS:
        raise StgsError(f"unknown budget {name!r}; choose from {', '.join(BUDGETS)}")
    layered = LAYERED[name] if overrides.get("layers") in ("layered", "still") else {}
    cfg = dataclasses.replace(BUDGETS[name], **(layered | overrides))
    cfg.validate()
    return cfg


def config_from_dict(doc: dict) -> TrainConfig:
    """The TrainConfig `dataclasses.asdict` gave (how a run's settings travel to its tasks)."""
    cfg = TrainConfig(**{**doc, "lr": LearningRates(**doc["lr"])})
    cfg.validate()
    return cfg


def stage_seed(seed: int, stage: str) -> int:
    """The seed of one stage of a run (the base stage, a GOP), independent of every other stage's."""
    return int.from_bytes(hashlib.sha256(f"{seed}/{stage}".encode()).digest()[:8], "little") >> 1
