"""`stgs eval MODEL_DIR DATASET`: quality of a trained model on held-out cameras, uncompressed and streamed.

Per frame and per GOP: PSNR and SSIM of renders from the validation cameras
against the dataset's images (and, where the dataset has foreground masks,
PSNR inside and outside them), for the uncompressed model dir and, with
`--dash`, for every feature Representation of the packaged tree (decoded
exactly as a player decodes it; a still scene: its static layer at the capture's
frame, and the tree's as `static`). LPIPS too where its backbone's weights are
already on this machine (torchvision's cache; never downloaded). Writes
eval.json and a side-by-side grid (render | ground truth | 10x error).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from functools import partial
from pathlib import Path

import cv2
import torch

from stgs.camera import Camera
from stgs.data import open_dataset
from stgs.data.units import in_model_units
from stgs.errors import FieldError, StgsError
from stgs.fsio import atomic_write_bytes, image_grid, save_png
from stgs.metrics import LPIPS, lpips_backbone_file, mse_psnr, psnr, ssim
from stgs.model.gop import GOPModel
from stgs.model.renderer import FrameRenderer, render_still
from stgs.model.static import StaticLayer
from stgs.model.store import SceneMeta, load_gop, load_static, read_meta
from stgs.packaged import packaged_gops, packaged_static
from stgs.train.images import default_memory, open_views, scale_camera
from stgs.tree import STATIC_REP, TRAIN_REPORT

GRID_ROWS = 4


def evaluate(model_dir: Path, dataset: Path, out: Path, dash: Path | None = None, holdout: list[str] | None = None,
             stride: int = 1, progress: bool = True, lpips_net: str | None = "alex", max_memory: int | None = None
             ) -> dict:
    """Write and return eval.json's document; `lpips_net` None: no LPIPS even where its weights are present;
    `max_memory`: bytes of held-out views decoded ahead and kept for the next stream (None: the default share of
    RAM, stgs.train.images.default_memory)."""
    from tqdm import tqdm

    meta = read_meta(model_dir)
    extra = meta.extra or {}
    ds = in_model_units(open_dataset(dataset), float(extra.get("world_scale", 1.0)))  # the model's unit of length
    cams_val = holdout or extra.get("validation_cameras") or list(ds.default_holdout)
    if not cams_val:
        raise FieldError("holdout", "no validation cameras: name them (the model dir names none)")
    unknown = sorted(set(cams_val) - set(ds.camera_names))
    if unknown:
        raise StgsError(f"{ds.name}: no camera(s) {unknown}")
    start = int(extra.get("start_frame", 0))
    scale = float((extra.get("config") or {}).get("scale", 1.0))
    # a still scene is scored as one GOP of one frame (its static layer, uncompressed and as the tree's player draws it)
    g, gops = (1, 1) if meta.still else (meta.shape.gop_size, meta.num_gops)
    if start + gops * g > ds.num_frames:
        raise StgsError(f"{ds.name} has {ds.num_frames} frames; the model needs {start + gops * g}")
    static = load_static(model_dir, meta)
    sources, drawers = still_drawers(static, dash) if meta.still else gop_drawers(model_dir, meta, static, dash)
    lpips = LPIPS.load(lpips_net) if lpips_net else None
    result: dict = {"model_dir": str(model_dir), "dataset": ds.name, "validation_cameras": cams_val,
                    "frame_stride": stride, "lpips": lpips_info(lpips, lpips_net), "format": meta.version,
                    "gaussians": {"static": static.capacity if static is not None else 0,
                                  "dynamic": 0 if meta.still else meta.shape.capacity}, "streams": {}}
    grid_rows: list[torch.Tensor] = []
    # View-major: every stream draws a view in turn, so each view's truth is decoded once and a packaged stream is
    # also scored against the uncompressed model's render of the same view (`render_psnr`, as stgs pack measures).
    frames = [start + k * g + i for k in range(gops) for i in range(0, g, stride)]
    _, held_out = open_views(ds, [], frames, scale, default_memory() if max_memory is None else max_memory, cams_val)
    assert held_out is not None  # open_views gives the holdout's views when asked for them
    truths = held_out
    truths.plan([(p, c, 0) for p in range(len(frames)) for c in range(len(cams_val))])
    per_gop: dict[str, list[dict]] = {name: [] for name in sources}
    streamed = [name for name in sources if name != "uncompressed"]
    try:
        views = iter(range(len(frames)))
        for k in tqdm(range(gops), desc="eval", unit="gop", disable=not progress):
            renderers = drawers(k)
            rows: dict[str, list[dict]] = {name: [] for name in sources}
            gop_mse: dict[str, list[float]] = {name: [] for name in streamed}
            for i in range(0, g, stride):
                f, p = start + k * g + i, next(views)
                by_name = {c.name: c for c in ds.cameras(f)}
                for c, cam_name in enumerate(cams_val):
                    cam, truth = scale_camera(by_name[cam_name], scale), truths.target(p, c)
                    reference = torch.empty(0)  # the uncompressed render, drawn first
                    for name, render in renderers.items():
                        image = render(i, cam).clamp(0, 1)
                        row = {"frame": f, "camera": cam_name, "psnr": _finite(psnr(image, truth)),
                               "ssim": float(ssim(image, truth))} | region_psnr(image, truth, ds.mask(f, cam_name))
                        if lpips is not None:
                            row["lpips"] = lpips(image, truth)
                        if name == "uncompressed":
                            reference = image
                            if len(grid_rows) < 3 * GRID_ROWS and i % max(1, g // 2) == 0:
                                grid_rows += [image, truth, ((image - truth).abs() * 10).clamp(0, 1)]
                        else:
                            gop_mse[name].append((image.double() - reference.double()).square().mean().item())
                        rows[name].append(row)
            for name in sources:
                scored = {"gop": k} | _means(rows[name])
                if name in gop_mse:
                    scored["render_psnr"] = mse_psnr(gop_mse[name])
                per_gop[name].append(scored | {"frames": rows[name]})
        for name in sources:
            result["streams"][name] = _means(per_gop[name]) | {"gops": per_gop[name]}
            if name in streamed:
                result["streams"][name]["render_psnr"] = _mean(g["render_psnr"] for g in per_gop[name])
    finally:
        truths.close()
    report = Path(model_dir) / TRAIN_REPORT
    if report.is_file() and not meta.still:
        result["train_seconds_per_gop"] = [gop.get("seconds") for gop in json.loads(report.read_text())["gops"]]
    out = Path(out)
    atomic_write_bytes(out / "eval.json", (json.dumps(result, indent=1) + "\n").encode())
    if grid_rows:
        save_png(out / "eval_grid.png", image_grid(grid_rows, 3))
    return result


Drawer = Callable[[int, Camera], torch.Tensor]
"""Frame i of the GOP it was made for, from a camera."""


def gop_drawers(model_dir: Path, meta: SceneMeta, static: StaticLayer | None, dash: Path | None
                ) -> tuple[list[str], Callable[[int], dict[str, Drawer]]]:
    """The streams (the uncompressed model and, with `dash`, every Representation of its tree) and GOP k -> a drawer
    per stream."""
    sources: dict[str, Callable[[int], GOPModel]] = {"uncompressed": lambda k: load_gop(model_dir, meta, k)}
    statics = dict.fromkeys(sources, static)
    if dash is not None:
        packaged = packaged_gops(Path(dash))
        sources |= packaged
        statics |= dict.fromkeys(packaged, packaged_static(Path(dash)))  # the tree's, as a player draws it
    return list(sources), lambda k: {name: FrameRenderer(load(k), static=statics[name]).render
                                     for name, load in sources.items()}


def still_drawers(static: StaticLayer | None, dash: Path | None
                  ) -> tuple[list[str], Callable[[int], dict[str, Drawer]]]:
    """A still scene's streams and drawers (one GOP of one frame): its static layer and, with `dash`, the tree's (as a
    player decodes it)."""
    layers = {"uncompressed": static} | ({STATIC_REP: packaged_static(Path(dash))} if dash is not None else {})
    checked = {name: layer for name, layer in layers.items() if layer is not None}
    if len(checked) != len(layers):
        raise StgsError("a still scene needs its static layer, in the model dir and the tree")
    drawers: dict[str, Drawer] = {name: partial(still_frame, layer) for name, layer in checked.items()}
    return list(drawers), lambda k: drawers


def still_frame(layer: StaticLayer, frame: int, camera: Camera) -> torch.Tensor:
    return render_still(layer, camera)


def scaled_view(ds, camera: Camera, frame: int, scale: float) -> tuple[Camera, torch.Tensor]:
    """`camera` (the dataset's, at `frame`) scaled as the model was trained (`scale`), and its image at that size."""
    cam = scale_camera(camera, scale)
    truth = ds.image(frame, camera.name)
    if truth.shape[:2] != (cam.height, cam.width):
        truth = torch.from_numpy(cv2.resize(truth.numpy(), (cam.width, cam.height), interpolation=cv2.INTER_AREA))
    return cam, truth


REGIONS = ("psnr_foreground", "psnr_background")
"""PSNR inside and outside the dataset's foreground masks (where it has masks): where the error lives."""

OPTIONAL = (*REGIONS, "lpips")
"""Per-view values some evaluations lack; averaged over the views that have them."""


def lpips_info(lpips: LPIPS | None, net: str | None) -> dict | None:
    """eval.json's `lpips`: which network was used, or why no LPIPS was computed (None: not asked for)."""
    if net is None:
        return None
    if lpips is None:
        return {"net": net, "computed": False, "reason": f"no local backbone weights at {lpips_backbone_file(net)} "
                "(stgs never downloads them)"}
    return {"net": net, "computed": True, "version": "0.1", "backbone": str(lpips.backbone)}


def region_psnr(image: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor | None) -> dict:
    """{psnr_foreground, psnr_background} of one view (None for a region the mask leaves empty); {} without a mask."""
    if mask is None:
        return {}
    if mask.shape != image.shape[:2]:
        mask = torch.from_numpy(cv2.resize(mask.numpy().astype("uint8"), (image.shape[1], image.shape[0]),
                                           interpolation=cv2.INTER_NEAREST) > 0)
    values = (psnr(image, truth, mask=mask), psnr(image, truth, mask=~mask))
    return {key: (_finite(v) if not math.isnan(v) else None) for key, v in zip(REGIONS, values, strict=True)}


def _means(rows: list[dict]) -> dict:
    """Mean PSNR and SSIM of views (or GOPs), and of the OPTIONAL values over those that have them."""
    means = {"psnr": _mean(r["psnr"] for r in rows), "ssim": _mean(r["ssim"] for r in rows)}
    for key in OPTIONAL:
        values = [r[key] for r in rows if r.get(key) is not None]
        if values:
            means[key] = _mean(values)
    return means


def _finite(value: float) -> float:
    return value if math.isfinite(value) else 99.0


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values) if values else math.nan
