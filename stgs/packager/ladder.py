"""The auto ladder: which of a codec's measured candidate rungs a pack keeps (docs/PACKAGING.md, "The auto ladder").

Each candidate is one ladder point of one codec paired with one keyframe rung, encoded for every GOP and measured: its
bytes over the scene above those of the cheapest keyframe rung (what the rungs differ by: with the lossless keyframe
alone, the feature bytes) and its quality (stgs.tree.QUALITY_MEASURES). The rungs kept are those on the upper
convex hull of (bytes, PSNR), cut at the top where the next step up gains less than `top_gain_db`, then picked from
the top down so that each rung costs at least `min_ratio` times the bytes of the rung below and adds at least
`min_gain_db` over it, the cheapest hull point being the floor. Every candidate's fate and its reason are reported,
for stats.json and `stgs pack`'s summary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

from stgs.errors import FieldError


@dataclass(frozen=True)
class LadderRules:
    """How the auto ladder picks rungs from a codec's measured candidates."""

    min_gain_db: float = 0.1
    """A rung must render at least this much better than the rung below it."""
    top_gain_db: float = 0.05
    """The ladder's top: the hull point whose next step gains less than this."""
    min_ratio: float = 1.5
    """A rung must cost at least this many times the bytes of the rung below it."""

    def validate(self) -> None:
        for name in ("min_gain_db", "top_gain_db"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise FieldError(name, f"must be a finite number >= 0, got {value}")
        if not (math.isfinite(self.min_ratio) and self.min_ratio >= 1):
            raise FieldError("min_ratio", f"must be a finite number >= 1, got {self.min_ratio}")


@dataclass(frozen=True)
class Candidate:
    """One measured ladder point of one codec, over the whole scene."""

    rep_id: str
    bytes: int
    """Bytes of every GOP: its features, and its keyframes beyond the cheapest keyframe rung's."""
    psnr: float
    """Quality (dB): against the capture where known, else against the uncompressed model."""


@dataclass(frozen=True)
class Verdict:
    """Whether a candidate is a rung, and why."""

    rep_id: str
    kept: bool
    reason: str


def upper_hull(points: list[Candidate]) -> list[Candidate]:
    """The candidates on the upper convex hull of (bytes, PSNR), in ascending bytes, with PSNR rising: a candidate
    that another beats for fewer or equal bytes, or that lies under the segment between two others, is not on it."""
    hull: list[Candidate] = []
    for c in sorted(points, key=lambda c: (c.bytes, -c.psnr)):
        if hull and c.psnr <= hull[-1].psnr:
            continue  # dominated: no more quality for at least as many bytes
        while len(hull) >= 2 and _not_above(hull[-2], hull[-1], c):
            hull.pop()
        hull.append(c)
    return hull


def _next_step(hull: list[Candidate], i: int, rules: LadderRules) -> Candidate:
    """The hull point a rung above hull[i] could be: the first that costs `min_ratio` times its bytes, else the
    last (i < len(hull) - 1)."""
    return next((c for c in hull[i + 1:] if c.bytes >= rules.min_ratio * hull[i].bytes), hull[-1])


def _not_above(a: Candidate, b: Candidate, c: Candidate) -> bool:
    """Whether b lies on or under the segment from a to c."""
    return (b.psnr - a.psnr) * (c.bytes - a.bytes) <= (c.psnr - a.psnr) * (b.bytes - a.bytes)


def choose_rungs(candidates: list[Candidate], rules: LadderRules) -> list[Verdict]:
    """A verdict for every candidate (in ascending bytes): the rungs kept and why each of the others was not.

    The top comes first: the first hull point whose next step (the next hull point at `min_ratio` times its bytes,
    else the last) gains under `top_gain_db`; the rungs below it are then
    picked downwards, each at least `min_ratio` times cheaper and `min_gain_db` worse than the rung above; the floor
    (the cheapest hull point) takes the place of the lowest rung picked when it sits too close under it."""
    if not candidates:
        return []
    hull = upper_hull(candidates)
    top = next((i for i in range(len(hull) - 1) if _next_step(hull, i, rules).psnr - hull[i].psnr < rules.top_gain_db),
               len(hull) - 1)
    verdicts = {c.rep_id: Verdict(c.rep_id, False, "under the rate-quality hull") for c in candidates}
    for c in hull[top + 1:]:
        verdicts[c.rep_id] = Verdict(c.rep_id, False, f"above the top: {c.psnr - hull[top].psnr:+.3f} dB over "
                                                      f"{hull[top].rep_id} for {c.bytes / hull[top].bytes:.2f}x "
                                                      f"its bytes (a step under {rules.top_gain_db} dB ends the "
                                                      "ladder)")
    kept = [hull[top]]
    for c in reversed(hull[:top]):
        above = kept[-1]
        ratio, gain = above.bytes / c.bytes, above.psnr - c.psnr
        if ratio < rules.min_ratio:
            verdicts[c.rep_id] = Verdict(c.rep_id, False, f"{above.rep_id} costs only {ratio:.2f}x its bytes "
                                                          f"(under {rules.min_ratio}x)")
        elif gain < rules.min_gain_db:
            verdicts[c.rep_id] = Verdict(c.rep_id, False, f"{above.rep_id} gains only {gain:+.3f} dB over it "
                                                          f"(under {rules.min_gain_db} dB)")
        else:
            kept.append(c)
    floor = hull[0]
    if kept[-1] is not floor and len(kept) > 1:
        last = kept.pop()
        verdicts[last.rep_id] = Verdict(last.rep_id, False, f"too close above the floor, {floor.rep_id}")
        kept.append(floor)
    for i, c in enumerate(kept):
        if i == 0:
            reason = "the top: the next step on the hull gains under the top rule" if top < len(hull) - 1 \
                else "the top: the best candidate"
        else:
            above = kept[i - 1]
            reason = f"{above.bytes / c.bytes:.2f}x fewer bytes than {above.rep_id}, {c.psnr - above.psnr:+.2f} dB"
            if c is floor:
                reason = f"the floor: {reason}"
        verdicts[c.rep_id] = Verdict(c.rep_id, True, reason)
    order = sorted(candidates, key=lambda c: (c.bytes, -c.psnr))
    return [verdicts[c.rep_id] for c in order]


def allocation_saving(per_gop: list[list[Candidate]], rungs: list[Candidate]) -> float:
    """What one ladder per GOP would save over the scene's ladder: the share of bytes that allocating each GOP its
    own hull point (the same mean PSNR at the fewest total bytes, over the Minkowski sum of the GOPs' hulls) saves
    at the scene rungs' mean PSNR, averaged over the rungs. `per_gop`: each GOP's candidates (bytes and PSNR of that
    GOP alone); `rungs`: the scene's chosen rungs (bytes summed and PSNR averaged over the GOPs)."""
    hulls = [upper_hull(c) for c in per_gop]
    n = len(hulls)
    steps = [((b.psnr - a.psnr) / n, b.bytes - a.bytes) for h in hulls for a, b in pairwise(h)]
    steps.sort(key=lambda s: s[0] / s[1], reverse=True)  # the steepest gain per byte first
    curve = [(sum(h[0].bytes for h in hulls), sum(h[0].psnr for h in hulls) / n)]
    for gain, cost in steps:
        curve.append((curve[-1][0] + cost, curve[-1][1] + gain))
    savings = []
    for r in rungs:
        need = next((_bytes_at(a, b, r.psnr) for a, b in pairwise(curve) if a[1] <= r.psnr <= b[1]), None)
        if need is None:
            need = curve[0][0] if r.psnr <= curve[0][1] else r.bytes
        savings.append(max(0.0, 1.0 - need / r.bytes))
    return sum(savings) / len(savings) if savings else 0.0


def _bytes_at(a: tuple[int, float], b: tuple[int, float], psnr: float) -> float:
    return a[0] if b[1] == a[1] else a[0] + (b[0] - a[0]) * (psnr - a[1]) / (b[1] - a[1])
