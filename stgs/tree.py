"""Every file name and path template of a model dir and a packaged tree, in one place.

Model dir (docs/MODEL_FORMAT.md): `model.json` and one safetensors file per
GOP; `stgs synth` adds its ground truth under `gt/`, `stgs train` its state.
Packaged tree (manifests/PROFILE.md): the MPD, stats.json and cameras.json
beside it, and every segment under a folder named after a digest of the
pack's inputs (`v-<id>/`), so content under a URL never changes. The MPD's
SegmentTemplates and the packager's file names both come from the templates
here, expanded by the one DASH template expander (expand_template, at the end).
"""

import re

from stgs.errors import MPDError
from stgs.limits import MAX_TEMPLATE_NUMBER_WIDTH

# --- model dir ---
MODEL_META = "model.json"
"""Versioned scene metadata, written last."""
GROUND_TRUTH_DIR = "gt"
"""`stgs synth`'s ground-truth images and cameras inside a model dir."""
MASKS_DIR = "masks"
"""Foreground masks (what moves) under the ground truth: `gt/masks/<camera>/<frame:05d>.png`."""
STATIC_FILE = "static.safetensors"
"""The static layer of a format-2 model dir."""


TRAIN_REPORT = "train_report.json"
"""`stgs train`'s report beside model.json."""


def gop_stem(index: int) -> str:
    """GOP `index`'s name in a model dir (and in the trainer's checkpoints and reports)."""
    return f"gop_{index:04d}"


def gop_file(index: int) -> str:
    """The safetensors file of GOP `index` in a model dir."""
    return f"{gop_stem(index)}.safetensors"


# --- packaged tree: documents beside the MPD ---
MANIFEST = "manifest.mpd"
"""The MPD, written last."""
STATS = "stats.json"
"""Per-GOP, per-Representation sizes and quality (stgs pack)."""
CAMERAS = "cameras.json"
"""The scene's cameras, when the model dir has them: {"format", "version", "cameras": [Camera.to_json()]}."""
CAMERAS_FORMAT = "streamstgs-cameras"
SCENE = "scene.json"
"""What a catalogue shows of the scene: {"format", "version", "title", "description", "poster"} (stgs pack; the poster
a path relative to the MPD, or null). A tree from before it has none: its folder name is its title."""
SCENE_FORMAT = "streamstgs-scene"
PACK_STATE = ".pack-state.json"
"""The packager's record of finished tasks (for --resume); hidden, so never served."""
PACK_WORK = ".pack-work"
"""A distributed pack's prepared GOPs, handed from each GOP's prepare task to its QP tasks; removed at the end."""
PACK_LOGS = ".pack-logs"
"""A distributed pack's per-task logs (stgs.tasks); hidden, so never served."""
QUALITY_MEASURES = ("truth_psnr", "render_psnr")
"""What a stats.json rung's quality per GOP is judged by, in order: its PSNR against the capture (estimated by the
packager where it knew the model's own error), else against the uncompressed model."""


def quality_measure(entries: list[dict]) -> str:
    """The first of QUALITY_MEASURES every one of `entries` (measures by name) has; the last where none has one."""
    return next((m for m in QUALITY_MEASURES if all(m in e for e in entries)), QUALITY_MEASURES[-1])


def rung_quality(representations: dict, rep_ids: list[str]) -> list[float]:
    """Per rung of `rep_ids`, a stats.json GOP's quality (`representations`: its entry per Representation), judged
    by quality_measure (KeyError, TypeError or ValueError where it is not there)."""
    entries = [representations[r] for r in rep_ids]
    measure = quality_measure(entries)
    return [float(e[measure]) for e in entries]

# --- packaged tree: segments ---
KEYFRAME_EXTENSION = ".stgk"
"""File extension of keyframe segments."""
KEYFRAME_MIME_TYPE = "application/vnd.streamstgs.keyframe"
"""@mimeType of the keyframe AdaptationSet (container: stgs.codec.keyframe)."""
KEYFRAME_REP = "keyframes"
"""The keyframe AdaptationSet's lossless Representation (the top keyframe rung; the only one in a fixed ladder)."""
STATIC_EXTENSION = ".stgl"
"""File extension of the static-layer segment (a format-2 tree's one segment per Period)."""
STATIC_MIME_TYPE = "application/vnd.streamstgs.static"
"""@mimeType of the static-layer AdaptationSet (container: stgs.codec.static)."""
STATIC_REP = "static"
"""The static-layer AdaptationSet's one Representation."""
SEGMENT_SUFFIXES = (KEYFRAME_EXTENSION, STATIC_EXTENSION, ".mp4", ".m4s")
"""Every segment file's suffix (documents are the rest)."""


def version_dir(pack_id: str) -> str:
    """The folder every segment of one pack lives under."""
    return f"v-{pack_id}"


