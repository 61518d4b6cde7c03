"""dibrpp's C++ kernels (``dibrpp/csrc``), built with torch's extension mechanism.

``make setup`` builds them (``python -m dibrpp build-kernels``) into torch's extension cache
(``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``) under a name that carries a digest of the
sources and flags: a later import only loads the built library, and two checkouts with different sources on one
machine keep a build each instead of rebuilding each other's on every switch. Where the build fails (no C++ compiler, no ninja), or with
``DIBRPP_NATIVE=0`` in the environment, :func:`mc_envmap` returns None and the renderer runs the same
computation in PyTorch (with one warning for a failed build).
"""
from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import sys
import time
import warnings
from pathlib import Path

SOURCES = (Path(__file__).parent / "csrc" / "mc_envmap.cpp",)
STALE_LOCK_S = 600  # a build lock this old was left by a killed build (a build takes ~30 s): torch would wait forever


def enabled() -> bool:
    return os.environ.get("DIBRPP_NATIVE", "1") != "0"


def simd_flags(simd: bool = True) -> list[str]:
    """AVX2 + FMA where this CPU has them (the lane loops of the kernel become 8-wide), else the compiler's
    baseline. FMA contraction stays off, so both builds compute the same values (a test checks it)."""
    flags = ["-ffp-contract=off"]
    if simd and platform.machine() in ("x86_64", "AMD64"):
        try:
            cpu = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpu = ""
        words = set(cpu.split())
        if {"avx2", "fma"} <= words:
            flags += ["-mavx2", "-mfma"]
    return flags


@functools.cache
def mc_envmap(simd: bool = True):
    """The fused MC env-map shading module (``forward``, ``backward_image``), or None where unavailable.
    simd=False: the build without AVX2, whatever the CPU (for tests)."""
    if not enabled():
        return None
    try:
        from torch.utils.cpp_extension import load

        if shutil.which("ninja") is None:  # the ninja wheel's binary, when the venv's bin is not on PATH
            import ninja

            os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + os.environ.get("PATH", "")
        isa = simd_flags(simd)
        # One name per instruction set and per source: a cache shared by different machines or checkouts never
        # loads (or rebuilds over) another's build.
        name = "dibrpp_mc_envmap" + ("_avx2" if "-mavx2" in isa else "") + "_" + build_digest(isa)
        remove_stale_lock(name)
        # -fopenmp: at::parallel_for runs on torch's own OpenMP pool (the library binds to the libgomp torch has
        # loaded). -fno-math-errno / -fno-trapping-math drop errno and trap bookkeeping only: the same values.
        return load(name, [str(s) for s in SOURCES], verbose=False, extra_ldflags=["-fopenmp"],
                    extra_cflags=["-O3", "-fopenmp", "-fno-math-errno", "-fno-trapping-math", *isa])
    except Exception as e:  # noqa: BLE001 -- any build failure: PyTorch computes the same values
        text = str(e)
        detail = text if len(text) < 600 else text[:200] + " ... " + text[-400:]  # the compiler's error is last
        warnings.warn(f"dibrpp's C++ MC kernel is unavailable ({type(e).__name__}: {detail}); "
                      "MC shading under env maps runs in PyTorch (slower, same values)")
        return None


def build_digest(flags: list[str]) -> str:
    """8 hex digits of the sources' bytes and the compiler flags."""
    digest = hashlib.sha256(" ".join(flags).encode())
    for source in SOURCES:
        digest.update(source.read_bytes())
    return digest.hexdigest()[:8]


def remove_stale_lock(name: str) -> None:
    """torch's build waits on ``<build dir>/lock`` while another process builds; a killed build leaves it behind."""
    from torch.utils.cpp_extension import _get_build_directory

    lock = Path(_get_build_directory(name, verbose=False)) / "lock"
    try:
        if time.time() - lock.stat().st_mtime > STALE_LOCK_S:
            warnings.warn(f"removing {lock}, left by a build killed {STALE_LOCK_S // 60}+ min ago")
            lock.unlink()
    except FileNotFoundError:
        pass


def build() -> int:
    """Build (or find) the kernels and say where; ``make setup`` runs this (``python -m dibrpp build-kernels``)
    so that the first render does not compile. Exit status 0 either way: without the kernels dibrpp still works."""
    t0 = time.time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = mc_envmap()
    if module is None:
        reason = caught[0].message if caught else "DIBRPP_NATIVE=0"
        print(f"dibrpp C++ kernels not built ({reason}); the PyTorch path will be used", file=sys.stderr)
        return 0
    print(f"dibrpp C++ kernels ready ({time.time() - t0:.1f} s): {module.__file__}")
    return 0
