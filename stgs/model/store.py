"""Model dir: save and load a StreamSTGS scene (format in docs/MODEL_FORMAT.md).

A model dir holds `model.json` (versioned metadata) and one safetensors file
per GOP. safetensors is a flat tensor container that is parsed, never
executed; every tensor's shape is checked against model.json before a model is
built, and capacities are capped before anything is allocated.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save

from stgs.errors import StgsError
from stgs.fsio import atomic_write_bytes
from stgs.limits import (
    MAX_CAPACITY,
    MAX_DOC_BYTES,
    MAX_FPS,
    MAX_GOP_SIZE,
    MAX_GOPS,
    MAX_PE_FREQS,
    MAX_WINDOW,
    MIN_FPS,
)
from stgs.model.gop import FEATURE_DIM, HIDDEN, DeformationField, GOPModel, GOPShape
from stgs.tree import MODEL_META, gop_file

FORMAT = "streamstgs-model"
VERSION = 1


@dataclass
class SceneMeta:
    """What model.json says about a scene."""

    shape: GOPShape
    """Sizes shared by every GOP."""
    fps: float
    """Playback frame rate."""
    gop_files: list[str]
    """One safetensors file name per GOP, in order."""
    extra: dict = field(default_factory=dict)
    """Free-form metadata (generator, effects, ground-truth location)."""

    @property
    def num_gops(self) -> int:
        return len(self.gop_files)

    @property
    def num_frames(self) -> int:
        return self.num_gops * self.shape.gop_size


def save_gop(model: GOPModel, path: Path) -> str:
    """Write one GOP atomically; returns its sha256."""
    tensors = {k: v.detach().to(torch.float32).contiguous() for k, v in model.state_dict().items()}
    # One metadata key: safetensors writes several in hash order (re-saves would differ byte-wise).
    data = save(tensors, metadata={"streamstgs": json.dumps({"format": FORMAT, "version": VERSION})})
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def write_meta(model_dir: Path, meta: SceneMeta, hashes: list[str]) -> None:
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "capacity": meta.shape.capacity,
        "grid_side": meta.shape.grid_side,
        "gop_size": meta.shape.gop_size,
        "window": meta.shape.window,
        "pe_freqs": meta.shape.pe_freqs,
        "feature_dim": FEATURE_DIM,
        "hidden": HIDDEN,
        "fps": meta.fps,
        "gops": [{"index": i, "file": f, "sha256": h}
                 for i, (f, h) in enumerate(zip(meta.gop_files, hashes, strict=True))],
        "extra": meta.extra,
    }
    atomic_write_bytes(model_dir / MODEL_META, (json.dumps(doc, indent=2) + "\n").encode())


def save_model(model_dir: Path, gops: list[GOPModel], fps: float, extra: dict | None = None) -> SceneMeta:
    """Write a whole model dir; model.json is written last."""
    if not gops:
        raise ValueError("save_model: a scene needs at least one GOP")
    shape = gops[0].shape
    if any(g.shape != shape for g in gops):
        raise ValueError("save_model: every GOP of a scene must share one shape (capacity, G, W)")
    model_dir = Path(model_dir)
    files = [gop_file(i) for i in range(len(gops))]
    hashes = [save_gop(g, model_dir / f) for g, f in zip(gops, files, strict=True)]
    meta = SceneMeta(shape, float(fps), files, dict(extra or {}))
    write_meta(model_dir, meta, hashes)
    return meta


def _int_field(doc: dict, key: str, lo: int, hi: int) -> int:
    value = doc.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise StgsError(f"model.json: '{key}' must be an integer in {lo}..{hi}, got {value!r}")
    return value


def read_meta(model_dir: Path) -> SceneMeta:
    """Parse and validate model.json (no tensor is read)."""
    path = Path(model_dir) / MODEL_META
    if not path.is_file():
        raise StgsError(f"{model_dir}: not a model dir (no model.json)")
    if path.stat().st_size > MAX_DOC_BYTES:
        raise StgsError(f"{path}: over the {MAX_DOC_BYTES}-byte limit of a model.json")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StgsError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise StgsError(f"{path}: JSON nested too deeply") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise StgsError(f"{path}: not a {FORMAT} file")
    if doc.get("version") != VERSION:
        raise StgsError(f"{path}: format version {doc.get('version')!r} is not supported "
                        f"(this build reads version {VERSION})")
    if doc.get("feature_dim") != FEATURE_DIM or doc.get("hidden") != HIDDEN:
        raise StgsError(f"{path}: feature_dim/hidden must be {FEATURE_DIM}/{HIDDEN}")
    shape = GOPShape(capacity=_int_field(doc, "capacity", 1, MAX_CAPACITY),
                     gop_size=_int_field(doc, "gop_size", 1, MAX_GOP_SIZE),
                     window=_int_field(doc, "window", 1, MAX_WINDOW),
                     pe_freqs=_int_field(doc, "pe_freqs", 0, MAX_PE_FREQS))
    fps = doc.get("fps")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not MIN_FPS <= fps <= MAX_FPS:
        raise StgsError(f"{path}: 'fps' must be a number in {MIN_FPS:g}..{MAX_FPS:g}, got {fps!r}")
    gops = doc.get("gops")
    if not isinstance(gops, list) or not 0 < len(gops) <= MAX_GOPS:
        raise StgsError(f"{path}: 'gops' must be a non-empty list")
    files = []
    for i, entry in enumerate(gops):
        name = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(name, str) or "/" in name or "\\" in name or name.startswith("."):
            raise StgsError(f"{path}: gops[{i}].file must be a plain file name")
        files.append(name)
    extra = doc.get("extra", {})
    return SceneMeta(shape, float(fps), files, extra if isinstance(extra, dict) else {})


def expected_shapes(shape: GOPShape) -> dict[str, tuple[int, ...]]:
    """Every tensor a GOP file must hold, with its shape."""
    field = DeformationField(shape.window, shape.pe_freqs)
    return {f"field.{k}": tuple(v.shape) for k, v in field.state_dict().items()} | _capacity_shapes(shape)


def _capacity_shapes(shape: GOPShape) -> dict[str, tuple[int, ...]]:
    n = shape.capacity
    return {"xyz": (n, 3), "log_scale": (n, 3), "rotation": (n, 4), "opacity_logit": (n,),
            "color": (n, 3), "features": (shape.num_features, n, FEATURE_DIM)}


def load_gop(model_dir: Path, meta: SceneMeta, index: int) -> GOPModel:
    """Load GOP `index`, checking every tensor's name, shape and finiteness."""
    if not 0 <= index < meta.num_gops:
        raise StgsError(f"GOP {index} does not exist (scene has {meta.num_gops})")
    path = Path(model_dir) / meta.gop_files[index]
    if not path.is_file():
        raise StgsError(f"{path}: missing GOP file")
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise StgsError(f"{path}: unreadable GOP file ({exc})") from exc
    want = expected_shapes(meta.shape)
    if set(tensors) != set(want):
        missing, unknown = sorted(set(want) - set(tensors)), sorted(set(tensors) - set(want))
        raise StgsError(f"{path}: tensors do not match the format (missing {missing}, unknown {unknown})")
    for name, t in tensors.items():
        if tuple(t.shape) != want[name]:
            raise StgsError(f"{path}: tensor '{name}' has shape {tuple(t.shape)}, "
                            f"model.json implies {want[name]}")
        if not torch.isfinite(t).all():
            raise StgsError(f"{path}: tensor '{name}' contains NaN or Inf")
    model = GOPModel(meta.shape)
    model.load_state_dict({k: v.to(torch.float32) for k, v in tensors.items()})
    return model


def load_model(model_dir: Path) -> tuple[SceneMeta, list[GOPModel]]:
    """Read a whole model dir."""
    meta = read_meta(model_dir)
    return meta, [load_gop(model_dir, meta, i) for i in range(meta.num_gops)]
