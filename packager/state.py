"""What identifies a pack and what it has finished: the pack id (the `v-<id>/` folder) and the resume state."""

from __future__ import annotations

import hashlib
import json
import threading
from pathlib import Path

from stgs.errors import StgsError
from stgs.fsio import atomic_write_bytes
from stgs.tree import MANIFEST, MODEL_META, PACK_STATE


def pack_id(model_dir: Path, digest_fields: dict) -> str:
    """A digest of the model and of every setting that determines the output bytes."""
    digest = hashlib.sha256((Path(model_dir) / MODEL_META).read_bytes())
    digest.update(json.dumps(digest_fields, sort_keys=True).encode())
    return digest.hexdigest()[:12]


def check_output_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise StgsError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not ((out / PACK_STATE).exists() or (out / MANIFEST).exists()):
        raise StgsError(f"{out}: folder is not empty and not a packaged scene; refusing to write into it")


class PackState:
    """Hashes of finished outputs, saved after every task (for resuming an interrupted pack)."""

    def __init__(self, out: Path, ident: str, resume: bool):
        self.path = out / PACK_STATE
        self.lock = threading.Lock()
        self.doc = {"pack_id": ident, "files": {}, "tasks": {}}
        if resume and self.path.is_file():
            try:
                old = json.loads(self.path.read_text())
            except json.JSONDecodeError:
                old = {}
            if old.get("pack_id") == ident:
                self.doc = old

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

    def record(self, task: str, files: dict[str, bytes], result: dict) -> None:
        with self.lock:
            for rel, data in files.items():
                self.doc["files"][rel] = hashlib.sha256(data).hexdigest()
            self.doc["tasks"][task] = {"files": sorted(files), "result": result}
            atomic_write_bytes(self.path, json.dumps(self.doc, indent=1, sort_keys=True).encode())
