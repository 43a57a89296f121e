"""What determines a synthetic scene: SynthConfig, its named presets and the effects it may name.

Light on purpose (no torch): the command line lists the presets and effects, and checks a config, before the
generator loads.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from stgs.errors import FieldError, StgsError

EFFECTS = ("rigid", "nonrigid", "color", "appear", "view_dependent", "static_background")
"""Every effect the generator knows."""
DEFAULT_EFFECTS = EFFECTS[:5]
"""The effects of a single-layer scene (static_background adds a static layer)."""

SCENE_TARGET = (0.0, 0.55, 0.0)


@dataclass
class SynthConfig:
    """Everything that determines a synthetic scene (one config object flows through a run)."""

    grid_side: int = 32
    """S: the scene's capacity is N = S² Gaussian slots."""
    num_gops: int = 2
    """GOPs in the scene."""
    gop_size: int = 30
    """Frames per GOP (G)."""
    window: int = 3
    """Sliding window W of temporal features."""
    fps: float = 30.0
    """Playback frame rate."""
    width: int = 160
    """Ground-truth image width."""
    height: int = 120
    """Ground-truth image height."""
    num_cameras: int = 6
    """Ground-truth cameras on a ring around the scene."""
    effects: tuple[str, ...] = DEFAULT_EFFECTS
    """Effects to simulate, of rigid, nonrigid, color, appear, view_dependent and static_background (EFFECTS); nothing
    that is not named here is animated (static_background: a layered scene)."""
    static_grid_side: int = 32
    """S_s of the static layer (the backdrop's S_s² Gaussians) when static_background is on."""
    fit_steps: int = 300
    """Adam steps of the parameter-space fit per GOP."""
    feature_smoothness: float = 0.3
    """Weight of the fit's feature roughness term (grid and time neighbours; 0: off): fewer feature bits."""
    seed: int = 0
    """Seed of the scene layout and the fit."""
    fidelity_stride: int = 5
    """Evaluate rendered fidelity on every n-th frame (all cameras)."""
    fold: bool = False
    """With static_background: fold the backdrop into every GOP (a format-1 model of the layered scene)."""
    static_from: str | None = None
    """With static_background: a 3DGS file (PLY, SPZ, glb) that is the backdrop instead of the procedural one
    (its view-independent colour: the truth has no degree-1 term; stgs.interop.static)."""
    static_transform: tuple[float, ...] | None = None
    """With static_from: the 4x4 similarity (16 numbers, row-major) from the file's frame to the scene's."""

    def gops_for_seconds(self, seconds: float) -> int:
        """GOPs of gop_size frames at fps that a capture of `seconds` needs (the last one may run past it)."""
        if not (math.isfinite(seconds) and seconds > 0):
            raise FieldError("seconds", f"must be a positive number of seconds, got {seconds}")
        return max(1, math.ceil(round(seconds * self.fps, 6) / self.gop_size))

    def validate(self) -> None:
        checks = [(self.grid_side >= 4, "grid_side must be >= 4"),
                  (self.num_gops >= 1, "num_gops must be >= 1"),
                  (self.gop_size >= 2, "gop_size must be >= 2"),
                  (1 <= self.window <= 8, "window must be in 1..8"),
                  (0 < self.fps <= 240, "fps must be in (0, 240]"),
                  (8 <= self.width <= 4096 and 8 <= self.height <= 4096,
                   "width and height must be in 8..4096"),
                  (self.num_cameras >= 1, "num_cameras must be >= 1"),
                  (self.fit_steps >= 0, "fit_steps must be >= 0"),
                  (0 <= self.feature_smoothness < 1e6, "feature_smoothness must be in [0, 1e6)"),
                  (self.fidelity_stride >= 1, "fidelity_stride must be >= 1"),
                  (self.static_grid_side >= 4, "static_grid_side must be >= 4")]
        for ok, message in checks:
            if not ok:
                raise StgsError(f"synth config: {message}")
        unknown = sorted(set(self.effects) - set(EFFECTS))
        if unknown:
            raise StgsError(f"synth config: unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")
        if self.fold and "static_background" not in self.effects:
            raise StgsError("synth config: fold needs the static_background effect (a layered scene to fold)")
        if self.static_from is not None and "static_background" not in self.effects:
            raise StgsError("synth config: static_from needs the static_background effect (it is the backdrop)")


PRESETS = {
    "small": SynthConfig(),
    "demo": SynthConfig(grid_side=64, num_gops=2, gop_size=30, width=320, height=240, fit_steps=400),
    "large": SynthConfig(grid_side=256, num_gops=2, gop_size=60, width=640, height=360,
                         num_cameras=8, fit_steps=600),
}
"""Named configs: small (tests, seconds), demo (the README's demo), large (65k Gaussians, 640x360)."""


def config_from_toml(path: Path, base: SynthConfig | None = None) -> SynthConfig:
    """A SynthConfig from a TOML file whose keys are SynthConfig field names."""
    try:
        doc = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise StgsError(f"{path}: cannot read synth config ({exc})") from exc
    names = {f.name: f for f in dataclasses.fields(SynthConfig)}
    unknown = sorted(set(doc) - set(names))
    if unknown:
        raise StgsError(f"{path}: unknown key(s) {unknown}; known: {', '.join(names)}")
    values = {}
    for key, value in doc.items():
        if key == "effects":
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise StgsError(f"{path}: 'effects' must be a list of names")
            value = tuple(value)
        elif key == "fold":
            if not isinstance(value, bool):
                raise StgsError(f"{path}: 'fold' must be true or false")
        elif not isinstance(value, (int, float)) or isinstance(value, bool):
            raise StgsError(f"{path}: '{key}' must be a number")
        values[key] = value
    return dataclasses.replace(base or SynthConfig(), **values)
