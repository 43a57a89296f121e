"""How coarsely a keyframe segment stores its attribute images and weights: its keyframe rung (manifests/PROFILE.md,
"Keyframe rungs"). No torch here: a manifest reader needs it without decoding anything."""

from __future__ import annotations

from dataclasses import dataclass, fields

from stgs.errors import FieldError

FLOAT_FIELD_BITS = 32
"""KeyframeQuant.field for float32 deformation weights (no quantisation)."""
MAX_FIELD_BITS = 8
"""The most bits quantised deformation weights take (one byte per code)."""


@dataclass(frozen=True)
class KeyframeQuant:
    """Bits of each attribute image of a keyframe segment (at most the lossless levels of attributes.SPECS, the
    defaults) and of its
    deformation weights (FLOAT_FIELD_BITS: float32; else 2..MAX_FIELD_BITS, per-row codes). docs/PACKAGING.md,
    "Keyframe rungs", measures what each attribute tolerates."""

    position: int = 16
    scale: int = 6
    rotation: int = 7
    opacity: int = 6
    color: int = 16
    field: int = FLOAT_FIELD_BITS

    def __post_init__(self) -> None:
        for f in fields(self)[:-1]:
            bits = getattr(self, f.name)
            if not 1 <= bits <= f.default:
                raise FieldError(f.name, f"must be 1..{f.default} bits, got {bits}")
        if self.field != FLOAT_FIELD_BITS and not 2 <= self.field <= MAX_FIELD_BITS:
            raise FieldError("field", f"must be 2..{MAX_FIELD_BITS} bits or {FLOAT_FIELD_BITS} (float), "
                                      f"got {self.field}")

    @property
    def lossless(self) -> bool:
        return self == LOSSLESS

    @property
    def value(self) -> str:
        """`position=12;scale=5;...;field=8`: the manifest's and the segment's spelling."""
        return ";".join(f"{f.name}={getattr(self, f.name)}" for f in fields(self))

    @classmethod
    def parse(cls, value: str) -> KeyframeQuant:
        """The quant a `value` spells (every field named once, as integers), else FieldError."""
        items = [part.partition("=") for part in value.split(";")]
        names = [f.name for f in fields(cls)]
        got = {k: v for k, _, v in items}
        if sorted(got) != sorted(names) or len(items) != len(names):
            raise FieldError("quant", f"must name {', '.join(names)} once each, got {value!r:.80}")
        if not all(v.isdigit() and len(v) <= 2 for v in got.values()):
            raise FieldError("quant", f"bits must be integers, got {value!r:.80}")
        return cls(**{k: int(v) for k, v in got.items()})


LOSSLESS = KeyframeQuant()
"""The top keyframe rung: every attribute at its full levels, float32 weights (no `quant` key in the segment)."""

KEYFRAME_RUNGS = {
    "lossless": LOSSLESS,
    "fine": KeyframeQuant(position=12, scale=5, rotation=6, opacity=5, color=10, field=8),
    "coarse": KeyframeQuant(position=8, scale=4, rotation=4, opacity=3, color=6, field=4),
}
"""The keyframe rungs an auto ladder pairs feature rungs with, by name (the tree's Representation ids:
stgs.tree.keyframe_rep_id). Chosen from the attribute sensitivity study in docs/PACKAGING.md, "Keyframe rungs"."""