def keyframe_template(version: str) -> str:
    """Keyframe segments by Representation: the lossless ones under `keyframes/`, a lossy rung's under
    `keyframes-<name>/`."""
    return f"{version}/$RepresentationID$/gop_$Number%05d${KEYFRAME_EXTENSION}"


def paired_keyframe_bytes(gop: dict, keyframe_rep: str) -> int:
    """A stats.json GOP's bytes of keyframe Representation `keyframe_rep` (the lossless one's are `keyframe_bytes`,
    a lossy rung's under `keyframes`; KeyError, TypeError or ValueError where it is not there)."""
    raw = gop["keyframe_bytes"] if keyframe_rep == KEYFRAME_REP else gop["keyframes"][keyframe_rep]
    return int(raw)


def keyframe_rep_id(rung: str) -> str:
    """The keyframe Representation id of a keyframe rung (stgs.codec.quant.KEYFRAME_RUNGS)."""
    return KEYFRAME_REP if rung == "lossless" else f"{KEYFRAME_REP}-{rung}"


def static_template(version: str) -> str:
    return f"{version}/static/layer{STATIC_EXTENSION}"


def poster_path(version: str) -> str:
    """Path (relative to the MPD) of the poster: one WebP still of the scene, under the version folder (its URL
    changes whenever the model does)."""
    return f"{version}/poster.webp"


def static_path(version: str) -> str:
    """Path (relative to the MPD) of the static-layer segment."""
    return expand_template(static_template(version), STATIC_REP)


def feature_media_template(version: str) -> str:
    return f"{version}/features/$RepresentationID$/seg_$Number%05d$.m4s"


def feature_init_template(version: str) -> str:
    return f"{version}/features/$RepresentationID$/init.mp4"


def keyframe_path(version: str, k: int, rep: str = KEYFRAME_REP) -> str:
    """Path (relative to the MPD) of GOP k's keyframe segment of Representation `rep`."""
    return expand_template(keyframe_template(version), rep, k)


def feature_path(version: str, rep: str, k: int | None) -> str:
    """Path of GOP k's feature segment of Representation `rep`, or of its init segment when k is None."""
    if k is None:
        return expand_template(feature_init_template(version), rep)
    return expand_template(feature_media_template(version), rep, k)


REP_PREFIXES = {"hevc": "qp", "av1": "av1q"}
"""Feature Representation ids per codec: the prefix + the ladder point (HEVC QP, AV1 QP)."""


def rep_id(qp: int, codec: str = "hevc") -> str:
    """The feature Representation id of a ladder point of `codec`."""
    return f"{REP_PREFIXES[codec]}{qp}"


def parse_rep_id(rep: str) -> tuple[str, int] | None:
    """(codec, ladder point) a packager-made Representation id names, or None."""
    for codec, prefix in sorted(REP_PREFIXES.items(), key=lambda item: -len(item[1])):
        rest = rep[len(prefix):]
        if rep.startswith(prefix) and rest.isdigit():
            return codec, int(rest)
    return None


def packaged_rep_id(rep: str) -> tuple[str, int]:
    """parse_rep_id of an id the packager made itself (ValueError for any other)."""
    parsed = parse_rep_id(rep)
    if parsed is None:
        raise ValueError(f"{rep!r} is not a feature Representation id of this packager")
    return parsed


def qp_of(rep: str) -> int | None:
    """The ladder point (HEVC QP, AV1 QP) a Representation id names (`qp<N>`, `av1q<N>`), or None."""
    parsed = parse_rep_id(rep)
    return None if parsed is None else parsed[1]


def expand_template(template: str, representation_id: str, number: int | None = None) -> str:
    """Substitute $RepresentationID$, $Number$ / $Number%0Nd$ and $$ in a segment URL template."""
    def sub(match: re.Match) -> str:
        name, fmt = match.group(1), match.group(2)
        if name == "":
            return "$"
        if name == "RepresentationID":
            return representation_id
        if name == "Number":
            if number is None:
                raise MPDError(f"template {template!r} needs $Number$")
            if fmt:
                width = re.fullmatch(r"%0(\d+)d", fmt)
                if not width:
                    raise MPDError(f"unsupported format tag {fmt!r} in {template!r}")
                if len(width.group(1)) > 3 or int(width.group(1)) > MAX_TEMPLATE_NUMBER_WIDTH:
                    raise MPDError(f"$Number$ width {width.group(1)} in {template!r} is over the limit of "
                                   f"{MAX_TEMPLATE_NUMBER_WIDTH}")
                return f"{number:0{int(width.group(1))}d}"
            return str(number)
        raise MPDError(f"unsupported identifier ${name}$ in {template!r}")

    return re.sub(r"\$([A-Za-z]*)(%[^$]*)?\$", sub, template)
