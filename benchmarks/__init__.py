"""Benchmarks of the supplementary's performance tables, each runnable as ``python -m benchmarks.<module>``.

- :mod:`benchmarks.renderer`: Table A, renderer scaling: shading time of SG for K lobes and MC for N samples
  (256x256 sphere), the training workload's render and rasterization alone (``make bench-renderer``).
- :mod:`benchmarks.mitsuba`: Table B, the same env-map optimisation in dibrpp and in Mitsuba 3, wall time and
  peak memory (``make bench-mitsuba``); its parts: :mod:`benchmarks.envmap_task` (the shared task),
  :mod:`benchmarks.envmap_dibrpp` and :mod:`benchmarks.envmap_mitsuba` (the two renderers' sides).
- :mod:`benchmarks.train_step`: time of one training iteration and its split into phases (no paper table;
  ``make bench-train``).
- :mod:`benchmarks.memory`: the process's resident memory and its peak (Linux /proc).

Results go under ``results/bench`` (``make bench`` runs all three).
"""
