"""The portable kernels (built without AVX-512) against the reference and, stage by stage, against their torch
twins, in separate processes.

This machine has AVX-512, so the default build runs the AVX-512 tile kernels;
the `#pragma omp simd` versions that other CPUs get are built here with
-march=x86-64-v3 (AVX2) into a private cache and held to the same oracle.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

CHECK = textwrap.dedent("""
    import torch
    from stgs.native.build import FLAGS
    from stgs.render import rasterize
    from tests.conftest import pinhole, random_scene
    from tests.model.test_gop import random_model
    from stgs.model.native_deform import deform_native

    assert "-march=x86-64-v3" in FLAGS
    args = random_scene(500, 3)
    view, K = pinhole(70, 45, 60.0)
    ref_in = [a.clone().requires_grad_() for a in args]
    nat_in = [a.float().clone().requires_grad_() for a in args]
    ref = rasterize(*ref_in, view, K, 70, 45, backend="reference")
    nat = rasterize(*nat_in, view.float(), K.float(), 70, 45, backend="native")
    g = torch.randn(ref.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    (ref * g).sum().backward()
    (nat * g.float()).sum().backward()
    assert (nat.double() - ref).abs().max() <= 1e-4
    for a, b in zip(ref_in, nat_in):
        peak = a.grad.abs().max()
        assert (a.grad - b.grad.double()).abs().max() <= 1e-3 * peak
    model = random_model(n=300)
    with torch.no_grad():
        want = model.deform(2, torch.zeros(3))
        got = deform_native(model, 2, torch.zeros(3))
    assert torch.allclose(want.means, got.means, rtol=1e-4, atol=1e-5)
    assert torch.allclose(want.colors, got.colors, rtol=1e-4, atol=1e-5)
    from stgs.model.native_deform import bf16_available
    assert not bf16_available()  # no AMX tiles in an AVX2 build: bf16 reports itself unavailable
    print("portable ok")
""")


def test_portable_kernels_match_reference(tmp_path):
    env = {**os.environ, "STGS_NATIVE_ARCH": "x86-64-v3", "STGS_NATIVE_CACHE": str(tmp_path)}
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    result = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, env=env,
                            cwd=root, timeout=300)
    assert result.returncode == 0 and "portable ok" in result.stdout, result.stderr[-3000:]
    assert list(tmp_path.glob("libstgs_native-*.so")), "the portable library was built"
    # Every stage of the portable build against its torch twin too (the tile lists id for id).
    stages = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                             "tests/render/test_stages.py"], capture_output=True, text=True, env=env, cwd=root,
                            timeout=300)
    assert stages.returncode == 0, stages.stdout[-3000:]
    assert " passed" in stages.stdout and "skipped" not in stages.stdout
