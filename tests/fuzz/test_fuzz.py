"""The fuzzers of stgs.testing.fuzz, bounded for CI: derandomised cases per target (the same every run), each under
an alarm; only the target's own error type may escape, and memory stays bounded. `python -m bench.fuzzing.fuzz` runs
them for longer with fresh cases (docs/SECURITY.md)."""

from __future__ import annotations

import time

import pytest

from stgs.testing.fuzz import MEMORY_BOUND_MB, TARGETS, HangError, Target, check, fuzz, peak_rss_mb
from stgs.testing.fuzz_inputs import SEED_MPD, SEED_VALUES

CASES = {"mpd": 2000, "keyframe": 1500, "static": 1000, "mp4": 2000, "trace": 1500, "scenario": 1500}


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_fuzzed_inputs_raise_only_the_typed_error(name):
    TARGETS[name].inputs()  # the seeds (an encode, a model) are built outside the measured growth
    before = peak_rss_mb()
    assert fuzz(name, CASES[name], derandomize=True) >= CASES[name] // 2
    assert peak_rss_mb() - before < MEMORY_BOUND_MB


@pytest.mark.parametrize("values", [
    {"media": "x/$Number%099999999999999999999d$.m4s"},
    {"media": "x/$Number%0999999999d$.m4s"},
    {"bandwidth": "9" * 400},
    {"timescale": "0"},
    {"duration": "PT" + "9" * 400 + "S"},
    {"duration": "P" + "9" * 5000 + "D"},
    {"seg_duration": "9" * 400},
])
def test_the_manifests_that_once_broke_the_player_are_typed_errors(values):
    data = SEED_MPD.format(**{**SEED_VALUES, **values}).encode()
    check(TARGETS["mpd"], data)


def test_a_scenario_listing_a_non_string_rule_is_a_typed_error(tmp_path):
    check(TARGETS["scenario"], 'scene = "."\nabr = [[]]')  # found by bench/fuzzing/fuzz.py: a TypeError before


def test_the_harness_reports_an_untyped_error_and_a_hang():
    def untyped(case: object) -> None:
        raise TypeError("not ours")

    def hangs(case: object) -> None:
        time.sleep(30)

    with pytest.raises(TypeError):
        check(Target(lambda: None, untyped, ValueError), b"")
    start = time.monotonic()
    with pytest.raises(HangError):
        check(Target(lambda: None, hangs, ValueError), b"")
    assert time.monotonic() - start < 10
