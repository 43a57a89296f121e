"""Per-GOP StreamSTGS training on the CPU (`stgs train DATASET OUT`).

1. Load the dataset's training views, scaled; compute per-camera dynamic masks.
2. Initial points: triangulated from the calibrated views of a few frames
   spread over the trained span (stgs.train.init), topped up with jittered
   copies and random frustum points to the capacity N = S².
3. Coarse stage: canonical 3DGS (no deformation) on frames from all times.
4. Per GOP, from the coarse canonical Gaussians: canonical Gaussians +
   temporal features + deformation field, one random (frame, camera) per
   iteration, feature noise λ·U(−0.5, 0.5), losses of stgs.train.losses,
   periodic PLAS sorting (for the grid smoothness term), MCMC-style
   relocation of dead Gaussians, pruning by average opacity at the end.
5. Write a model dir (docs/MODEL_FORMAT.md) + cameras.json + train_report.json.

Checkpoints (safetensors + JSON, no pickle) under OUT/.train/ allow --resume;
a non-finite loss stops the run with the last good checkpoint kept.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from stgs.camera import Camera, resize, surrounds
from stgs.codec.attributes import OPACITY_LOGIT_RANGE
from stgs.codec.plas import PLASConfig, plas_order, sort_key
from stgs.data import Dataset, open_dataset, split
from stgs.errors import StgsError
from stgs.fsio import atomic_write_bytes
from stgs.memory import reuse_large_allocations
from stgs.metrics import psnr, ssim, ssim_map
from stgs.model.gop import GOPModel, GOPShape, frame_time
from stgs.model.store import save_gop, save_model
from stgs.model.view import splat
from stgs.train import losses
from stgs.train.aux import AuxTransformer
from stgs.train.config import TrainConfig
from stgs.train.dynamic import gop_dynamic_masks
from stgs.train.init import (
    MIN_TRIANGULATED,
    background_shell_points,
    ground_height,
    random_frustum_points,
    triangulate,
)
from stgs.tree import CAMERAS, CAMERAS_FORMAT, MODEL_META, TRAIN_REPORT, gop_file, gop_stem

STATE_DIR = ".train"
GAUSSIAN_AXIS = {"xyz": 0, "log_scale": 0, "rotation": 0, "opacity_logit": 0, "color": 0, "features": 1}
"""Which axis of each per-Gaussian parameter indexes the Gaussians."""


class DivergedError(StgsError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


@dataclass
class Views:
    """Training images of some frames (kept as uint8: a quarter of float32) and their cameras."""

    cameras: list[Camera]
    frames: list[int]
    images: torch.Tensor
    """(F, C, H, W, 3) uint8."""
    dynamic: torch.Tensor | None = None
    """(C, H, W) bool dynamic-pixel masks."""

    def target(self, f: int, c: int) -> torch.Tensor:
        return self.images[f, c].float().div_(255.0)


def scale_camera(cam: Camera, scale: float) -> Camera:
    """The camera at `scale` times its image size (the training resolution)."""
    return resize(cam, max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))


def load_views(ds: Dataset, names: list[str], frames: list[int], scale: float, progress: bool) -> Views:
    by_name = {c.name: c for c in ds.cameras(frames[0])}
    cams = [scale_camera(by_name[n], scale) for n in names]
    h, w = cams[0].height, cams[0].width
    if any((c.height, c.width) != (h, w) for c in cams):
        raise StgsError(f"{ds.name}: training cameras must share one image size")
    images = torch.empty(len(frames), len(cams), h, w, 3, dtype=torch.uint8)
    for i, f in enumerate(tqdm(frames, desc="load frames", unit="frame", disable=not progress)):
        for j, cam in enumerate(cams):
            img = ds.image(f, cam.name)
            if img.shape[:2] != (h, w):
                img = torch.from_numpy(cv2.resize(img.numpy(), (w, h), interpolation=cv2.INTER_AREA))
            images[i, j] = (img * 255 + 0.5).clamp(0, 255).to(torch.uint8)
    return Views(cams, frames, images)


@dataclass
class InitialPoints:
    """Where the Gaussians start."""

    points: torch.Tensor
    """(N, 3) positions."""
    colors: torch.Tensor
    """(N, 3) colours."""
    anchored: torch.Tensor
    """(N,) bool: seen in the images (triangulated or on the rig's walls and floor) rather than filler
    (jittered copies, random points), which starts fainter so it cannot veil the scene."""
    triangulated: int
    """How many points triangulated."""
    background: int = 0
    """How many points went on the rig's walls and floor."""


def initial_points(ds: Dataset, names: list[str], frames: list[int], count: int, gen: torch.Generator,
                   limit: int = 0, background_share: float = 0.0) -> InitialPoints:
    """`count` starting points, triangulated at each of `frames` (people who move are seeded where they are
    at each of those times); `background_share` of them on the rig's walls and floor
    (background_shell_points) when the cameras surround the scene."""
    cams, images = _training_views(ds, names, frames[0])  # the walls and floor are coloured from the first frame
    found_at = [triangulate(cams, images, [ds.mask(frames[0], c.name) for c in cams])]
    for frame in frames[1:]:  # one more frame's images held at a time
        later_cams, later_images = _training_views(ds, names, frame)
        found_at.append(triangulate(later_cams, later_images, [ds.mask(frame, c.name) for c in later_cams]))
    # A time with too few points to describe the scene there (tiny images, no texture) contributes none: a few
    # points from each of several such times would draw every seeded copy around them instead of random points.
    found_at = [(p, c) for p, c in found_at if len(p) >= MIN_TRIANGULATED]
    pts = torch.cat([p for p, _ in found_at]) if found_at else torch.empty(0, 3)
    col = torch.cat([c for _, c in found_at]) if found_at else torch.empty(0, 3)
    if limit and len(pts) > limit:
        keep = torch.randperm(len(pts), generator=gen)[:limit]
        pts, col = pts[keep], col[keep]
    if len(pts) < MIN_TRIANGULATED:  # random points instead
        pts, col = pts[:0], col[:0]
    found = len(pts)
    parts, colors, background = [], [], 0
    if background_share and surrounds(cams):
        shell, shell_col = background_shell_points(cams, images, int(count * background_share), gen,
                                                   ground_height(cams, pts))
        parts.append(shell)
        colors.append(shell_col)
        count -= len(shell)
        background = len(shell)
    if found >= count:
        keep = torch.randperm(found, generator=gen)[:count]
        pts, col = pts[keep], col[keep]
    parts.append(pts)
    colors.append(col)
    anchored = sum(len(p) for p in parts)
    extra_random = (count - len(pts)) // 2 if found else count - len(pts)
    jitter_n = count - len(pts) - extra_random
    if jitter_n:
        src = torch.randint(found, (jitter_n,), generator=gen)
        spread = (pts.std(0) * 0.02).clamp_min(1e-3)
        parts.append(pts[src] + torch.randn(jitter_n, 3, generator=gen) * spread)
        colors.append(col[src])
    if extra_random:
        parts.append(random_frustum_points(cams, extra_random, gen))
        colors.append(torch.rand(extra_random, 3, generator=gen))
    points = torch.cat(parts)
    flags = torch.arange(len(points)) < anchored
    return InitialPoints(points, torch.cat(colors), flags, found, background)


def _training_views(ds: Dataset, names: list[str], frame: int) -> tuple[list[Camera], list[torch.Tensor]]:
    cams = [c for c in ds.cameras(frame) if c.name in names]
    return cams, [ds.image(frame, c.name) for c in cams]


def init_frames(frames: list[int], count: int) -> list[int]:
    """`count` of `frames` spread evenly from the first (all of them when there are fewer)."""
    if count >= len(frames):
        return list(frames)
    if count == 1:
        return [frames[0]]
    return [frames[round(i * (len(frames) - 1) / (count - 1))] for i in range(count)]


def init_canonical(model: GOPModel, init: InitialPoints, opacity: float = 0.1, filler_opacity: float = 0.02) -> None:
    """3DGS-style initial attributes: scale from the mean distance to the 3 nearest points."""
    points = init.points
    with torch.no_grad():
        model.xyz.copy_(points)
        d = torch.cdist(points, points)
        d.fill_diagonal_(float("inf"))
        nn3 = d.topk(min(3, len(points) - 1), largest=False).values.mean(1) if len(points) > 1 else torch.ones(1)
        model.log_scale.copy_(torch.log(nn3.clamp(1e-4, 1e2))[:, None].expand(-1, 3))
        model.rotation.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]))
        start = torch.where(init.anchored, opacity, filler_opacity)
        model.opacity_logit.copy_(torch.log(start / (1 - start)))
        model.color.copy_(init.colors.clamp(0, 1))
        model.features.zero_()


