"""A small, reusable single-scene Blender Cycles API (the project's ground-truth renderer).

One object with a Principled BSDF, lit only by an equirectangular environment map, seen by one
square perspective camera, in the project's conventions (:mod:`dibrpp.conventions`):

* world +Z up; ``world_to_camera`` is the 4x4 matrix of :func:`dibrpp.conventions.look_at`
  (camera looks down its local -Z, +Y up); the Blender camera's ``matrix_world`` is its inverse;
* ``fov`` is Blender's camera ``angle`` for a square image (sensor fit AUTO);
* environment maps are linear HDR, top row first, plugged into an Environment Texture node with
  default mapping at strength 1;
* images come back linear (scene-referred) RGBA, top row first, alpha from ``film_transparent``.

Typical use::

    out = render_scene(verts, faces, world_to_camera=w2c, fov=fov, resolution=64, envmap=env, roughness=0.3)
    out["rgba"]  # (64, 64, 4) float32

and, to render one scene from many cameras without rebuilding it, the scene is described by two
records, :class:`PrincipledMaterial` (what the surface is) and :class:`RenderSettings` (how Cycles
renders: resolution, samples, bounces, filter, film, denoiser, threads)::

    scene = build_scene(verts, faces, envmap=env, material=PrincipledMaterial(roughness=0.3),
                        settings=RenderSettings(resolution=64, spp=32))
    for w2c in cameras:
        set_camera(scene, w2c, fov)
        out = render(scene)

Scenes built by hand with bpy (e.g. :mod:`datagen.envmaps`' skies and rooms) use the same public
calls: :func:`configure_render` applies a :class:`RenderSettings` to any scene and
:func:`render_still` renders its active camera to an array.

Only one scene exists at a time (bpy holds one global state): :func:`build_scene` resets Blender
to empty factory settings first, so calls never leak state into each other. bpy is not
thread-safe: parallelise with processes.

The package's parts: :mod:`~datagen.cycles.material` (the Principled surface), :mod:`~datagen.cycles.settings`
(how Cycles renders), :mod:`~datagen.cycles.scene` (building and changing the scene),
:mod:`~datagen.cycles.render` (rendering to arrays), :mod:`~datagen.cycles.blender` (what they share).
"""
from .blender import reset, scratch_dir
from .material import PrincipledMaterial
from .render import read_render_exr, render, render_scene, render_still
from .scene import CyclesScene, build_scene, make_world, set_camera, set_envmap, set_seed
from .settings import RenderSettings, configure_render

__all__ = ["CyclesScene", "PrincipledMaterial", "RenderSettings", "build_scene", "configure_render", "make_world",
           "read_render_exr", "render", "render_scene", "render_still", "reset", "scratch_dir", "set_camera",
           "set_envmap", "set_seed"]
