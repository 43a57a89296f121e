"""The settings of one pack run (`PackConfig`): light, so that the command line reads them without the
packager's heavy stack."""

from __future__ import annotations

import os
import unicodedata
from dataclasses import asdict, dataclass, field

from stgs.codec.plas_config import PLASConfig
from stgs.codec.quant import KEYFRAME_RUNGS
from stgs.codec.video import AV1, CODECS, HEVC, LADDERS, FeatureCodec
from stgs.errors import FieldError
from stgs.limits import MAX_DESCRIPTION_CHARS, MAX_TITLE_CHARS
from stgs.packager.ladder import LadderRules


@dataclass
class PackConfig:
    """Settings of one pack run."""

    ladder: str = "auto"
    """auto: each codec's rungs are picked by measurement from its candidate points (docs/PACKAGING.md, "The auto
    ladder"); fixed: every point given is a rung."""
    qps: tuple[int, ...] | None = None
    """HEVC feature-video QPs: the rungs of a fixed ladder, the candidates of an auto one (None: the codec's
    default ladder, or its default candidates)."""
    preset: str = "medium"
    """x265 preset."""
    loop_filters: bool = True
    """Keep x265's in-loop deblocking and SAO filters (False: off, in the stream, so decoders skip them)."""
    codecs: tuple[str, ...] = ("hevc", "av1")
    """Feature-video AdaptationSets to write: 12-bit HEVC, 10-bit AV1 (what browsers decode), or both."""
    av1_qps: tuple[int, ...] | None = None
    """AV1 feature-video QPs (SVT-AV1's 1..63 scale), as `qps` is for HEVC."""
    rules: LadderRules = field(default_factory=LadderRules)
    """How the auto ladder picks its rungs."""
    keyframe_rungs: tuple[str, ...] = ("fine", "coarse")
    """Lossy keyframe rungs (stgs.codec.quant.KEYFRAME_RUNGS) an auto ladder may pair a feature rung with
    (docs/PACKAGING.md, "Keyframe rungs"); a fixed ladder pairs every rung with the lossless keyframe."""
    av1_preset: str = AV1.default_preset
    """SVT-AV1 preset (0 slowest .. 13 fastest)."""
    jobs: int = field(default_factory=lambda: os.cpu_count() or 1)
    """Encodes run in parallel."""
    plas: PLASConfig = field(default_factory=PLASConfig)
    """PLAS sort settings."""
    sort: bool = True
    """PLAS-sort the Gaussians (False: keep the model's order, for comparisons)."""
    stats_views: int = 4
    """Cameras for the rendered-view PSNR where the model dir names no held-out cameras (spread over the scene's)."""
    stats_frames: int | None = None
    """Frames per GOP for the rendered-view PSNR, spread evenly; None: every frame (docs/PACKAGING.md, "Quality per
    rung", measures what fewer cost)."""
    resume: bool = False
    """Skip (GOP, ladder point) tasks whose outputs a previous interrupted run left complete."""
    title: str | None = None
    """The scene's title in a catalogue (scene.json; None: the model dir's name)."""
    description: str = ""
    """The scene's description in a catalogue (scene.json): plain text, shown as text, never as markup."""
    poster: bool = True
    """Render a poster (a WebP still from the first scene camera, mid first GOP) for catalogues and the player."""

    def validate(self) -> None:
        if self.ladder not in LADDERS:
            raise FieldError("ladder", f"must be one of {', '.join(LADDERS)}, got {self.ladder!r}")
        self.rules.validate()
        lossy = [name for name in KEYFRAME_RUNGS if name != "lossless"]
        if len(set(self.keyframe_rungs)) != len(self.keyframe_rungs) or set(self.keyframe_rungs) - set(lossy):
            raise FieldError("keyframe_rungs", f"must list distinct rungs of {', '.join(lossy)}, "
                             f"got {self.keyframe_rungs}")
        if self.stats_views < 1:
            raise FieldError("stats_views", f"must be >= 1, got {self.stats_views}")
        if self.stats_frames is not None and self.stats_frames < 1:
            raise FieldError("stats_frames", f"must be >= 1 or None (every frame), got {self.stats_frames}")
        if not self.codecs or len(set(self.codecs)) != len(self.codecs) or set(self.codecs) - set(CODECS):
            raise FieldError("codecs", f"must list distinct codecs of {', '.join(CODECS)}, got {self.codecs}")
        for name, preset in (("qps", "preset"), ("av1_qps", "av1_preset")):
            codec = CODECS["hevc" if name == "qps" else "av1"]
            q, points = codec.quantizers, self.points(codec)
            if not points or any(p not in q for p in points) or len(set(points)) != len(points):
                raise FieldError(name, f"must list distinct values in {q.start}..{q.stop - 1}, got {points}")
            if getattr(self, preset) not in codec.presets:
                raise FieldError(preset, f"must be one of {', '.join(codec.presets)}, got {getattr(self, preset)!r}")
        if self.jobs < 1:
            raise FieldError("jobs", f"must be >= 1, got {self.jobs}")
        for name, text, cap in (("title", self.title or "", MAX_TITLE_CHARS),
                                ("description", self.description, MAX_DESCRIPTION_CHARS)):
            if len(text) > cap:
                raise FieldError(name, f"must be at most {cap} characters, got {len(text)}")
            if any(unicodedata.category(c) == "Cc" and c not in "\n\t" for c in text):
                raise FieldError(name, "must not hold control characters")
        if self.title is not None and not self.title.strip():
            raise FieldError("title", "must not be blank")

    def digest_fields(self) -> dict:
        """What determines the output bytes (not jobs or resume)."""
        return {"ladder": self.ladder, "qps": list(self.points(HEVC)), "preset": self.preset,
                "loop_filters": self.loop_filters, "codecs": list(self.codecs), "av1_qps": list(self.points(AV1)),
                "av1_preset": self.av1_preset, "rules": asdict(self.rules), "plas": asdict(self.plas),
                "sort": self.sort, "stats_views": self.stats_views, "stats_frames": self.stats_frames, "format": 2,
                **({"keyframe_rungs": list(self.lossy_keyframes())} if self.lossy_keyframes() else {})}

    def lossy_keyframes(self) -> tuple[str, ...]:
        """The lossy keyframe rungs this pack writes and measures: an auto ladder's, none for a fixed one."""
        return self.keyframe_rungs if self.ladder == "auto" else ()

    def points(self, codec: FeatureCodec) -> tuple[int, ...]:
        """The ladder points of `codec` to encode: the rungs of a fixed ladder, the candidates of an auto one."""
        given = self.qps if codec.name == "hevc" else self.av1_qps
        if given is not None:
            return tuple(given)
        return codec.candidates if self.ladder == "auto" else codec.ladder

    def encodes(self) -> list[tuple[FeatureCodec, int]]:
        """Every (codec, ladder point) to encode per GOP, HEVC first."""
        return [(CODECS[name], q) for name in CODECS if name in self.codecs for q in self.points(CODECS[name])]

    def preset_of(self, codec: FeatureCodec) -> str:
        return self.preset if codec.name == "hevc" else self.av1_preset
