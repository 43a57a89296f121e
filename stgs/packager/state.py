"""What identifies a pack and what it has finished: the pack id (the `v-<id>/` folder) and the resume state."""

from __future__ import annotations

import hashlib
import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from stgs.errors import MPDError, StgsError
from stgs.fsio import atomic_write_bytes
from stgs.mpd.model import PROFILE_STGS, read_mpd
from stgs.tree import MANIFEST, MODEL_META, PACK_STATE


def pack_id(model_dir: Path, gop_files: list[str], digest_fields: dict) -> str:
    """A digest of what is packed (model.json and the bytes of every GOP file, in order) and of every setting
    that determines the output bytes: a GOP file changed in place gives another id, so no URL under `v-<id>/`
    (served as immutable) ever changes its content."""
    model_dir = Path(model_dir)
    digest = hashlib.sha256((model_dir / MODEL_META).read_bytes())
    for name in gop_files:
        digest.update(name.encode() + b"\0")
        with open(model_dir / name, "rb") as f:
            while chunk := f.read(1 << 22):
                digest.update(chunk)
    digest.update(json.dumps(digest_fields, sort_keys=True).encode())
    return digest.hexdigest()[:12]


def _ours(out: Path) -> bool:
    """Whether a non-empty folder holds a tree stgs pack wrote (or began): its state file, or an MPD of the
    StreamSTGS profile."""
    try:
        if json.loads((out / PACK_STATE).read_text()).get("pack_id"):
            return True
    except (OSError, ValueError, AttributeError):
        pass
    try:
        return PROFILE_STGS in read_mpd(out / MANIFEST).profiles
    except (OSError, MPDError):
        return False


def check_output_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise StgsError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not _ours(out):
        raise StgsError(f"{out}: folder is not empty and not a tree stgs pack wrote; refusing to write into it")


class PackState:
    """Hashes of finished outputs, saved after every task (for resuming an interrupted pack)."""

    def __init__(self, out: Path, ident: str, resume: bool):
        self.path = out / PACK_STATE
        self.lock = threading.Lock()
        self.doc: dict[str, Any] = {"pack_id": ident, "files": {}, "tasks": {}}
        if resume and self.path.is_file():
            try:
                old = json.loads(self.path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                old = {}
            if isinstance(old, dict) and old.get("pack_id") == ident:
                self.doc = old
        self.save()  # before any output: a run killed at its first segment leaves a tree --resume recognises

    def save(self) -> None:
        atomic_write_bytes(self.path, json.dumps(self.doc, indent=1, sort_keys=True).encode())

    def done(self, out: Path, task: str) -> dict | None:
        """The recorded result of `task` if every file it wrote is still intact."""
        entry = self.doc["tasks"].get(task)
        if entry is None:
            return None
        for rel in entry["files"]:
            path = out / rel
            if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != self.doc["files"].get(rel):
                return None
        return entry["result"]

    def forget(self, which: Callable[[str], bool]) -> None:
        """Drop the tasks `which(name)` selects, and the files only they wrote."""
        with self.lock:
            tasks = self.doc["tasks"]
            for name in [t for t in tasks if which(t)]:
                del tasks[name]
            kept = {rel for entry in tasks.values() for rel in entry["files"]}
            self.doc["files"] = {rel: d for rel, d in self.doc["files"].items() if rel in kept}
            self.save()

    def record(self, task: str, files: dict[str, str], result: dict) -> None:
        """`task` finished: the SHA-256 of each file it wrote (by path) and its result."""
        with self.lock:
            for rel, digest in files.items():
                self.doc["files"][rel] = digest
            self.doc["tasks"][task] = {"files": sorted(files), "result": result}
            self.save()
