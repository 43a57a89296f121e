"""A training run as tasks (`stgs train`, locally or with `--ray`): the base stage once, then one task per GOP,
then the model dir, written by the driver exactly as a local run writes it.

Every task reads the dataset and the run's state folder (`OUT/.train/`) and writes its result there atomically:
the base stage's file (stgs.train.base), each GOP's trained model and report. A GOP draws from generators seeded
by the run's seed and its own index (Trainer.seed_stage), so it trains to the same bytes in any process and any
order, given the same thread count: torch's CPU kernels add in an order that follows the thread count, so a Ray
run pins it (`threads`, default 1 per task) and a local run reproduces a Ray run's bytes with the same `threads`.
A task resumes from its own checkpoints, so a retried task (its worker killed) continues where it stopped, and a
run resumed after its driver died skips the GOPs whose results are already saved.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

from safetensors.torch import load_file

from stgs.fsio import atomic_write_bytes
from stgs.memory import process_peak_rss_mb
from stgs.model.gop import GOPModel
from stgs.model.store import save_gop, save_model
from stgs.tasks import Task, open_runner
from stgs.train.base import BASE_FILE, BaseStage
from stgs.train.config import TrainConfig, config_from_dict
from stgs.train.dynamic import gop_dynamic_masks
from stgs.train.images import Views, default_memory, open_views, scale_camera
from stgs.train.layers import moving_pixels
from stgs.train.trainer import Trainer
from stgs.train.validation import still_scores
from stgs.tree import CAMERAS, CAMERAS_FORMAT, TRAIN_REPORT, gop_file, gop_stem

LOG_DIR = "logs"
"""Per-task logs under the run's state folder."""


def report_file(k: int) -> str:
    return f"{gop_stem(k)}.report.json"


def saved_base(trainer: Trainer) -> BaseStage:
    """The base stage from the state folder, in use by `trainer`."""
    return trainer.use_base(BaseStage.load(trainer.state / BASE_FILE, trainer.shape))


def base_stage(trainer: Trainer) -> BaseStage:
    """The coarse stage (single) or stage A (layered), run once and saved in the state folder; loaded from there
    when an earlier task or run finished it."""
    path = trainer.state / BASE_FILE
    if path.is_file():
        return saved_base(trainer)
    views, val = stage_views(trainer, trainer.coarse_frames(), holdout=trainer.still)
    start = time.perf_counter()
    scores: dict[str, float | None] = {}
    try:
        if trainer.static_shape is not None:
            trainer.stage_a(views)
            base = BaseStage(static=trainer.static, migrated=trainer.migrated)
        else:
            base = BaseStage(coarse=trainer.coarse(views, trainer.shape))
        seconds = time.perf_counter() - start
        if trainer.still and trainer.static is not None:  # a still's report scores its one layer, as a GOP's does
            scores["train_psnr"] = still_scores(trainer.static, views, limit=8, colour=trainer.colour)[0]
            scores["val_psnr"], scores["val_ssim"] = (still_scores(trainer.static, val) if val is not None
                                                      else (None, None))
    finally:
        views.close()  # and val's: they share one source
    base.colour = trainer.colour
    base.info = {"seconds": seconds, "triangulated_points": trainer.triangulated,
                 "background_points": trainer.background_points, "peak_rss_mb": process_peak_rss_mb()} \
        | trainer.layer_info | scores
    if base.colour is not None:
        base.info["camera_colour"] = base.colour.summary(trainer.train_names)
    trainer.state.mkdir(parents=True, exist_ok=True)
    base.save(path)
    return trainer.use_base(base)


def gop_done(trainer: Trainer, k: int) -> bool:
    return (trainer.state / gop_file(k)).is_file() and (trainer.state / report_file(k)).is_file()


def gop_views(trainer: Trainer, k: int) -> tuple[Views, Views | None]:
    """GOP k's training views with their dynamic-pixel masks, and its validation views (None without any).
    A layered GOP's masks are each frame's moving pixels, as stage A's (the dataset's foreground masks, grown,
    where it has them), since its layer holds only what moves; format 1's one mask per camera of what varied
    over the GOP's first frames both misses pixels that move in a given frame and marks pixels that are still in it
    (docs/TRAINING.md, the loss table)."""
    cfg = trainer.cfg
    views, val = stage_views(trainer, trainer.gop_frames(k), holdout=True)
    if cfg.dynamic and trainer.layered:
        views.set_masks(moving_pixels(trainer.ds, views, cfg.dynamic_theta))
    elif cfg.dynamic:
        masks = gop_dynamic_masks(views, cfg.dynamic_frames, cfg.dynamic_theta).numpy()
        views.set_masks(lambda frame, c: masks[c])
    return views, val


def stage_views(trainer: Trainer, frames: list[int], holdout: bool = False) -> tuple[Views, Views | None]:
    """The training views of `frames` (and the validation cameras', with `holdout`) through one cache of the
    run's budget (TrainConfig.max_memory)."""
    cfg = trainer.cfg
    budget = default_memory() if cfg.max_memory is None else cfg.max_memory
    return open_views(trainer.ds, trainer.train_names, frames, cfg.scale, budget,
                      trainer.val_names if holdout else None)


def gop_stage(trainer: Trainer, k: int) -> dict:
    """Train GOP k from the saved base stage; save it and its report in the state folder."""
    base = trainer.base or saved_base(trainer)
    views, val = gop_views(trainer, k)
    try:
        model, report = trainer.train_gop(k, base.coarse, views, val)
    finally:
        views.close()
    report.peak_rss_mb = process_peak_rss_mb()
    save_gop(model, trainer.state / gop_file(k))
    atomic_write_bytes(trainer.state / report_file(k), json.dumps(dataclasses.asdict(report)).encode())
    return {"gop": k, "seconds": report.seconds, "val_psnr": report.val_psnr}


