"""The native build: sources compiled one per process, then linked; a compiler error is one clear error and
leaves nothing in the cache."""

from __future__ import annotations

from pathlib import Path

import pytest

from stgs.native import build


def use_fake_compiler(tmp_path: Path, monkeypatch, step: str) -> None:
    """A shell script as $CXX (and a private cache): it answers --version, runs `step` with the step's arguments
    in "$*", then creates the file after -o."""
    fake = tmp_path / "fake-g++"
    fake.write_text('#!/bin/sh\nif [ "$1" = "--version" ]; then echo "fake 1.0"; exit 0; fi\n' + step + "\n"
                    'for a; do [ "$prev" = "-o" ] && : > "$a"; prev="$a"; done\n')
    fake.chmod(0o755)
    monkeypatch.setenv("CXX", str(fake))
    monkeypatch.setenv("STGS_NATIVE_CACHE", str(tmp_path / "cache"))


def test_a_failing_compiler_is_one_clear_error_and_leaves_no_files(tmp_path, monkeypatch):
    use_fake_compiler(tmp_path, monkeypatch,
                      'case "$*" in *deform_int16.cpp*) echo "deform_int16.cpp: error: boom" >&2; exit 1;; esac')
    with pytest.raises(build.NativeUnavailableError, match=r"native build failed: deform_int16\.cpp: error: boom"):
        build.build()
    assert list((tmp_path / "cache").iterdir()) == []  # no library, no objects


def test_every_source_is_compiled_then_linked_once(tmp_path, monkeypatch):
    calls = tmp_path / "calls"
    use_fake_compiler(tmp_path, monkeypatch, f'echo "$*" >> {calls}')
    library = build.build()
    assert library.is_file() and [p.name for p in (tmp_path / "cache").iterdir()] == [library.name]
    lines = calls.read_text().splitlines()
    compiled = sorted(line.split(" -c ")[1].split()[0].rsplit("/", 1)[1] for line in lines if " -c " in line)
    assert compiled == sorted(build.SOURCES)
    links = [line for line in lines if " -c " not in line]
    assert len(links) == 1 and "-shared" in links[0] and links[0].count(".o") == len(build.SOURCES)