def scene_extent(cams: list[Camera]) -> float:
    centres = torch.stack([c.center for c in cams])
    return float((centres - centres.mean(0)).norm(dim=1).max()) * 1.1 + 1e-6


class Optimizer:
    """Adam over named parameter groups, with per-Gaussian row surgery (permute, reset) for sorting and relocation."""

    def __init__(self, model: GOPModel, cfg: TrainConfig, extent: float, aux: AuxTransformer | None,
                 canonical_only: bool = False):
        lr = cfg.lr
        groups = [("xyz", [model.xyz], lr.position * extent), ("log_scale", [model.log_scale], lr.scale),
                  ("rotation", [model.rotation], lr.rotation), ("opacity_logit", [model.opacity_logit], lr.opacity),
                  ("color", [model.color], lr.color)]
        if not canonical_only:
            groups += [("features", [model.features], lr.features), ("field", list(model.field.parameters()), lr.field)]
            if aux is not None:
                groups.append(("aux", list(aux.parameters()), lr.aux))
        self.opt = torch.optim.Adam([{"params": p, "lr": r, "name": n} for n, p, r in groups], eps=1e-15)
        self.model, self.cfg, self.extent = model, cfg, extent

    def set_progress(self, fraction: float) -> None:
        lr = self.cfg.lr
        for g in self.opt.param_groups:
            if g["name"] == "xyz":
                g["lr"] = _log_lerp(lr.position, lr.position_final, fraction) * self.extent
            elif g["name"] == "field":
                g["lr"] = _log_lerp(lr.field, lr.field_final, fraction)

    def rows(self, name: str, index: torch.Tensor, source: torch.Tensor | None = None) -> None:
        """Reset (source None) or copy (from rows `source`) the Adam state of Gaussian rows `index`."""
        param = getattr(self.model, name)
        state = self.opt.state.get(param)
        if not state:
            return
        axis = GAUSSIAN_AXIS[name]
        for key in ("exp_avg", "exp_avg_sq"):
            t = state[key]
            if source is None:
                t.index_fill_(axis, index, 0.0)
            else:
                t.index_copy_(axis, index, t.index_select(axis, source))

    def permute(self, order: torch.Tensor) -> None:
        with torch.no_grad():
            for name, axis in GAUSSIAN_AXIS.items():
                param = getattr(self.model, name)
                param.copy_(param.index_select(axis, order))
                state = self.opt.state.get(param)
                for key in ("exp_avg", "exp_avg_sq"):
                    if state:
                        state[key].copy_(state[key].index_select(axis, order))


