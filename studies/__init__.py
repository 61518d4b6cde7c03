"""Renderer studies of the supplementary's Sec. B and C (Figures A-E), on a unit sphere under procedural HDR
light; they use the renderer only, never the learning code. ``python -m studies --out results/studies``
(``make studies``) runs them all.

- :mod:`studies.noise`: Fig. A, MC noise vs samples per pixel and roughness, with and without env-map MIS;
- :mod:`studies.sg_fit`: Fig. B, SG mixtures of K lobes fitted to env maps, error vs K;
- :mod:`studies.ambiguity`: Fig. C, sharp light + rough sphere vs smooth light + glossy sphere;
- :mod:`studies.joint_fit`: Figs. D (MC) and E (SG), joint optimisation of light, albedo, roughness, specular;
- :mod:`studies.common`: the shared scene (procedural env maps, SG fits, orbit cameras), foreground measures,
  tables and image grids.

Each study module has ``Sizes`` (its default sizes), ``QUICK`` (tiny sizes for the smoke test) and
``run(out, sizes, device) -> str`` (writes its tables and figures, returns its Markdown table).
"""
