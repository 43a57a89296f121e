"""Procedural dynamic scene: the ground truth that synthetic model dirs are fitted to.

Four objects share the capacity: a static ground disc, a ring, a blob and a
small cluster of sparks; a few slots stay unused (opacity 0). Each named
effect animates one aspect, and an effect that is not named is not applied:

- rigid: the ring spins about the vertical axis and slides sideways;
- nonrigid: the blob's surface wobbles radially;
- color: the blob's colour cycles through hues;
- appear: the sparks fade in and out;
- view_dependent: the ring's colour depends on the viewing direction;
- static_background: a striped backdrop (a cylinder beyond the cameras) and a
  floor ring around the ground disc that never change, drawn by their own
  Gaussians (`static_capacity` of them): a layered scene's static layer.

Foreground (what a dataset's masks mark) is the ring, the blob and the sparks.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from stgs.model.gop import GOPModel
from stgs.model.static import StaticLayer
from stgs.render.project import normalize_quats
from stgs.synth.config import EFFECTS

FOREGROUND = ("ring", "blob", "sparks")
"""The objects a foreground mask covers."""
BACKDROP_RADIUS = 5.0
"""The backdrop cylinder's radius (the cameras ring the scene at 3.2)."""

OBJECT_SHARES = {"ground": 0.30, "ring": 0.25, "blob": 0.30, "sparks": 0.10}
"""Fraction of the capacity per object; the rest stays unused."""