def _log_lerp(a: float, b: float, t: float) -> float:
    return math.exp(math.log(a) * (1 - t) + math.log(b) * t)


@dataclass
class GOPReport:
    gop: int
    seconds: float = 0.0
    iterations: int = 0
    final_loss: float = 0.0
    train_psnr: float = 0.0
    val_psnr: float | None = None
    val_ssim: float | None = None
    relocated: int = 0
    pruned: int = 0
    curve: list[dict] = field(default_factory=list)
    """(iteration, seconds, loss, validation PSNR and SSIM) samples: accuracy vs time."""


class Trainer:
    def __init__(self, dataset: Path, out: Path, cfg: TrainConfig, progress: bool = True, resume: bool = False,
                 kind: str = "auto"):
        cfg.validate()
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        reuse_large_allocations()
        self.ds = open_dataset(dataset, kind)
        self.out, self.cfg, self.progress, self.resume = Path(out), cfg, progress, resume
        self.train_names, self.val_names = split(self.ds, cfg.holdout)
        usable = self.ds.num_frames - cfg.start_frame
        self.num_gops = usable // cfg.gop_size
        if cfg.max_gops is not None:
            self.num_gops = min(self.num_gops, cfg.max_gops)
        if self.num_gops < 1:
            raise StgsError(f"{self.ds.name}: {usable} frame(s) from frame {cfg.start_frame} do not fill one "
                            f"GOP of {cfg.gop_size}")
        self.shape = GOPShape(cfg.grid_side ** 2, cfg.gop_size, cfg.window, cfg.pe_freqs)
        self.state = self.out / STATE_DIR
        if self.out.exists() and not self.out.is_dir():
            raise StgsError(f"{self.out}: exists and is not a folder")
        ours = {STATE_DIR, MODEL_META, CAMERAS, TRAIN_REPORT}
        if self.out.is_dir() and not (self.out / MODEL_META).is_file() and \
                any(p.name not in ours for p in self.out.iterdir()):
            raise StgsError(f"{self.out}: folder is not empty and not a model dir; refusing to write into it")
        if not resume and self.state.exists():
            shutil.rmtree(self.state)
        self.state.mkdir(parents=True, exist_ok=True)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        torch.manual_seed(cfg.seed)
        self.extent = scene_extent(self.ds.cameras(cfg.start_frame))

    def gop_frames(self, k: int) -> list[int]:
        start = self.cfg.start_frame + k * self.cfg.gop_size
        return list(range(start, start + self.cfg.gop_size))

    # --- checkpoints ---

    def save_checkpoint(self, name: str, model: GOPModel, opt: Optimizer, extra: dict,
                        aux: AuxTransformer | None = None, accum: torch.Tensor | None = None) -> None:
        tensors = {f"model.{k}": v.detach().contiguous() for k, v in model.state_dict().items()}
        if aux is not None:
            tensors |= {f"aux.{k}": v.detach().contiguous() for k, v in aux.state_dict().items()}
        for group in opt.opt.param_groups:
            for i, p in enumerate(group["params"]):
                for key, t in opt.opt.state.get(p, {}).items():
                    if torch.is_tensor(t):
                        tensors[f"adam.{group['name']}.{i}.{key}"] = t.detach().reshape(t.shape).contiguous()
        if accum is not None:
            tensors["accum"] = accum.contiguous()
        tensors["rng"] = self.gen.get_state()
        path = self.state / f"{name}.safetensors"
        tmp = path.with_suffix(".tmp")
        save_file(tensors, str(tmp), metadata={"state": json.dumps(extra)})
        tmp.replace(path)

    def load_checkpoint(self, name: str, model: GOPModel, opt: Optimizer,
                        aux: AuxTransformer | None = None) -> tuple[dict, torch.Tensor | None] | None:
        path = self.state / f"{name}.safetensors"
        if not (self.resume and path.is_file()):
            return None
        from safetensors import safe_open

        with safe_open(str(path), "pt") as f:
            extra = json.loads(f.metadata()["state"])
        tensors = load_file(str(path))
        model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        if aux is not None:
            aux.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("aux.")})
        for group in opt.opt.param_groups:
            for i, p in enumerate(group["params"]):
                prefix = f"adam.{group['name']}.{i}."
                state = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
                if state:
                    opt.opt.state[p] = state
        self.gen.set_state(tensors["rng"])
        return extra, tensors.get("accum")

    def _coarse_state(self, iteration: int) -> dict:
        return {"iteration": iteration, "triangulated": self.triangulated, "background": self.background_points}

    # --- stages ---

    def coarse(self, views: Views) -> GOPModel:
        """Canonical 3DGS (no deformation) on frames from all times."""
        cfg = self.cfg
        model = GOPModel(self.shape)
        opt = Optimizer(model, cfg, self.extent, None, canonical_only=True)
        resumed = self.load_checkpoint("coarse", model, opt)
        start = resumed[0]["iteration"] if resumed else 0
        if resumed:  # the counts the interrupted run found, for the report
            self.triangulated, self.background_points = resumed[0].get("triangulated"), resumed[0].get("background")
        else:
            init = initial_points(self.ds, self.train_names, init_frames(views.frames, cfg.init_frames),
                                  self.shape.capacity, self.gen, cfg.init_points, cfg.background_share)
            self.triangulated, self.background_points = init.triangulated, init.background
            init_canonical(model, init)
        bar = tqdm(range(start, cfg.coarse_iterations), desc="coarse canonical", unit="it", disable=not self.progress)
        for it in bar:
            opt.set_progress(it / max(1, cfg.coarse_iterations))
            f = int(torch.randint(len(views.frames), (1,), generator=self.gen))
            c = int(torch.randint(len(views.cameras), (1,), generator=self.gen))
            img = splat(model.canonical(), views.cameras[c])
            loss = losses.photometric(img, views.target(f, c), cfg.lambda_ssim)
            self._step(opt, loss, "coarse", it, model)
            if cfg.relocate and (it + 1) % cfg.relocate_every == 0 and it < cfg.relocate_until * cfg.coarse_iterations:
                self.relocate(model, opt, torch.sigmoid(model.opacity_logit.detach()))
            if (it + 1) % cfg.checkpoint_every == 0:
                self.save_checkpoint("coarse", model, opt, self._coarse_state(it + 1))
        if cfg.coarse_iterations:
            self.save_checkpoint("coarse", model, opt, self._coarse_state(cfg.coarse_iterations))
        return model

    def _step(self, opt: Optimizer, loss: torch.Tensor, stage: str, it: int, model: GOPModel) -> None:
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

    def train_gop(self, k: int, coarse: GOPModel, views: Views, val: Views | None) -> tuple[GOPModel, GOPReport]:
        cfg = self.cfg
        model = GOPModel(self.shape)
        model.load_state_dict(coarse.state_dict())
        with torch.no_grad():
            model.features.zero_()
            model.features.add_(torch.randn(model.features.shape, generator=self.gen) * 1e-2)
        aux = AuxTransformer(cfg.pe_freqs) if cfg.aux else None
        opt = Optimizer(model, cfg, self.extent, aux)
        report = GOPReport(k)
        accum = torch.zeros(2, self.shape.capacity)  # running sum and count of deformed opacities
        resumed = self.load_checkpoint(gop_stem(k), model, opt, aux)
        start = 0
        if resumed:
            extra, saved_accum = resumed
            start, report = extra["iteration"], GOPReport(**extra["report"])
            accum = saved_accum if saved_accum is not None else accum
        clock = time.perf_counter() - report.seconds
        bar = tqdm(range(start, cfg.iterations), desc=f"GOP {k}", unit="it", disable=not self.progress)
        loss_value = math.nan
        window = []  # losses since the last curve point: one view's loss is too noisy to show a trend
        for it in bar:
            opt.set_progress(it / cfg.iterations)
            loss, img, target, opac = self.gop_loss(model, aux, views)
            self._step(opt, loss, f"GOP {k}", it, model)
            loss_value = loss.item()
            window.append(loss_value)
            accum[0] += opac
            accum[1] += 1
            if cfg.relocate and (it + 1) % cfg.relocate_every == 0 and it < cfg.relocate_until * cfg.iterations:
                report.relocated += self.relocate(model, opt, accum[0] / accum[1].clamp_min(1))
                accum.zero_()
            if cfg.smooth_weight and (it + 1) % cfg.sort_every == 0 and it + 1 < cfg.iterations:
                self.sort(model, opt, accum)
            if (it + 1) % max(1, cfg.iterations // 10) == 0 or it + 1 == cfg.iterations:
                paused = time.perf_counter()
                seconds = paused - clock
                vp, vs = self.validate(model, val) if val is not None else (None, None)
                clock += time.perf_counter() - paused  # validation does not count as training time
                report.curve.append({"iteration": it + 1, "seconds": seconds, "loss": sum(window) / len(window),
                                     "val_psnr": vp, "val_ssim": vs})
                window.clear()
                bar.set_postfix(loss=f"{report.curve[-1]['loss']:.4f}",
                                psnr=f"{psnr(img.detach().clamp(0, 1), target):.1f}")
            if (it + 1) % cfg.checkpoint_every == 0 and it + 1 < cfg.iterations:
                report.seconds = time.perf_counter() - clock
                self.save_checkpoint(gop_stem(k), model, opt, {"iteration": it + 1,
                                                                 "report": dataclasses.asdict(report)}, aux, accum)
        report.pruned = self.prune(model, accum)
        report.seconds = time.perf_counter() - clock
        report.iterations = cfg.iterations
        report.final_loss = loss_value
        report.train_psnr = self.validate(model, views, limit=8)[0]
        if val is not None:
            report.val_psnr, report.val_ssim = self.validate(model, val)
        return model, report

    def gop_loss(self, model: GOPModel, aux: AuxTransformer | None, views: Views):
        cfg = self.cfg
        i = int(torch.randint(len(views.frames), (1,), generator=self.gen))
        c = int(torch.randint(len(views.cameras), (1,), generator=self.gen))
        cam, target = views.cameras[c], views.target(i, c)
        noise = (torch.rand(model.features.shape[1], cfg.window * 16, generator=self.gen) - 0.5) * cfg.feature_noise
        window = model.window_features(i) + noise
        t = frame_time(i, self.shape.gop_size)
        center = cam.center.float()
        h = model.field.hidden(window, t)
        g = model.apply_offsets(model.field.decode(h, model.xyz, center))
        img = splat(g, cam)
        ssim_values = ssim_map(img, target)
        loss = losses.photometric(img, target, cfg.lambda_ssim, ssim_values=ssim_values)
        if cfg.dynamic and views.dynamic is not None:
            loss = loss + cfg.dynamic_weight * losses.photometric(img, target, cfg.lambda_ssim, views.dynamic[c],
                                                                  ssim_values)
        if aux is not None:
            h_aux = aux(aux.tokens(model, i, window))  # the same noisy window the MLP sees
            g_aux = model.apply_offsets(model.field.decode(h_aux, model.xyz, center))
            img_aux = splat(g_aux, cam)
            loss = loss + cfg.aux_ssim_weight * (1 - losses.ssim(img_aux, target))
            loss = loss + cfg.distill_weight * losses.self_distillation(h, h_aux)
        if cfg.temporal_weight:
            idx = torch.randint(self.shape.capacity, (min(cfg.temporal_sample, self.shape.capacity),),
                                generator=self.gen)
            loss = loss + cfg.temporal_weight * losses.temporal_huber(model.features[:, idx], cfg.huber_delta)
        loss = loss + cfg.opacity_weight * losses.opacity_l1(g.opacities)
        if cfg.smooth_weight:
            side = self.shape.grid_side
            loss = loss + cfg.smooth_weight * (losses.grid_smoothness(model.color, side)
                                               + losses.grid_smoothness(model.log_scale, side)
                                               + losses.grid_smoothness(model.features[i], side))
        return loss, img, target, g.opacities.detach()

    @torch.no_grad()
    def relocate(self, model: GOPModel, opt: Optimizer, avg: torch.Tensor) -> int:
        """Move dead Gaussians (average opacity `avg` below dead_opacity) onto live ones sampled by opacity,
        splitting the opacity (3DGS-MCMC)."""
        dead = torch.nonzero(avg < self.cfg.dead_opacity).squeeze(1)
        alive = avg >= self.cfg.dead_opacity
        if len(dead) == 0 or not alive.any():
            return 0
        probs = torch.where(alive, avg, torch.zeros_like(avg))
        src = torch.multinomial(probs, len(dead), replacement=True, generator=self.gen)
        counts = torch.bincount(src, minlength=len(avg)).float()
        base = torch.sigmoid(model.opacity_logit)
        split = 1 - (1 - base[src]).clamp_min(1e-6) ** (1 / (counts[src] + 1))
        for name, axis in GAUSSIAN_AXIS.items():
            param = getattr(model, name)
            param.index_copy_(axis, dead, param.index_select(axis, src))
            opt.rows(name, dead, None)
            opt.rows(name, src, None)
        logit = torch.logit(split.clamp(1e-6, 1 - 1e-6)).clamp(*OPACITY_LOGIT_RANGE)
        model.opacity_logit[dead] = logit
        model.opacity_logit[src] = logit
        model.xyz[dead] += torch.randn(len(dead), 3, generator=self.gen) * model.log_scale[dead].exp() * 0.5
        return len(dead)

    @torch.no_grad()
    def sort(self, model: GOPModel, opt: Optimizer, accum: torch.Tensor) -> None:
        side = self.shape.grid_side
        order = plas_order(sort_key(model), side, PLASConfig(seed=self.cfg.seed))
        opt.permute(order)
        accum.copy_(accum[:, order])

    @torch.no_grad()
    def prune(self, model: GOPModel, accum: torch.Tensor) -> int:
        """Park the slots whose average opacity over the GOP stayed below dead_opacity.

        The stream cannot carry opacity 0 (its floor is sigmoid(-4)), so a parked slot gets the floor opacity
        and the smallest scale of the live Gaussians: a faint dot about a pixel wide that widens neither the
        opacity nor the scale range of the packed attributes.
        """
        avg = accum[0] / accum[1].clamp_min(1)
        dead = (avg < self.cfg.dead_opacity) & (accum[1] > 0)
        model.opacity_logit[dead] = OPACITY_LOGIT_RANGE[0]
        if not dead.all():
            model.log_scale[dead] = model.log_scale[~dead].amin(0)
        return int(dead.sum())

    @torch.no_grad()
    def validate(self, model: GOPModel, views: Views, limit: int = 6) -> tuple[float, float]:
        """Mean PSNR and SSIM of `limit` (frame, camera) pairs spread over the views."""
        from stgs.model.view import FrameRenderer

        renderer = FrameRenderer(model)
        psnrs, ssims = [], []
        pairs = [(f, c) for f in range(len(views.frames)) for c in range(len(views.cameras))]
        step = max(1, len(pairs) // limit)
        for f, c in pairs[::step][:limit]:
            image, target = renderer.render(f, views.cameras[c]).clamp(0, 1), views.target(f, c)
            psnrs.append(psnr(image, target))
            ssims.append(float(ssim(image, target)))
        return float(sum(psnrs) / len(psnrs)), float(sum(ssims) / len(ssims))

    # --- the run ---

    def run(self) -> dict:
        cfg = self.cfg
        all_frames = [f for k in range(self.num_gops) for f in self.gop_frames(k)]
        step = max(1, len(all_frames) // max(1, min(len(all_frames), 2 * cfg.gop_size)))
        self.triangulated = self.background_points = None
        coarse_views = load_views(self.ds, self.train_names, all_frames[::step], cfg.scale, self.progress)
        start = time.perf_counter()
        coarse = self.coarse(coarse_views)
        coarse_s = time.perf_counter() - start
        del coarse_views
        reports, gops = [], []
        for k in range(self.num_gops):
            done = self.state / gop_file(k)
            report_path = self.state / f"{gop_stem(k)}.report.json"
            if self.resume and done.is_file() and report_path.is_file():
                gops.append(self._load_done(done))
                reports.append(json.loads(report_path.read_text()))
                continue
            frames = self.gop_frames(k)
            views = load_views(self.ds, self.train_names, frames, cfg.scale, self.progress)
            if cfg.dynamic:
                views.dynamic = gop_dynamic_masks(views.images, cfg.dynamic_frames, cfg.dynamic_theta)
            val = (load_views(self.ds, self.val_names, frames, cfg.scale, False) if self.val_names else None)
            model, report = self.train_gop(k, coarse, views, val)
            save_gop(model, done)
            atomic_write_bytes(report_path, json.dumps(dataclasses.asdict(report)).encode())
            gops.append(model)
            reports.append(dataclasses.asdict(report))
        return self.finish(gops, reports, coarse_s)

    def _load_done(self, path: Path) -> GOPModel:
        model = GOPModel(self.shape)
        model.load_state_dict(load_file(str(path)))
        return model

    def finish(self, gops: list[GOPModel], reports: list[dict], coarse_s: float) -> dict:
        cfg = self.cfg
        extra = {"generator": "stgs.train", "dataset": self.ds.name, "start_frame": cfg.start_frame,
                 "train_cameras": self.train_names, "validation_cameras": self.val_names,
                 "config": json.loads(json.dumps(dataclasses.asdict(cfg)))}
        save_model(self.out, gops, self.ds.fps, extra)
        cams = [scale_camera(c, cfg.scale) for c in self.ds.cameras(cfg.start_frame)]
        doc = {"format": CAMERAS_FORMAT, "version": 1, "cameras": [c.to_json() for c in cams]}
        atomic_write_bytes(self.out / CAMERAS, (json.dumps(doc, indent=1) + "\n").encode())
        report = {"dataset": self.ds.name, "budget": cfg.budget, "gops": reports, "coarse_seconds": coarse_s,
                  "triangulated_points": self.triangulated,
                  "background_points": self.background_points, "capacity": self.shape.capacity,
                  "train_cameras": self.train_names, "validation_cameras": self.val_names}
        atomic_write_bytes(self.out / TRAIN_REPORT, (json.dumps(report, indent=1) + "\n").encode())
        return report


def train(dataset: Path, out: Path, cfg: TrainConfig, progress: bool = True, resume: bool = False,
          kind: str = "auto") -> dict:
    """Train a model dir at `out` from a multi-view dataset; returns the training report."""
    return Trainer(dataset, out, cfg, progress, resume, kind).run()

