"""Rendering: the scene's camera to linear RGBA arrays (and the albedo), or any bpy scene's active camera."""
from __future__ import annotations

import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from dibrpp.io import DataError, read_exr_channels

from .blender import bpy_module, scratch_dir
from .material import ALBEDO_OUTPUT, SHADED_OUTPUT, PrincipledMaterial
from .scene import CyclesScene, build_scene, set_camera
from .settings import RenderSettings

_ALBEDO_OFF = ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces", "use_denoising")


def read_render_exr(path) -> np.ndarray:
    """The Combined RGBA (H, W, 4) float32 of a render EXR Blender wrote, top row first."""
    ch = read_exr_channels(path)
    planes = []
    for c in "RGBA":
        names = [n for n in ch if n.endswith(f"Combined.{c}")] or [n for n in ch if n == c]
        if not names:
            raise DataError(f"{path}: render EXR has no Combined.{c} channel (has {sorted(ch)})")
        planes.append(ch[names[0]])
    img = np.stack(planes, -1).astype(np.float32)
    if not np.isfinite(img).all():
        raise DataError(f"{path}: non-finite values in the render")
    return img


def _render_file(scene, path: Path) -> Path:
    """Render ``scene``'s active camera into the EXR ``path``; returns the path Blender wrote."""
    bpy = bpy_module()
    path.parent.mkdir(parents=True, exist_ok=True)
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True, scene=scene.name)
    if not path.is_file() and Path(str(path) + ".exr").is_file():  # Blender appends a missing extension
        path = Path(str(path) + ".exr")
    return path


def _read_and_remove(path: Path) -> np.ndarray:
    try:
        return read_render_exr(path)
    finally:
        path.unlink(missing_ok=True)


def render_still(scene=None, name: str = "still") -> np.ndarray:
    """Render the active camera of a bpy scene (default: the current one) set up by
    :func:`configure_render`; returns its Combined RGBA (H, W, 4) float32, linear, top row first."""
    scene = bpy_module().context.scene if scene is None else scene
    return _read_and_remove(_render_file(scene, Path(scratch_dir()) / f"{name}.exr"))


def _render_to(cs: CyclesScene, path: Path) -> Path:
    t0 = time.perf_counter()
    path = _render_file(cs.scene, path)
    cs.render_seconds += time.perf_counter() - t0
    cs.renders += 1
    return path


def _set_albedo_mode(cs: CyclesScene, on: bool) -> None:
    """Switch the material to its base-colour emission output, without bounces (and back)."""
    nodes = cs.material.node_tree.nodes
    nodes[ALBEDO_OUTPUT].is_active_output = on
    nodes[SHADED_OUTPUT].is_active_output = not on
    cs.material.cycles.emission_sampling = "NONE" if on else "AUTO"
    c = cs.scene.cycles
    if on:
        cs._saved_bounces = {k: getattr(c, k) for k in _ALBEDO_OFF}
        for k in _ALBEDO_OFF:
            setattr(c, k, 0 if k != "use_denoising" else False)  # the albedo is noise-free: never denoised
    else:
        for k, v in getattr(cs, "_saved_bounces", {}).items():
            setattr(c, k, v)


def _render_albedo(cs: CyclesScene) -> np.ndarray:
    _set_albedo_mode(cs, True)
    try:
        return _read_and_remove(_render_to(cs, Path(cs.tmpdir) / "albedo.exr"))[..., :3]
    finally:
        _set_albedo_mode(cs, False)


def render(cs: CyclesScene, exr_path=None) -> dict:
    """Render the current camera; returns {'rgba': (R, R, 4) float32 linear, top row first[, 'albedo']}.

    With ``albedo_aov`` the albedo is a second, cheap render of the same camera, samples and seed in
    which the object emits its linear base colour (no lighting, no bounces): a pixel holds the
    pixel-filtered base colour times coverage (premultiplied, 0 on the background), the same as a
    Cycles colour AOV would. ``exr_path``: keep Cycles' EXR of the shaded render there (else a
    temporary file that is deleted).
    """
    if exr_path is not None:
        out = {"rgba": read_render_exr(_render_to(cs, Path(exr_path)))}
    else:
        out = {"rgba": _read_and_remove(_render_to(cs, Path(cs.tmpdir) / "render.exr"))}
    if cs.albedo_aov:
        out["albedo"] = _render_albedo(cs)
    return out


def _split_kwargs(kwargs: dict) -> tuple[dict, dict]:
    """Keyword arguments -> (PrincipledMaterial fields, RenderSettings fields); anything else is an error."""
    mat_keys = {f.name for f in fields(PrincipledMaterial)}
    set_keys = {f.name for f in fields(RenderSettings)}
    unknown = sorted(set(kwargs) - mat_keys - set_keys)
    if unknown:
        raise TypeError(f"unknown argument(s) {unknown}; material: {sorted(mat_keys)}; settings: {sorted(set_keys)}")
    return ({k: v for k, v in kwargs.items() if k in mat_keys}, {k: v for k, v in kwargs.items() if k in set_keys})


def render_scene(verts, faces, *, world_to_camera, fov, envmap, material: PrincipledMaterial | None = None,
                 settings: RenderSettings | None = None, uvs=None, face_uvs=None, smooth=True, **params) -> dict:
    """Render one object under an environment map with Cycles, in one call; see :mod:`datagen.cycles`.

    Geometry, ``envmap``, ``material`` and ``settings`` are those of :func:`build_scene`; the camera those
    of :func:`set_camera`. For convenience any field of :class:`PrincipledMaterial` (base_color, texture,
    roughness, metallic, specular_ior_level, subsurface_*) or of :class:`RenderSettings` (resolution, spp,
    seed, max_bounces, filter_width, albedo_aov, threads, ...) may be given as a keyword instead; it
    overrides the record's value. Returns {'rgba': (R, R, 4) float32 linear, top row first} plus 'albedo'
    (R, R, 3), the linear base colour (premultiplied by coverage, 0 on the background; see :func:`render`),
    when ``albedo_aov``.
    """
    mat_kw, set_kw = _split_kwargs(params)
    material = replace(material or PrincipledMaterial(), **mat_kw)
    settings = replace(settings or RenderSettings(), **set_kw)
    cs = build_scene(verts, faces, envmap=envmap, settings=settings, material=material, uvs=uvs,
                     face_uvs=face_uvs, smooth=smooth)
    set_camera(cs, world_to_camera, fov)
    return render(cs)
