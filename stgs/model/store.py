"""Model dir: save and load a StreamSTGS scene (format in docs/MODEL_FORMAT.md).

A model dir holds `model.json` (versioned metadata), one safetensors file per
GOP (the dynamic layer) and, in format 2, one for the scene's static layer. A
still scene is format 2 with the static layer alone and no GOP.
safetensors is a flat tensor container that is parsed, never executed; every
tensor's shape is checked against model.json before a model is built, and
capacities are capped before anything is allocated. A scene without a static
layer is written as format 1, byte for byte what earlier builds wrote.
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
from stgs.model.gop import FEATURE_DIM, HIDDEN, DeformationField, GOPModel, GOPShape, square_side
from stgs.model.static import SH_DEGREES, StaticLayer
from stgs.tree import MODEL_META, STATIC_FILE, gop_file

FORMAT = "streamstgs-model"
VERSION = 2
"""The newest format this build writes (a scene with a static layer) and reads."""
VERSIONS = (1, 2)
"""Formats this build reads: 1 (dynamic GOPs only) and 2 (plus an optional static layer)."""


class ModelFormatError(StgsError):
    """A model dir or one of its tensors does not match the format (the message names the file and field)."""


@dataclass(frozen=True)
class StaticMeta:
    """What model.json says about the static layer."""

    capacity: int
    """Gaussians N_s = S_s² of the static layer."""
    file: str
    """Its safetensors file."""
    sha256: str = ""
    sh_degree: int = 0
    """0: view-independent colour; 1: plus the linear view-dependent term (stgs.model.static)."""

    @property
    def grid_side(self) -> int:
        return square_side(self.capacity)


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
    static: StaticMeta | None = None
    """The scene's static layer (format 2), or None."""

    @property
    def version(self) -> int:
        """The format this scene needs: 2 with a static layer, else 1."""
        return 2 if self.static is not None else 1

    @property
    def num_gops(self) -> int:
        return len(self.gop_files)

    @property
    def still(self) -> bool:
        """A still scene: the static layer alone, no GOP (`shape` then describes no file)."""
        return not self.gop_files

    @property
    def num_frames(self) -> int:
        return self.num_gops * self.shape.gop_size


