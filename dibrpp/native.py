"""dibrpp's C++ kernels (``dibrpp/csrc``), built with torch's extension mechanism.

``make setup`` builds them (``python -m dibrpp.native``) into torch's extension cache
(``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``); a later import only loads the built
library, and rebuilds it if a source changed. Where the build fails (no C++ compiler, no ninja), or with
``DIBRPP_NATIVE=0`` in the environment, :func:`mc_envmap` returns None and the renderer runs the same
computation in PyTorch (with one warning for a failed build).
"""
from __future__ import annotations

import functools
import os
import sys
import time
import warnings
from pathlib import Path

SOURCES = (Path(__file__).parent / "csrc" / "mc_envmap.cpp",)


def enabled() -> bool:
    return os.environ.get("DIBRPP_NATIVE", "1") != "0"


@functools.cache
def mc_envmap():
    """The fused MC env-map shading module (``forward``, ``backward_image``), or None where unavailable."""
    if not enabled():
        return None
    try:
        from torch.utils.cpp_extension import load

        return load("dibrpp_mc_envmap", [str(s) for s in SOURCES], extra_cflags=["-O3", "-fopenmp"],
                    extra_ldflags=["-fopenmp"], verbose=False)
    except Exception as e:  # noqa: BLE001 -- any build failure: PyTorch computes the same values
        warnings.warn(f"dibrpp's C++ MC kernel is unavailable ({type(e).__name__}: {str(e)[:300]}); "
                      "MC shading under env maps runs in PyTorch (slower, same values)")
        return None


def main() -> int:
    """Build (or find) the kernels; ``make setup`` runs this so that the first render does not compile."""
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


if __name__ == "__main__":
    sys.exit(main())
