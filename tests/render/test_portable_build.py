"""The kernels other CPUs get, built here into private caches and held to the same oracle as the default
build, in separate processes: -march=x86-64-v3 (AVX2 and FMA, no AVX-512: the AVX2 compositors, inference and
tracked, the AVX2 backward, and the int16 deformation, which must equal this machine's AVX-512 int16
kernel bit for bit where it has one) and -march=x86-64-v2 (no AVX: every stage the
portable `#pragma omp simd` kernel, and no int16 deformation). Each is checked against the reference and,
stage by stage, against the torch twins.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import textwrap

import pytest
import torch

from stgs.model.native_deform import int16_kernel
from tests.model.test_gop import int16_parity_case

CHECK = textwrap.dedent("""
    import torch
    from stgs.native.build import FLAGS
    from stgs.render import rasterize
    from tests.conftest import pinhole, random_scene
    from tests.model.test_gop import random_model
    from stgs.model.native_deform import deform_native

    import os
    assert "-march=" + os.environ["STGS_NATIVE_ARCH"] in FLAGS
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
    with torch.no_grad():  # the inference compositor (AVX2's own kernel in the v3 build)
        fast = rasterize(*[a.float() for a in args], view.float(), K.float(), 70, 45, backend="native")
    assert (fast.double() - ref.detach()).abs().max() <= 1e-4
    for a, b in zip(ref_in, nat_in):
        peak = a.grad.abs().max()
        assert (a.grad - b.grad.double()).abs().max() <= 1e-3 * peak
    model = random_model(n=300)
    with torch.no_grad():
        want = model.deform(2, torch.zeros(3))
        got = deform_native(model, 2, torch.zeros(3))
    assert torch.allclose(want.means, got.means, rtol=1e-4, atol=1e-5)
    assert torch.allclose(want.colors, got.colors, rtol=1e-4, atol=1e-5)
    from stgs.model.native_deform import bf16_available, check_precision, int16_available
    from stgs.model.precision_oracles import deform_int16_reference
    from stgs.native.library import NativeUnavailableError
    assert not bf16_available()  # no AMX tiles in these builds: bf16 reports itself unavailable
    if os.environ["STGS_NATIVE_ARCH"] == "x86-64-v3":  # AVX2: the int16 kernel is built, and right
        assert int16_available()
        with torch.no_grad():
            got = deform_native(model, 2, torch.zeros(3), precision="int16")
            want = deform_int16_reference(model, 2, torch.zeros(3))
        assert (got.means - want.means).abs().max() <= 2e-3 * want.means.abs().max()
        from tests.model.test_gop import int16_parity_case
        torch.save(int16_parity_case(), os.environ["STGS_INT16_OUT"])
    else:  # no AVX2: int16 says so
        assert not int16_available()
        try:
            check_precision("int16")
            raise AssertionError("int16 ran without AVX2")
        except NativeUnavailableError as err:
            assert "AVX2" in str(err)
    print("portable ok")
""")


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the -march levels named here are x86-64's")
@pytest.mark.parametrize("arch", ["x86-64-v3", "x86-64-v2"])
def test_portable_kernels_match_reference(tmp_path, arch):
    env = {**os.environ, "STGS_NATIVE_ARCH": arch, "STGS_NATIVE_CACHE": str(tmp_path),
           "STGS_INT16_OUT": str(tmp_path / "int16.pt")}
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    result = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, env=env,
                            cwd=root, timeout=300)
    assert result.returncode == 0 and "portable ok" in result.stdout, result.stderr[-3000:]
    assert list(tmp_path.glob("libstgs_native-*.so")), "the portable library was built"
    if arch == "x86-64-v3" and int16_kernel() not in (None, "avx2"):  # this build's AVX-512 int16 kernel
        avx2, here = torch.load(tmp_path / "int16.pt"), int16_parity_case()
        assert avx2.keys() == here.keys()
        for key in here:
            assert torch.equal(here[key], avx2[key]), f"{int16_kernel()} and avx2 int16 kernels differ in {key}"
    # Every stage of the portable build against its torch twin too (the tile lists id for id).
    stages = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                             "tests/render/test_stages.py"], capture_output=True, text=True, env=env, cwd=root,
                            timeout=300)
    assert stages.returncode == 0, stages.stdout[-3000:]
    assert " passed" in stages.stdout and "skipped" not in stages.stdout