def finish(trainer: Trainer) -> dict:
    """The model dir from the saved base stage and GOPs (model.json last), its cameras and the training report."""
    cfg, state = trainer.cfg, trainer.state
    base = saved_base(trainer)
    gops = []
    for k in range(trainer.num_gops):
        model = GOPModel(trainer.shape)
        model.load_state_dict(load_file(str(state / gop_file(k))))
        gops.append(model)
    reports = [json.loads((state / report_file(k)).read_text()) for k in range(trainer.num_gops)]
    extra = {"generator": "stgs.train", "dataset": trainer.ds.name, "start_frame": cfg.start_frame,
             "train_cameras": trainer.train_names, "validation_cameras": trainer.val_names,
             "world_scale": trainer.world_scale, "config": json.loads(json.dumps(dataclasses.asdict(cfg)))}
    save_model(trainer.out, gops, trainer.ds.fps, extra, static=base.static, shape=trainer.shape)
    cams = [scale_camera(c, cfg.scale) for c in trainer.ds.cameras(cfg.start_frame)]
    doc = {"format": CAMERAS_FORMAT, "version": 1, "cameras": [c.to_json() for c in cams]}
    atomic_write_bytes(trainer.out / CAMERAS, (json.dumps(doc, indent=1) + "\n").encode())
    info = dict(base.info)
    coarse_s, colours = info.pop("seconds"), info.pop("camera_colour", None)
    peaks = [info.pop("peak_rss_mb", None), process_peak_rss_mb()] + [r.get("peak_rss_mb") for r in reports]
    report = {"dataset": trainer.ds.name, "budget": cfg.budget, "gops": reports, "coarse_seconds": coarse_s,
              "triangulated_points": info.pop("triangulated_points"),
              "background_points": info.pop("background_points"), "capacity": trainer.shape.capacity,
              "train_cameras": trainer.train_names, "validation_cameras": trainer.val_names, "layers": cfg.layers,
              "frames": trainer.ds.num_frames, "untrained_tail": trainer.tail_frames,
              "world_scale": trainer.world_scale,
              "peak_rss_mb": max((p for p in peaks if p is not None), default=None)}
    if base.static is not None:
        report |= {"static_capacity": base.static.capacity, "static_seconds": coarse_s} | info
    if trainer.still:
        report["still"] = True
    if colours is not None:
        report["camera_colour"] = colours
    atomic_write_bytes(trainer.out / TRAIN_REPORT, (json.dumps(report, indent=1) + "\n").encode())
    return report


@dataclass(frozen=True)
class TrainJob:
    """What a task needs to rebuild the run where it runs (plain data)."""

    dataset: str
    out: str
    cfg: dict
    kind: str
    progress: bool


def _trainer(job: TrainJob) -> Trainer:
    return Trainer(Path(job.dataset), Path(job.out), config_from_dict(job.cfg), job.progress, resume=True,
                   kind=job.kind)


def base_task(job: TrainJob) -> dict:
    return {"seconds": base_stage(_trainer(job)).info["seconds"]}


def gop_task(job: TrainJob, k: int) -> dict:
    """GOP k's task: a retry of an attempt that finished (its worker died before the driver took the result)
    returns what that attempt saved instead of training again over its output."""
    trainer = _trainer(job)
    if gop_done(trainer, k):
        report = json.loads((trainer.state / report_file(k)).read_text())
        return {"gop": k, "seconds": report["seconds"], "val_psnr": report["val_psnr"]}
    return gop_stage(trainer, k)


def train(dataset: Path, out: Path, cfg: TrainConfig, progress: bool = True, resume: bool = False,
          kind: str = "auto", ray: str | None = None, retries: int = 3) -> dict:
    """Train a model dir at `out` from a multi-view dataset; returns the training report. `ray`: None (this
    process) or a Ray address (stgs.tasks.open_runner), where each task gets `cfg.threads` cores (default 1)."""
    if ray is not None and cfg.threads is None:
        cfg = dataclasses.replace(cfg, threads=1)
    trainer = Trainer(Path(dataset), Path(out), cfg, progress, resume, kind)
    # A missing or wrongly sized view is found now, from the files' headers, not when its GOP's turn comes.
    span = (trainer.coarse_frames() if trainer.still else
            list(range(cfg.start_frame, cfg.start_frame + trainer.num_gops * cfg.gop_size)))
    trainer.ds.check_views(span, trainer.train_names + trainer.val_names)
    runner = open_runner(ray, retries, progress)  # before anything is written: a bad address leaves no output
    try:
        trainer.prepare_output()
        # Ray's workers report through the driver's one progress bar; a local run shows each stage's own.
        job = TrainJob(str(Path(dataset).resolve()), str(trainer.out.resolve()), dataclasses.asdict(cfg), kind,
                       progress and ray is None)
        cpus, logs = cfg.threads or 1, trainer.state / LOG_DIR
        tasks: list[Task] = []
        after: tuple[str, ...] = ()
        if not (trainer.state / BASE_FILE).is_file():
            tasks.append(Task("base", base_task, (job,), cpus=cpus, fresh_process=True))
            after = ("base",)
        tasks += [Task(gop_stem(k), gop_task, (job, k), after=after, cpus=cpus, fresh_process=True)
                  for k in range(trainer.num_gops) if not gop_done(trainer, k)]
        runner.run(tasks, logs, "train: base stage and GOPs")
    finally:
        runner.close()
    return finish(trainer)
