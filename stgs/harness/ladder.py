"""What the simulator needs of a packaged scene: per GOP the keyframe size and per Representation the media
segment size and quality, plus each init segment's size (from a local folder, or stats.json at a URL)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlparse

from stgs.client.abr import UpcomingGOP
from stgs.client.fetch.download import Downloader, FetchError
from stgs.client.manifest import Presentation
from stgs.client.urlpolicy import UrlPolicy
from stgs.errors import MPDError, StgsError
from stgs.limits import MAX_INIT_BYTES, MAX_MPD_BYTES
from stgs.tree import KEYFRAME_REP, MANIFEST, STATS, paired_keyframe_bytes, rung_quality


@dataclass
class Ladder:
    pres: Presentation
    keyframe_bytes: list[int]
    """Per GOP."""
    media_bytes: dict[str, list[int]]
    """Representation id -> per GOP."""
    init_bytes: dict[str, int]
    psnr: dict[str, list[float | None]]
    """Representation id -> per GOP rendered PSNR (stats.json), None where unknown."""
    stats: dict | None
    static_bytes: int = 0
    """A layered scene's static-layer segment (fetched once per playback), 0 in format 1."""
    lossy_keyframe_bytes: dict[str, list[int]] = field(default_factory=dict)
    """Lossy keyframe Representation id -> per GOP (`keyframe_bytes` are the lossless ones')."""

    def __post_init__(self) -> None:
        # The static layer is the first transfer a player makes and its first throughput sample: a format-2
        # ladder without its size would start every rule from a 0-byte transfer.
        if (self.pres.static is not None) != (self.static_bytes > 0):
            raise ValueError(f"static_bytes {self.static_bytes}: a ladder carries its static layer's size exactly "
                             "when its presentation has one")

    @property
    def url(self) -> str:
        return self.pres.url

    def keyframe_size(self, rep: str, k: int) -> int:
        """Bytes of GOP k's segment of keyframe Representation `rep`."""
        return self.keyframe_bytes[k] if rep == KEYFRAME_REP else self.lossy_keyframe_bytes[rep][k]

    def rung_keyframe_bytes(self, i: int) -> list[int]:
        """Per GOP, the bytes of the keyframes ladder rung i plays with (its keyframe Representation's)."""
        r = self.pres.ladder[i]
        return [self.keyframe_size(r.keyframe_rep, k) for k in range(len(self.media_bytes[r.rep_id]))]

    def rung_kbps(self, i: int) -> float:
        """Mean kbit/s of ladder rung i over the GOPs: its features and the keyframes it plays with."""
        r = self.pres.ladder[i]
        return (statistics.mean(self.rung_keyframe_bytes(i)) + statistics.mean(self.media_bytes[r.rep_id])) * 8 \
            / self.pres.segment_seconds / 1e3

    def gop_info(self, k: int) -> UpcomingGOP:
        """GOP k's sizes (bits) and per-rung PSNR (None unless every rung has one), as the ABR rules see them."""
        ladder = self.pres.ladder
        psnr = [p for r in ladder if (p := self.psnr[r.rep_id][k]) is not None]
        return UpcomingGOP.paired([self.keyframe_size(r.keyframe_rep, k) * 8 for r in ladder],
                                  [self.media_bytes[r.rep_id][k] * 8 for r in ladder],
                                  psnr if len(psnr) == len(ladder) else None)


def _local_path(base: Path, url: str) -> Path:
    return base / urlparse(url).path.lstrip("/")