def save_gop(model: GOPModel | StaticLayer, path: Path, version: int = 1) -> str:
    """Write one GOP (or the static layer) atomically; returns its sha256."""
    tensors = {k: v.detach().to(torch.float32).contiguous() for k, v in model.state_dict().items()}
    # One metadata key: safetensors writes several in hash order (re-saves would differ byte-wise).
    data = save(tensors, metadata={"streamstgs": json.dumps({"format": FORMAT, "version": version})})
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def write_meta(model_dir: Path, meta: SceneMeta, hashes: list[str]) -> None:
    doc = {
        "format": FORMAT,
        "version": meta.version,
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
    if meta.static is not None:
        doc["static"] = {"file": meta.static.file, "sha256": meta.static.sha256, "capacity": meta.static.capacity,
                         "grid_side": meta.static.grid_side, "sh_degree": meta.static.sh_degree}
    atomic_write_bytes(model_dir / MODEL_META, (json.dumps(doc, indent=2) + "\n").encode())


def save_model(model_dir: Path, gops: list[GOPModel], fps: float, extra: dict | None = None,
               static: StaticLayer | None = None, shape: GOPShape | None = None) -> SceneMeta:
    """Write a whole model dir (format 2 with a static layer, else format 1); model.json is written last. A still
    scene has a static layer and no GOP: `shape` then gives the GOP sizes model.json records (the trainer's)."""
    if gops:
        shape = gops[0].shape
    elif static is None or shape is None:
        raise ValueError("save_model: a scene needs at least one GOP, or a static layer and a shape (a still)")
    if any(g.shape != shape for g in gops):
        raise ValueError("save_model: every GOP of a scene must share one shape (capacity, G, W)")
    if static is not None:
        check_static(static.capacity, static.sh_degree, "save_model")
        _check_finite(static.state_dict(), "save_model: static layer")
    model_dir = Path(model_dir)
    version = 2 if static is not None else 1
    files = [gop_file(i) for i in range(len(gops))]
    hashes = [save_gop(g, model_dir / f, version) for g, f in zip(gops, files, strict=True)]
    static_meta = None
    if static is not None:
        digest = save_gop(static, model_dir / STATIC_FILE, version)
        static_meta = StaticMeta(static.capacity, STATIC_FILE, digest, static.sh_degree)
    meta = SceneMeta(shape, float(fps), files, dict(extra or {}), static_meta)
    write_meta(model_dir, meta, hashes)
    return meta


def check_static(capacity: int, sh_degree: int, where: str) -> None:
    """A static layer must be a square PLAS grid of at most MAX_CAPACITY Gaussians with a known colour degree."""
    if not 0 < capacity <= MAX_CAPACITY or square_side(capacity) == 0:
        raise ModelFormatError(f"{where}: static.capacity must be a square S_s² in 1..{MAX_CAPACITY} "
                               f"(its images are an S_s x S_s grid), got {capacity}")
    if sh_degree not in SH_DEGREES:
        raise ModelFormatError(f"{where}: static.sh_degree must be one of {SH_DEGREES}, got {sh_degree!r}")


def _check_finite(tensors: dict[str, torch.Tensor], where: str) -> None:
    for name, t in tensors.items():
        if not torch.isfinite(t).all():
            raise ModelFormatError(f"{where}: tensor '{name}' contains NaN or Inf")


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
    version = doc.get("version")
    if version not in VERSIONS or isinstance(version, bool):
        raise StgsError(f"{path}: format version {version!r} is not supported "
                        f"(this build reads versions {', '.join(map(str, VERSIONS))})")
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
    static = _static_meta(doc, path) if version >= 2 else None
    if not isinstance(gops, list) or len(gops) > MAX_GOPS or (not gops and static is None):
        raise StgsError(f"{path}: 'gops' must be a list of at most {MAX_GOPS} GOPs, empty only beside a static "
                        "layer (a still scene)")
    files = []
    for i, entry in enumerate(gops):
        name = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(name, str) or "/" in name or "\\" in name or name.startswith("."):
            raise StgsError(f"{path}: gops[{i}].file must be a plain file name")
        files.append(name)
    extra = doc.get("extra", {})
    return SceneMeta(shape, float(fps), files, extra if isinstance(extra, dict) else {}, static)


def _static_meta(doc: dict, path: Path) -> StaticMeta | None:
    entry = doc.get("static")
    if entry is None:
        return None
    if not isinstance(entry, dict):
        raise ModelFormatError(f"{path}: 'static' must be an object or null")
    capacity = entry.get("capacity")
    if not isinstance(capacity, int) or isinstance(capacity, bool):
        raise ModelFormatError(f"{path}: static.capacity must be an integer, got {capacity!r}")
    sh_degree = entry.get("sh_degree", 0)
    check_static(capacity, sh_degree, str(path))
    name = entry.get("file")
    if not isinstance(name, str) or "/" in name or "\\" in name or name.startswith(".") or not name:
        raise ModelFormatError(f"{path}: static.file must be a plain file name")
    return StaticMeta(capacity, name, str(entry.get("sha256", "")), sh_degree)


def expected_shapes(shape: GOPShape) -> dict[str, tuple[int, ...]]:
    """Every tensor a GOP file must hold, with its shape."""
    field = DeformationField(shape.window, shape.pe_freqs)
    return {f"field.{k}": tuple(v.shape) for k, v in field.state_dict().items()} | _capacity_shapes(shape)


def _capacity_shapes(shape: GOPShape) -> dict[str, tuple[int, ...]]:
    n = shape.capacity
    return {"xyz": (n, 3), "log_scale": (n, 3), "rotation": (n, 4), "opacity_logit": (n,),
            "color": (n, 3), "features": (shape.num_features, n, FEATURE_DIM)}


def static_shapes(capacity: int, sh_degree: int = 0) -> dict[str, tuple[int, ...]]:
    """Every tensor the static layer's file must hold, with its shape."""
    return {k: tuple(v.shape) for k, v in StaticLayer(capacity, sh_degree).state_dict().items()}


def _read_checked(path: Path, want: dict[str, tuple[int, ...]], what: str) -> dict[str, torch.Tensor]:
    """A safetensors file's tensors, refused unless their names and shapes are `want` and every value is finite."""
    if not path.is_file():
        raise ModelFormatError(f"{path}: missing {what} file")
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelFormatError(f"{path}: unreadable {what} file ({exc})") from exc
    if set(tensors) != set(want):
        missing, unknown = sorted(set(want) - set(tensors)), sorted(set(tensors) - set(want))
        raise ModelFormatError(f"{path}: tensors do not match the format (missing {missing}, unknown {unknown})")
    for name, t in tensors.items():
        if tuple(t.shape) != want[name]:
            raise ModelFormatError(f"{path}: tensor '{name}' has shape {tuple(t.shape)}, "
                                   f"model.json implies {want[name]}")
    _check_finite(tensors, str(path))
    return {k: v.to(torch.float32) for k, v in tensors.items()}


def load_gop(model_dir: Path, meta: SceneMeta, index: int) -> GOPModel:
    """Load GOP `index` (its dynamic layer), checking every tensor's name, shape and finiteness."""
    if not 0 <= index < meta.num_gops:
        raise StgsError(f"GOP {index} does not exist (scene has {meta.num_gops})")
    tensors = _read_checked(Path(model_dir) / meta.gop_files[index], expected_shapes(meta.shape), "GOP")
    model = GOPModel(meta.shape)
    model.load_state_dict(tensors)
    return model


def load_static(model_dir: Path, meta: SceneMeta) -> StaticLayer | None:
    """The scene's static layer, or None (format 1, or format 2 without one)."""
    if meta.static is None:
        return None
    s = meta.static
    tensors = _read_checked(Path(model_dir) / s.file, static_shapes(s.capacity, s.sh_degree), "static layer")
    layer = StaticLayer(s.capacity, s.sh_degree)
    layer.load_state_dict(tensors)
    return layer


def load_model(model_dir: Path) -> tuple[SceneMeta, list[GOPModel]]:
    """Read a whole model dir's GOPs (the static layer: load_static)."""
    meta = read_meta(model_dir)
    return meta, [load_gop(model_dir, meta, i) for i in range(meta.num_gops)]
