"""Shared helpers: random scenes and cameras for the splatter tests, the stgs command in a subprocess, the loop-filter
flags of an HEVC stream; a still scene made from a one-frame capture (the client's and the web player's tests)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared"
"""../shared beside the checkout (real data, DASH schema); tests that need it skip without it."""
PANOPTIC = SHARED / "data" / "panoptic-basketball"
"""The real multi-view capture the tests read in place (never copied into the repo)."""


def random_scene(n: int, seed: int, dtype=torch.float64, spread: float = 0.6, depth: float = 3.0,
                 log_scale: float = -3.0) -> list[torch.Tensor]:
    """means, quats, scales, opacities, colors of n random Gaussians in front of an identity camera."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype) * spread
    means[:, 2] += depth
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=gen, dtype=dtype) * 0.5 + log_scale)
    opacities = torch.rand(n, generator=gen, dtype=dtype)
    colors = torch.rand(n, 3, generator=gen, dtype=dtype)
    return [means, quats, scales, opacities, colors]


def pinhole(width: int, height: int, focal: float, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat, K) of an identity-pose camera with a centred principal point."""
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def run_stgs(*args, cwd=None) -> subprocess.CompletedProcess:
    """Run the stgs command in a subprocess (as a user would), capturing its output."""
    return subprocess.run([sys.executable, "-m", "stgs.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "PYTHONWARNINGS": "ignore"}, timeout=600)


LOOP_FILTERS_OFF = {"sample_adaptive_offset_enabled_flag": "0", "pps_deblocking_filter_disabled_flag": "1"}
"""The SPS/PPS flags that switch SAO and deblocking, as an HEVC stream without the in-loop filters sets them."""


def loop_filter_flags(data: bytes, path: Path) -> dict[str, str]:
    """The SPS/PPS flags that switch SAO and deblocking in the HEVC stream `data` (written to `path`), as FFmpeg's
    trace_headers bitstream filter reads them."""
    path.write_bytes(data)
    trace = subprocess.run(["ffmpeg", "-v", "trace", "-i", str(path), "-c", "copy", "-bsf:v", "trace_headers",
                            "-f", "null", "-"], capture_output=True, text=True, check=True).stderr
    flags = {}
    for line in trace.splitlines():
        for name in LOOP_FILTERS_OFF:
            if name in line:
                flags.setdefault(name, line.split()[-1])
    return flags


STILL_CAMERA = "cam00"
"""The still scene's held-out camera (the trainer holds out the first of the capture's cameras)."""


@pytest.fixture(scope="session")
def still_scene(tmp_path_factory) -> Path:
    """A still scene end to end from a one-frame capture (a synthetic scene's first frame, COLMAP per-frame layout):
    `stgs train` as a user runs it (no --layers: it notes the still), then packed to `tree/still`. Its folder holds
    `capture`, `model`, `train.stderr` and `tree/still`."""
    from stgs.packager import PackConfig, pack
    from stgs.synth import SynthConfig
    from tests.data.captures import ground_truth, write_capture

    base = tmp_path_factory.mktemp("still")
    cfg = SynthConfig(grid_side=8, num_gops=1, gop_size=2, width=96, height=72, num_cameras=8,
                      effects=("rigid", "static_background"), static_grid_side=24)
    write_capture(ground_truth(base / "truth", cfg), base / "capture", "frames", num_frames=1)
    trained = run_stgs("train", str(base / "capture"), str(base / "model"), "--coarse-iterations", "400",
                       "--threads", "2", "--quiet")
    assert trained.returncode == 0, trained.stderr
    (base / "train.stderr").write_text(trained.stderr)
    pack(base / "model", base / "tree" / "still", PackConfig(title="A still rig shot"), progress=False)
    return base