def load_ladder(scene: str, codec: str = "auto") -> Ladder:
    """The ladder of a packaged scene folder (sizes from the files) or MPD URL (sizes from stats.json), for the
    feature set a player of `codec` plays (stgs.client.manifest.FEATURE_CODEC_CHOICES)."""
    if scene.startswith(("http://", "https://")):
        return asyncio.run(_remote(scene, codec))
    folder = Path(scene)
    mpd = folder / MANIFEST if folder.is_dir() else folder
    folder = mpd.parent
    try:
        pres = Presentation.parse(mpd.read_bytes(), "file:///" + MANIFEST, codec)
    except OSError as exc:
        raise StgsError(f"{scene}: not a packaged scene ({exc.strerror or exc})") from None
    except MPDError as exc:
        raise StgsError(f"{mpd}: {exc}") from None
    stats = json.loads((folder / STATS).read_text()) if (folder / STATS).is_file() else None
    try:
        kfs = {rep: [_local_path(folder, pres.keyframe_url(k, rep)).stat().st_size for k in range(pres.num_gops)]
               for rep in pres.keyframe_reps}
        media = {r.rep_id: [_local_path(folder, pres.media_url(r.rep_id, k)).stat().st_size
                            for k in range(pres.num_gops)] for r in pres.ladder}
        init = {r.rep_id: _local_path(folder, pres.init_url(r.rep_id)).stat().st_size for r in pres.ladder}
        static = 0 if pres.static is None else _local_path(folder, pres.static_url()).stat().st_size
    except OSError as exc:
        raise StgsError(f"{scene}: segment missing ({exc.filename})") from None
    return _ladder(pres, kfs, media, init, stats, static)


def _ladder(pres: Presentation, keyframes: dict[str, list[int]], media: dict[str, list[int]], init: dict[str, int],
            stats: dict | None, static: int) -> Ladder:
    lossy = {rep: sizes for rep, sizes in keyframes.items() if rep != KEYFRAME_REP}
    return Ladder(pres, keyframes.get(KEYFRAME_REP, []), media, init, _psnr(stats, pres), stats, static, lossy)


def _psnr(stats: dict | None, pres: Presentation) -> dict[str, list[float | None]]:
    """Per rung and GOP, its quality as stats.json gives it (stgs.tree.rung_quality), None where it does not."""
    ids = [r.rep_id for r in pres.ladder]
    out: dict[str, list[float | None]] = {r: [] for r in ids}
    for k in range(pres.num_gops):
        values: list[float | None] = [None] * len(ids)
        if stats is not None:
            with contextlib.suppress(KeyError, IndexError, TypeError, ValueError):
                values = list(rung_quality(stats["gops"][k]["representations"], ids))
        for r, v in zip(ids, values, strict=True):
            out[r].append(v)
    return out


async def _remote(url: str, codec: str) -> Ladder:
    policy = UrlPolicy(url)
    async with Downloader(policy=policy) as dl:
        try:
            pres = Presentation.parse(await dl.fetch(url, "document", MAX_MPD_BYTES), url, codec)
            policy.allow_hosts_of(pres.base)
            stats = json.loads(await dl.fetch(pres.sibling_url(STATS), "document", 16 << 20))
            init = {r.rep_id: len(await dl.fetch(pres.init_url(r.rep_id), "init", MAX_INIT_BYTES))
                    for r in pres.ladder}
        except (FetchError, MPDError, json.JSONDecodeError) as exc:
            raise StgsError(f"{url}: cannot read the scene's manifest, stats.json or init segments ({exc})") from None
    try:
        kfs = {rep: [paired_keyframe_bytes(g, rep) for g in stats["gops"]] for rep in pres.keyframe_reps}
        media = {r.rep_id: [int(g["representations"][r.rep_id]["bytes"]) for g in stats["gops"]] for r in pres.ladder}
        static = 0 if pres.static is None else int(stats["static"]["bytes"])
    except (KeyError, TypeError, ValueError) as exc:
        raise StgsError(f"{url}: stats.json lacks per-GOP sizes ({exc})") from None
    if len(stats["gops"]) != pres.num_gops:
        raise StgsError(f"{url}: stats.json lists {len(stats['gops'])} GOPs, the MPD {pres.num_gops}")
    return _ladder(pres, kfs, media, init, stats, static)