@dataclass
class TruthFrame:
    """The true Gaussians at one instant (view-dependent colour left symbolic)."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacities: torch.Tensor
    base_colors: torch.Tensor
    view_axis: torch.Tensor
    """(N, 3) unit axis; colour += view_gain * dot(view direction, axis)."""
    view_gain: torch.Tensor
    """(N, 3) per-channel gain of the view-dependent term (0 when the effect is off)."""

    @torch.no_grad()
    def copy_into(self, target: GOPModel | StaticLayer, opacity_eps: float) -> None:
        """Set the canonical attributes (xyz, log_scale, rotation, opacity_logit, color) of a GOP model or a
        static layer to these Gaussians; opacities are clamped to [eps, 1 - eps] before the logit."""
        target.xyz.copy_(self.means)
        target.log_scale.copy_(self.log_scales)
        target.rotation.copy_(self.quats)
        target.opacity_logit.copy_(torch.logit(self.opacities.clamp(opacity_eps, 1 - opacity_eps)))
        target.color.copy_(self.base_colors)

    def select(self, keep: torch.Tensor) -> TruthFrame:
        """The Gaussians `keep` (a bool mask or indices) selects."""
        return TruthFrame(*(getattr(self, f.name)[keep] for f in dataclasses.fields(self)))

    def colors(self, camera_center: torch.Tensor) -> torch.Tensor:
        view = self.means - camera_center.to(self.means.dtype)
        view = view / view.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return self.base_colors + self.view_gain * (view * self.view_axis).sum(1, keepdim=True)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions (broadcasting)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def yaw_quat(angle: float) -> torch.Tensor:
    """Rotation by `angle` radians about world +y, as a wxyz quaternion."""
    return torch.tensor([math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0])


def hue_to_rgb(hue: torch.Tensor) -> torch.Tensor:
    """Fully saturated colours on the hue circle (hue in turns), scaled to [0.15, 0.85]."""
    k = torch.stack([hue, hue + 2 / 3, hue + 1 / 3], -1) * 2 * math.pi
    return 0.5 + 0.35 * torch.cos(k)


class ProceduralScene:
    """Ground truth of the synthetic scene for a capacity and a set of effects."""

    def __init__(self, capacity: int, effects: tuple[str, ...], seed: int = 0, static_capacity: int = 0):
        unknown = sorted(set(effects) - set(EFFECTS))
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")
        if capacity < 16:
            raise ValueError("capacity must be at least 16 Gaussians")
        if ("static_background" in effects) != (static_capacity > 0):
            raise ValueError("static_background needs static_capacity > 0 (and static_capacity needs the effect)")
        self.capacity = capacity
        self.effects = frozenset(effects)
        gen = torch.Generator().manual_seed(seed)
        self.static = _backdrop(static_capacity, gen) if static_capacity else None
        """The static layer's truth (TruthFrame) with static_background, else None."""
        self.slices: dict[str, slice] = {}
        start = 0
        for name, share in OBJECT_SHARES.items():
            count = int(capacity * share)
            self.slices[name] = slice(start, start + count)
            start += count
        self.unused = slice(start, capacity)
        self._build_rest_state(gen)

    def _build_rest_state(self, gen: torch.Generator) -> None:
        n = self.capacity
        self.rest_means = torch.zeros(n, 3)
        self.rest_log_scales = torch.full((n, 3), math.log(0.02))
        self.rest_quats = normalize_quats(torch.randn(n, 4, generator=gen))
        self.rest_opacity = torch.zeros(n)
        self.rest_colors = torch.zeros(n, 3)
        self.view_axis = torch.zeros(n, 3)
        self.view_axis[:, 0] = 1.0
        self.view_gain = torch.zeros(n, 3)

        g = self.slices["ground"]
        count = g.stop - g.start
        r = 1.6 * torch.sqrt(torch.rand(count, generator=gen))
        theta = 2 * math.pi * torch.rand(count, generator=gen)
        self.rest_means[g] = torch.stack([r * torch.cos(theta), torch.zeros(count),
                                          r * torch.sin(theta)], -1)
        self.rest_log_scales[g] = torch.log(torch.tensor([0.09, 0.004, 0.09]))
        self.rest_quats[g] = torch.tensor([1.0, 0, 0, 0])
        checker = ((torch.floor(self.rest_means[g][:, 0] * 2) + torch.floor(self.rest_means[g][:, 2] * 2)) % 2)
        self.rest_colors[g] = 0.25 + 0.35 * checker[:, None] * torch.tensor([1.0, 0.9, 0.7])
        self.rest_opacity[g] = 0.9

        g = self.slices["ring"]
        count = g.stop - g.start
        u = 2 * math.pi * torch.rand(count, generator=gen)
        v = 2 * math.pi * torch.rand(count, generator=gen)
        tube = 0.3 + 0.08 * torch.cos(v)
        self.ring_local = torch.stack([tube * torch.cos(u), 0.08 * torch.sin(v), tube * torch.sin(u)], -1)
        self.rest_means[g] = self.ring_local + torch.tensor([-0.6, 0.55, 0.0])
        self.rest_log_scales[g] = math.log(0.035)
        self.rest_colors[g] = torch.tensor([0.85, 0.45, 0.2])
        self.rest_opacity[g] = 0.85
        if "view_dependent" in self.effects:
            self.view_axis[g] = torch.tensor([0.0, 0.0, 1.0])
            self.view_gain[g] = torch.tensor([-0.25, 0.1, 0.3])

        g = self.slices["blob"]
        count = g.stop - g.start
        d = torch.randn(count, 3, generator=gen)
        self.blob_dirs = d / d.norm(dim=1, keepdim=True)
        self.rest_means[g] = 0.3 * self.blob_dirs + torch.tensor([0.6, 0.6, 0.0])
        self.rest_log_scales[g] = math.log(0.04)
        self.blob_hue = 0.55 + 0.1 * torch.rand(count, generator=gen)
        self.rest_colors[g] = hue_to_rgb(self.blob_hue)
        self.rest_opacity[g] = 0.8

        g = self.slices["sparks"]
        count = g.stop - g.start
        self.rest_means[g] = torch.tensor([0.0, 1.15, 0.35]) + 0.12 * torch.randn(count, 3, generator=gen)
        self.rest_log_scales[g] = math.log(0.025)
        self.rest_colors[g] = torch.tensor([0.95, 0.9, 0.4])
        self.rest_opacity[g] = 0.9

    def at(self, time_s: float) -> TruthFrame:
        """The true Gaussians at `time_s` seconds."""
        means = self.rest_means.clone()
        quats = self.rest_quats.clone()
        colors = self.rest_colors.clone()
        opacity = self.rest_opacity.clone()
        if "rigid" in self.effects:
            g = self.slices["ring"]
            angle = 1.2 * time_s
            c, s = math.cos(angle), math.sin(angle)
            rot = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])
            shift = torch.tensor([-0.6 + 0.25 * math.sin(0.8 * time_s), 0.55, 0.0])
            means[g] = self.ring_local @ rot.T + shift
            quats[g] = quat_mul(yaw_quat(angle).expand(g.stop - g.start, 4), quats[g])
        if "nonrigid" in self.effects:
            g = self.slices["blob"]
            d = self.blob_dirs
            wobble = 1 + 0.18 * torch.sin(3 * d[:, 1] * math.pi + 2.5 * time_s) * torch.cos(2 * d[:, 0] + 1.5 * time_s)
            means[g] = 0.3 * wobble[:, None] * d + torch.tensor([0.6, 0.6, 0.0])
        if "color" in self.effects:
            g = self.slices["blob"]
            colors[g] = hue_to_rgb(self.blob_hue + 0.15 * time_s)
        if "appear" in self.effects:
            g = self.slices["sparks"]
            level = min(1.0, max(0.0, 0.5 + 1.5 * math.sin(2 * math.pi * time_s / 2.0)))
            opacity[g] = self.rest_opacity[g] * level
        return TruthFrame(means, self.rest_log_scales.clone(), quats, opacity, colors,
                          self.view_axis, self.view_gain)


