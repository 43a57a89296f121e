"""The stgs command: help for every subcommand, one-line errors, synth from the command line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from stgs.cli import build_parser, main
from stgs.model.store import load_model
from tests.conftest import run_stgs as stgs

SUBCOMMANDS = ["prepare", "inspect", "synth", "train", "eval", "pack", "serve", "play", "sim", "demo", "bench",
               "export"]


def test_every_subcommand_has_help(capsys):
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices
    assert sorted(choices) == sorted(SUBCOMMANDS)
    for name in SUBCOMMANDS:  # in this process: the parsers are the script's (one subprocess below)
        with pytest.raises(SystemExit) as done:
            main([name, "--help"])
        assert done.value.code == 0 and "usage: stgs " + name in capsys.readouterr().out
    result = stgs("--help")
    assert result.returncode == 0 and all(name in result.stdout for name in SUBCOMMANDS)


def test_synth_help_names_every_effect_the_generator_knows():
    from stgs.cli.config_flags import field_docs
    from stgs.synth.config import EFFECTS, SynthConfig

    doc = field_docs(SynthConfig)["effects"]
    assert all(name in doc for name in EFFECTS)


def test_the_parsers_load_neither_torch_nor_opencv():
    """Every subcommand's help, choices and defaults come from light modules: help and a mistyped flag are
    instant, and the heavy stack loads only when a command runs."""
    code = ("import sys; from stgs.cli import build_parser; build_parser(); "
            "print(sorted({'torch', 'cv2', 'OpenImageIO'} & set(sys.modules)))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


@pytest.mark.parametrize("args,message", [
    (["synth", "OUT", "--effects", "rigid,explode"], "unknown effect(s) ['explode']"),
    (["synth", "OUT", "--config", "missing.toml"], "cannot read synth config"),
    (["synth", "OUT", "--grid-side", "2"], "grid_side must be >= 4"),
    (["synth", "OUT", "--feature-smoothness", "-1"], "feature_smoothness must be in [0, 1e6)"),
    (["synth", "OUT", "--seconds", "2", "--gops", "3"], "--seconds and --gops both set the scene's length"),
    (["bench", "render", "--sizes", "12,abc"], "--sizes must be comma-separated integers"),
    (["bench", "synth", "--smoothness", "0,x"], "--smoothness must be comma-separated numbers"),
    (["bench", "synth", "--smoothness", "nan"], "--smoothness must list numbers in [0, 1e6)"),
    (["train", "DATA", "OUT", "--position-lr", "0"], "lr.position must be a positive number"),
    (["train", "DATA", "OUT", "--position-lr", "inf"], "lr.position must be a positive number"),
    (["train", "DATA", "OUT", "--lr", "features"], "--lr expects NAME=NUMBER, got 'features'"),
    (["train", "DATA", "OUT", "--lr", "features=fast"], "--lr expects NAME=NUMBER, got 'features=fast'"),
    (["train", "DATA", "OUT", "--lr", "speed=1e-3"], "unknown learning rate(s) speed; known: position,"),
    (["train", "DATA", "OUT", "--lr", "field=-1e-3"], "lr.field must be a positive number"),
    (["train", "DATA", "OUT", "--lr", "position=1e-4", "--position-lr", "1e-4"],
     "--position-lr and --lr position=... both set"),
])
def test_user_errors_are_one_line(tmp_path, args, message):
    result = stgs(*args, cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stgs: ") and message in lines[0]
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "OUT").exists()


def test_train_overrides_from_the_command_line():
    from stgs.cli import train_overrides
    from stgs.train.config import BUDGETS

    args = build_parser().parse_args(["train", "DATA", "OUT", "--budget", "cpu", "--grid-side", "64", "--no-aux",
                                      "--position-lr", "8e-4"])
    overrides = train_overrides(args)
    assert overrides["grid_side"] == 64 and overrides["aux"] is False
    assert overrides["lr"].position == 8e-4 and overrides["lr"].position_final == pytest.approx(8e-6)
    assert overrides["lr"].features == BUDGETS["cpu"].lr.features  # the rest stays the budget's
    assert "lr" not in train_overrides(build_parser().parse_args(["train", "DATA", "OUT"]))


def test_any_learning_rate_from_the_command_line():
    from stgs.cli import train_overrides
    from stgs.train.config import BUDGETS

    cpu = BUDGETS["cpu"].lr
    args = build_parser().parse_args(["train", "DATA", "OUT", "--budget", "cpu", "--lr", "features=5e-3",
                                      "--lr", "field=3.2e-3", "--position-lr", "8e-4"])
    rates = train_overrides(args)["lr"]
    assert rates.features == 5e-3 and rates.field == 3.2e-3 and rates.position == 8e-4
    # a decaying rate keeps its decay: the final rate moves by the same factor as the initial one
    assert rates.field_final == pytest.approx(cpu.field_final * 2) and rates.position_final == pytest.approx(8e-6)
    assert rates.opacity == cpu.opacity and rates.camera_colour == cpu.camera_colour
    args = build_parser().parse_args(["train", "DATA", "OUT", "--lr", "field=3.2e-3", "--lr", "field_final=1e-5"])
    rates = train_overrides(args)["lr"]
    assert rates.field == 3.2e-3 and rates.field_final == 1e-5  # set apart: kept as given


@pytest.mark.parametrize("where", ["file-as-parent", "read-only-fs"])
def test_unwritable_output_is_one_line(tmp_path, where):
    """Outputs nobody can write (not even root): under a regular file, or on /proc."""
    if where == "file-as-parent":
        (tmp_path / "plain.txt").write_text("x")
        out = tmp_path / "plain.txt" / "out"
    else:
        out = "/proc/stgs-test-output"
    result = stgs("synth", str(out), "--grid-side", "4", "--gops", "1", "--gop-size", "2",
                  "--fit-steps", "1", "--quiet")
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stgs: ") and "Traceback" not in result.stderr


def test_synth_takes_the_capture_length_in_seconds(tmp_path):
    out = tmp_path / "scene"
    result = stgs("synth", str(out), "--seconds", "1", "--gop-size", "4", "--grid-side", "4", "--width", "32",
                  "--height", "24", "--cameras", "2", "--fit-steps", "2", "--effects", "rigid", "--quiet")
    assert result.returncode == 0, result.stderr
    meta, gops = load_model(out)
    assert len(gops) == 8 and meta.fps == 30.0  # 30 frames of the small preset's 30 fps need 8 GOPs of 4
    assert "8 GOPs x 4 frames (1.06667 s at 30 fps)" in result.stdout


def test_synth_command_writes_a_model_dir(tmp_path):
    out = tmp_path / "scene"
    result = stgs("synth", str(out), "--grid-side", "8", "--gops", "1", "--gop-size", "4",
                  "--width", "32", "--height", "24", "--cameras", "2", "--fit-steps", "20",
                  "--effects", "rigid,color", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "fidelity of the model vs ground truth" in result.stdout
    meta, _ = load_model(out)
    assert meta.shape.capacity == 64 and meta.extra["config"]["effects"] == ["rigid", "color"]


@pytest.mark.parametrize(("text", "size"), [("4096", 4096), ("512M", 512 << 20), ("1.5G", 3 << 29),
                                            ("2GiB", 2 << 30), ("64kb", 64 << 10), ("0", 0)])
def test_memory_sizes_take_binary_units(text, size):
    assert build_parser().parse_args(["train", "d", "o", "--max-memory", text]).max_memory == size


@pytest.mark.parametrize("text", ["lots", "-1G", "1X", "nanM"])
def test_a_bad_memory_size_is_one_line(text):
    result = stgs("train", "nowhere", "out", "--max-memory", text)
    assert result.returncode == 2 and "--max-memory" in result.stderr and "Traceback" not in result.stderr
