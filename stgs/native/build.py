"""Compile the native CPU kernels (C++ with OpenMP); stgs.native.library loads them.

The library is compiled once per source/flag/compiler combination into a cache
folder (``$STGS_NATIVE_CACHE``, else ``$XDG_CACHE_HOME/stgs/native``, else
``~/.cache/stgs/native``), written atomically, and reused. The README's setup
builds it (``python -m stgs.native.build``); the first load builds it if the
setup did not. Without a compiler everything still works on the pure-torch
reference, slower.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from stgs.errors import NativeUnavailableError

SOURCES = ("project.cpp", "binning.cpp", "forward.cpp", "kept.cpp", "backward.cpp", "ssim.cpp", "temporal.cpp",
           "deform.cpp", "deform_bf16.cpp", "deform_int16.cpp")
"""The splatter by stage (projection, binning, forward, a kept layer's forward, backward), the training loss's
SSIM and temporal term, then the deformation field."""
HEADERS = ("stgs_abi.h", "splat.h", "splat_avx2.h", "splat_avx512.h", "backward_simd.h", "fastmath.h", "deform.h",
           "project.h", "project_avx512.h", "tile_reach.h", "deform_int16.h", "deform_int16_avx2.h",
           "deform_int16_avx512.h")
"""stgs_abi.h is the C ABI (every export, read by stgs.native.abi); the others are internal."""
CSRC = Path(__file__).with_name("csrc")
ARCH = os.environ.get("STGS_NATIVE_ARCH", "native")
"""-march target; e.g. STGS_NATIVE_ARCH=x86-64-v3 builds the portable (no AVX-512) kernels."""
FLAGS = ["-O3", f"-march={ARCH}", "-fopenmp", "-fPIC", "-shared", "-std=c++17", "-fvisibility=hidden",
         "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-Wall", "-Wextra"]
"""-ffp-contract=off keeps forward and backward recomputations bit-identical;
-fno-trapping-math lets floor and float->int conversions vectorise (no FP traps are used);
-fvisibility=hidden leaves the declarations of stgs_abi.h as the library's only exports."""


def compiler() -> str:
    return os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or "c++"


def cache_dir() -> Path:
    if os.environ.get("STGS_NATIVE_CACHE"):
        return Path(os.environ["STGS_NATIVE_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "stgs" / "native"


def build_key(cxx: str) -> str:
    digest = hashlib.sha256()
    for name in SOURCES + HEADERS:
        digest.update(name.encode())
        digest.update((CSRC / name).read_bytes())
    digest.update(" ".join(FLAGS).encode())
    try:
        version = subprocess.run([cxx, "--version"], capture_output=True, text=True,
                                 check=False).stdout
    except OSError as exc:
        raise NativeUnavailableError(f"no C++ compiler ({cxx}): {exc}") from exc
    digest.update(version.encode())
    digest.update(cpu_flags().encode())  # -march=native: a build is only valid on its CPU
    return digest.hexdigest()[:16]


def cpu_flags() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return ""


def library_path() -> Path:
    return cache_dir() / f"libstgs_native-{build_key(compiler())}.so"


def build(verbose: bool = False) -> Path:
    """Compile the kernels unless an up-to-date build is cached; returns the library path.

    Each source compiles in its own g++ process, as many at once as there are cores, then one link."""
    target = library_path()
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    cxx = compiler()
    compile_flags = [f for f in FLAGS if f != "-shared"]
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".build-") as work:
        objects = [str(Path(work) / f"{Path(s).stem}.o") for s in SOURCES]
        commands = [[cxx, *compile_flags, "-I", str(CSRC), "-c", str(CSRC / s), "-o", o]
                    for s, o in zip(SOURCES, objects, strict=True)]
        tmp = str(Path(work) / "lib.so")
        commands.append([cxx, *FLAGS, *objects, "-o", tmp])
        if verbose:
            print("building native kernels:", *(" ".join(c) for c in commands), sep="\n  ", file=sys.stderr)
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            list(pool.map(_run_compiler, commands[:-1]))  # list(): the first failure raises here
        _run_compiler(commands[-1])
        os.replace(tmp, target)
    return target


def _run_compiler(cmd: list[str]) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise NativeUnavailableError(f"native build failed: {proc.stderr.strip()[:2000]}")


def main() -> int:
    try:
        path = build(verbose=True)
    except NativeUnavailableError as exc:
        print(f"stgs: {exc}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
