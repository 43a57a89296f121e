"""`stgs demo`, the README's main command, end to end (a few minutes: the scene twice, layered and folded).

The demo fits the default scene with 150 Adam steps per GOP instead of 400 (`--fit-steps`): every stage runs
as in the default demo, on a rougher model (about 43 dB against 53.6), in under half the time."""

from __future__ import annotations

import json

import cv2

from tests.conftest import run_stgs as stgs


def test_demo_streams_the_default_scene_end_to_end(tmp_path):
    out = tmp_path / "demo"
    result = stgs("demo", "--out", str(out), "--quiet", "--fit-steps", "150")
    assert result.returncode == 0, result.stderr
    assert "streamed frames vs ground truth" in result.stdout and "dB PSNR" in result.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 60 and summary["gaussians"] == 4096
    assert summary["model_fidelity_psnr_db"] > 40.0
    assert summary["streamed_vs_truth_psnr_db"] > 35.0  # after compression at whatever QPs the ABR picked
    assert summary["stalls"]["count"] == 0 and summary["kb_per_frame"] > 0
    assert set(summary["qps"]) <= {12, 16, 20, 24, 28, 32, 36, 40} and len(summary["qps"]) == 2  # auto ladder
    log = json.loads((out / "playback.json").read_text())
    assert log["abr"] == "mpc" and log["frames"] == 60 and log["error"] is None
    cap = cv2.VideoCapture(str(out / "orbit.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 60
    ok, first = cap.read()
    assert ok and first.shape == (240, 320, 3) and first.std() > 5  # a real picture, not a blank
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet.shape == (2 * 240, 6 * 320, 3)
    assert cv2.imread(str(out / "compare.png")).shape == (4 * 240, 3 * 320, 3)
    assert (out / "dash" / "manifest.mpd").is_file() and (out / "dash" / "cameras.json").is_file()
    # The default scene is layered: its static layer streamed once; the folded format-1 twin is compared.
    assert log["static_bytes"] == summary["static_bytes"] > 0 and summary["static_gaussians"] == 1024
    two, one = summary["formats"]["2"]["per_qp"], summary["formats"]["1"]["per_qp"]
    stats = json.loads((out / "dash" / "stats.json").read_text())
    assert set(two) == set(one) == set(stats["representations"])  # the folded twin at the rungs the ladder kept
    assert {r for r in two if r.startswith("qp")} and {r for r in two if r.startswith("av1q")}
    assert summary["formats"]["1"]["gaussians"] == 72 * 72  # 4,096 moving + 1,024 backdrop, padded to a square
    for rid in two:  # the backdrop sent once costs less than in every GOP
        assert two[rid]["kb_per_frame"] < one[rid]["kb_per_frame"]
    assert "format 2 (static layer sent once) vs format 1" in result.stdout
    assert "/player/?mpd=/manifest.mpd" in result.stdout  # how to watch it in a browser
    from stgs.cli.browser import missing_browser

    if missing_browser() is None:  # the web player mid-playback, where Chromium is here
        shot = cv2.imread(str(out / "web.png"))
        assert shot is not None and shot.std() > 5, [ln for ln in result.stdout.splitlines() if "web player" in ln]
    else:
        assert "web player screenshot skipped" in result.stdout


def test_bench_render_smoke():
    result = stgs("bench", "render", "--sizes", "300", "--width", "64", "--height", "48",
                  "--repeats", "1")
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| 300 |")]
    backends = [r.split("|")[2].strip() for r in rows]
    from stgs.model.native_deform import bf16_backends, int16_kernel

    bf16 = [f"native bf16 ({bf16_backends()[0]})"] if bf16_backends() else []  # the back end it ran on
    int16 = [f"native int16 ({int16_kernel()})"] if int16_kernel() else []  # and the int16 kernel
    deforms = ["torch fp32", "native fp32", *bf16, *int16]
    assert backends == ["reference fp64", "reference fp32", "native fp32", *deforms]
    reduced = [r.split("|") for r in rows if "native bf16" in r or "native int16" in r]
    for cells in reduced:  # image PSNR against the fp32 deformation: finite and high, not identical
        assert 40 < float(cells[5]) < 200


def test_bench_pack_smoke(tmp_path):
    plot = tmp_path / "rd.png"
    result = stgs("bench", "pack", "--scene", "small", "--qps", "20,32", "--presets", "ultrafast",
                  "--sides", "16", "--plot", str(plot))
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ultrafast |")
            or line.startswith("| medium |")]
    assert len(rows) == 4  # ultrafast with PLAS, medium without, at QPs 20 and 32
    assert plot.stat().st_size > 10_000
    assert "| 16 | 256 |" in result.stdout


def test_bench_play_smoke(tmp_path):
    from stgs.packager import PackConfig, pack
    from stgs.synth import SynthConfig, synthesize

    synthesize(SynthConfig(grid_side=8, num_gops=2, gop_size=4, width=32, height=24, num_cameras=1, fit_steps=10),
               tmp_path / "model", progress=False)
    pack(tmp_path / "model", tmp_path / "dash", PackConfig(ladder="fixed",
                                                           qps=(20, 32), preset="ultrafast"), progress=False)
    result = stgs("bench", "play", "--dash", str(tmp_path / "dash"), "--qps", "20,32", "--width", "64",
                  "--height", "48", "--repeats", "1")
    assert result.returncode == 0, result.stderr
    rows = [line.split("|") for line in result.stdout.splitlines() if line.startswith("| dash |")]
    from stgs.model.native_deform import bf16_available

    precisions = ["fp32"] + (["bf16"] if bf16_available() else [])  # bf16 runs where the CPU has it
    assert [r[3].strip() for r in rows] == ["20", "32"] * len(precisions) * 2  # as measured, then in the table
    assert [r[4].strip() for r in rows] == [p for p in precisions for _ in "ab"] * 2
    assert all(int(r[5]) >= 1 for r in rows)  # the player's decoder threads, as its log reports them
    assert all(int(r[6]) == 2 for r in rows)  # the player's default render-ahead, as its log reports it
    assert all(int(r[8]) == 8 for r in rows)  # every frame of the 2 GOPs x 4 frames was presented
    mbits = [float(r[7]) for r in rows[:2]]
    assert mbits[0] > mbits[1] > 0
    assert "| 20 | fp32 |" in result.stdout  # the largest-scene table
