"""The Gaussians of one frame of a scene (static layer ∪ deformed dynamic layer) as Splats, from a model dir or a
packaged tree at one of its Representations, for `stgs export`.

Our deformation is view-dependent (ΔO and ΔC read the direction from the camera to each Gaussian) and a static
layer may carry a degree-1 colour; the formats hold one opacity and spherical harmonics per Gaussian. So a frame
is evaluated from one eye: opacities and, at degree 0, colours as that eye sees them. At degree 1 the colour of
each dynamic Gaussian is fitted by least squares over the directions from the scene's cameras
(stgs.interop.sh.fit_degree1), and the static layer's own degree-1 term is written as it is.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stgs.errors import MPDError, StgsError
from stgs.interop import sh as harmonics
from stgs.interop.splats import Splats, colour_to_dc, from_gaussians, from_static
from stgs.model.gop import GOPModel, frame_time
from stgs.model.static import StaticLayer
from stgs.model.store import MODEL_META, load_gop, load_static, read_meta
from stgs.mpd.model import read_mpd
from stgs.mpd.profile import FEATURE_SCHEME, KEYFRAME_SCHEME, KeyframeDescriptor, gop_count, still_static_set
from stgs.packaged import packaged_gops, packaged_static
from stgs.tree import MANIFEST, STATIC_REP


@dataclass
class SceneSource:
    """A scene whose frames can be exported."""

    name: str
    gop_size: int
    num_gops: int
    fps: float
    static: StaticLayer | None
    load_gop: Callable[[int], GOPModel]
    _last: tuple[int, GOPModel] | None = None

    @property
    def still(self) -> bool:
        """A still scene: the static layer alone, one frame."""
        return self.num_gops == 0 and self.static is not None

    @property
    def num_frames(self) -> int:
        return 1 if self.still else self.num_gops * self.gop_size

    def gop(self, k: int) -> GOPModel:
        if self._last is None or self._last[0] != k:
            self._last = (k, self.load_gop(k))
        return self._last[1]


def open_source(path: Path, rep: str | None = None) -> SceneSource:
    """A model dir, or a packaged tree (its folder or its manifest.mpd) decoded at Representation `rep` (default:
    the highest-bandwidth one, the least compressed)."""
    path = Path(path)
    if path.is_file() and path.name == MANIFEST:
        path = path.parent
    if (path / MODEL_META).is_file():
        if rep is not None:
            raise StgsError(f"{path}: a model dir has no Representations; a rung is chosen in a packaged tree")
        meta = read_meta(path)
        return SceneSource(str(path), meta.shape.gop_size, meta.num_gops, meta.fps, load_static(path, meta),
                           lambda k: load_gop(path, meta, k))
    if not (path / MANIFEST).is_file():
        raise StgsError(f"{path}: neither a model dir ({MODEL_META}) nor a packaged tree ({MANIFEST})")
    if is_still_tree(path):
        if rep not in (None, STATIC_REP):
            raise StgsError(f"{path}: a still scene has one Representation, {STATIC_REP}")
        return SceneSource(f"{path} ({STATIC_REP})", 1, 0, 1.0, packaged_static(path), no_gop)
    loaders = packaged_gops(path)
    try:
        mpd = read_mpd(path / MANIFEST)
        keyframes = mpd.adaptation_set(KEYFRAME_SCHEME)
        d = KeyframeDescriptor.parse(keyframes)
        reps = [r for a in mpd.adaptation_sets(FEATURE_SCHEME) for r in a.representations]
    except (OSError, MPDError) as exc:
        raise StgsError(f"{path}: not a packaged scene ({exc})") from None
    if rep is None:
        rep = max(reps, key=lambda r: (r.bandwidth, r.id)).id
    if rep not in loaders:
        raise StgsError(f"{path}: no Representation {rep!r} (it has {', '.join(sorted(loaders))})")
    num_gops = gop_count(mpd.duration, keyframes.segment_template.seconds)
    return SceneSource(f"{path} ({rep})", d.gop_size, num_gops, d.fps, packaged_static(path), loaders[rep])


def is_still_tree(path: Path) -> bool:
    """Whether the packaged tree at `path` is a still scene (its static-layer set alone)."""
    try:
        return still_static_set(read_mpd(path / MANIFEST)) is not None
    except (OSError, MPDError) as exc:
        raise StgsError(f"{path}: not a packaged scene ({exc})") from None


def no_gop(k: int) -> GOPModel:
    raise StgsError("a still scene has no GOP")


def parse_frames(text: str, num_frames: int) -> list[int]:
    """Frames of "N" or "A:B" (B excluded, either side may be left out), checked against the scene."""
    first, sep, last = text.partition(":")
    try:
        lo = int(first) if first.strip() else 0
        hi = (int(last) if last.strip() else num_frames) if sep else lo + 1
    except ValueError:
        raise StgsError(f"frames {text!r}: expected N or A:B") from None
    if not 0 <= lo < hi <= num_frames:
        raise StgsError(f"frames {text!r}: the scene has frames 0..{num_frames - 1}")
    return list(range(lo, hi))


@torch.no_grad()
def frame_splats(source: SceneSource, frame: int, eye: torch.Tensor, sh_degree: int = 0,
                 cameras: list[torch.Tensor] | None = None) -> Splats:
    """Frame `frame` of the scene as seen from `eye` (3,), static layer first, in canonical form
    (Splats.canonical: what every lossless format reads back); `sh_degree` 1 fits the dynamic
    colours over the centres `cameras` (at least 4, around the scene) and keeps the static layer's degree 1."""
    if sh_degree not in (0, 1):
        raise StgsError(f"sh_degree {sh_degree}: 0 or 1")
    if source.still and source.static is not None:
        return static_splats(source.static, eye, sh_degree).canonical()
    if sh_degree and (cameras is None or len(cameras) < 4):
        raise StgsError("a degree-1 export fits the view-dependent colour over the scene's cameras: it needs four "
                        "or more (cameras.json beside the scene)")
    k, i = divmod(frame, source.gop_size)
    model = source.gop(k)
    eye = eye.float()
    window, t = model.window_features(i), frame_time(i, model.shape.gop_size)
    h = model.field.hidden(window, t)
    offsets = model.field.decode(h, model.xyz, eye)
    g = model.apply_offsets(offsets)
    sh = None
    if sh_degree:
        colours, dirs = [], []
        for centre in cameras or []:
            colours.append(model.apply_offsets(model.field.decode(h, model.xyz, centre.float())).colors.numpy())
            d = g.means.numpy().astype(np.float64) - centre.double().numpy()
            dirs.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12))
        values = np.stack(colours, 1).astype(np.float64) - 0.5
        prior = np.zeros((len(g.means), 4, 3))
        prior[:, 0] = (g.colors.numpy().astype(np.float64) - 0.5) / harmonics.C0
        sh = harmonics.fit_degree1(values, np.stack(dirs, 1), prior).astype(np.float32)
    dynamic = from_gaussians(g, model.log_scale + offsets[1], sh)
    if source.static is None:
        return dynamic.canonical()
    fixed = static_splats(source.static, eye, sh_degree)
    return Splats(*(np.concatenate([getattr(fixed, f), getattr(dynamic, f)]) for f in
                    ("means", "log_scales", "quats", "opacity_logits", "sh"))).canonical()


def static_splats(static: StaticLayer, eye: torch.Tensor, sh_degree: int) -> Splats:
    """The static layer as Splats: with its degree-1 colour (`sh_degree` 1), or its colour as `eye` sees it."""
    if sh_degree:
        return from_static(static if static.sh_degree else StaticLayer.from_canonical(static, sh_degree=1))
    fixed = from_static(StaticLayer.from_canonical(static))
    if static.sh_degree:  # the view-dependent colour as the eye sees it
        fixed.sh = colour_to_dc(static.gaussians(eye.float()).colors.detach().numpy())[:, None]
    return fixed
