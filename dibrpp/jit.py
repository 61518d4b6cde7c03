"""Optional torch.compile of the renderer's hot functions, with the eager function as the fallback."""
from __future__ import annotations

import warnings

import torch


class CompiledOrEager:
    """``fn`` through ``torch.compile`` (fused loops in the forward and the backward instead of one pass
    per tensor op), or ``fn`` itself, with one warning, where compilation fails (no C++ compiler, an
    unsupported platform). Shapes are compiled as dynamic: a new batch or pixel count does not recompile.
    Module-level instances share one compilation cache across renderers."""

    def __init__(self, fn):
        self.fn, self.compiled, self.failed = fn, None, False

    def __call__(self, *args):
        if not self.failed:
            try:
                if self.compiled is None:
                    self.compiled = torch.compile(self.fn, dynamic=True)
                return self.compiled(*args)
            except Exception as e:  # noqa: BLE001 -- any compiler failure: fall back, results are identical
                warnings.warn(f"torch.compile of {self.fn.__name__} failed ({type(e).__name__}: {str(e)[:200]}); "
                              "it runs eagerly")
                self.failed = True
        return self.fn(*args)