def _backdrop(count: int, gen: torch.Generator) -> TruthFrame:
    """`count` static Gaussians: 3/4 on a striped cylinder beyond the cameras, 1/4 on a floor ring around the
    ground disc (radius 1.7 to 3.0)."""
    wall = count * 3 // 4
    floor = count - wall
    theta = 2 * math.pi * torch.rand(wall, generator=gen)
    y = 2.8 * torch.rand(wall, generator=gen) - 0.2
    wall_means = torch.stack([BACKDROP_RADIUS * torch.cos(theta), y, BACKDROP_RADIUS * torch.sin(theta)], -1)
    stripes = (torch.floor(theta * 12 / math.pi) % 2)[:, None]
    bands = (torch.floor(y * 2.5) % 3)[:, None] / 2
    wall_colors = 0.2 + 0.5 * stripes * torch.tensor([0.3, 0.6, 0.9]) + 0.25 * bands * torch.tensor([0.9, 0.4, 0.2])
    spacing = math.sqrt(2 * math.pi * BACKDROP_RADIUS * 2.8 / max(1, wall))
    r = torch.sqrt(1.7 ** 2 + (3.0 ** 2 - 1.7 ** 2) * torch.rand(floor, generator=gen))
    phi = 2 * math.pi * torch.rand(floor, generator=gen)
    floor_means = torch.stack([r * torch.cos(phi), torch.full((floor,), -0.01), r * torch.sin(phi)], -1)
    floor_colors = 0.3 + 0.3 * (torch.floor(phi * 8 / math.pi) % 2)[:, None] * torch.tensor([0.4, 0.8, 0.5])
    floor_spacing = math.sqrt(math.pi * (3.0 ** 2 - 1.7 ** 2) / max(1, floor))
    n = wall + floor
    # Wall Gaussians are flat in their radial direction (a yaw turns the local x axis onto the tangent).
    yaw = math.pi / 2 - theta
    wall_quats = torch.stack([torch.cos(yaw / 2), torch.zeros(wall), torch.sin(yaw / 2), torch.zeros(wall)], -1)
    quats = torch.cat([wall_quats, torch.tensor([1.0, 0, 0, 0]).expand(floor, 4)])
    wall_scale = torch.tensor([spacing * 0.7, spacing * 0.7, 0.01])
    floor_scale = torch.tensor([floor_spacing * 0.7, 0.005, floor_spacing * 0.7])
    log_scales = torch.cat([wall_scale.log().expand(wall, 3), floor_scale.log().expand(floor, 3)])
    zeros = torch.zeros(n, 3)
    return TruthFrame(torch.cat([wall_means, floor_means]), log_scales.clone(), quats.clone(), torch.full((n,), 0.95),
                      torch.cat([wall_colors, floor_colors]).clamp(0, 1), zeros + torch.tensor([1.0, 0, 0]), zeros)


class FoldedScene:
    """A layered scene's truth with its static layer folded into every frame: the same scene for a single-layer
    (format-1) model, whose GOPs must fit the backdrop too. The backdrop follows the moving Gaussians; slots
    past them up to the next square capacity are invisible (opacity 0)."""

    def __init__(self, scene: ProceduralScene):
        if scene.static is None:
            raise ValueError("only a layered scene (static_background) can be folded")
        self.scene = scene
        used = scene.capacity + len(scene.static.means)
        side = math.isqrt(used - 1) + 1
        self.capacity = side * side
        pad = self.capacity - used
        hidden = torch.zeros(pad, 3)
        self.padding = TruthFrame(hidden, torch.full((pad, 3), math.log(0.01)),
                                  torch.tensor([1.0, 0, 0, 0]).expand(pad, 4).clone(), torch.zeros(pad), hidden,
                                  torch.tensor([0.0, 1.0, 0.0]).expand(pad, 3).clone(), hidden)

    def at(self, time_s: float) -> TruthFrame:
        """The true Gaussians at `time_s`: the moving ones, the backdrop, the invisible padding."""
        parts = [self.scene.at(time_s), self.scene.static, self.padding]
        return TruthFrame(*(torch.cat([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(TruthFrame)))
