"""The one live Blender scene: a mesh with a Principled material, lit only by an environment map, seen by one
perspective camera; :func:`build_scene` makes it, :func:`set_camera`, :func:`set_envmap` and :func:`set_seed`
change it between renders."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from .blender import (LINEAR_COLORSPACE, as_array, bpy_module, empty_node_tree, image_from_array, load_image, reset,
                      scratch_dir)
from .material import PrincipledMaterial, make_material
from .settings import RenderSettings, configure_render


@dataclass
class CyclesScene:
    """Handles to the objects of the one live Blender scene built by :func:`build_scene`."""

    scene: object
    obj: object
    camera: object
    material: object
    world: object
    env_node: object
    resolution: int
    albedo_aov: bool
    tmpdir: str = field(default_factory=lambda: scratch_dir())
    render_seconds: float = 0.0  # wall time spent inside Cycles' render call (cumulative)
    renders: int = 0
    settings: RenderSettings | None = None

    @property
    def bsdf(self):
        return self.material.node_tree.nodes["Principled BSDF"]


# ----------------------------------------------------------------------------- geometry

def _checked_geometry(verts, faces) -> tuple[np.ndarray, np.ndarray]:
    v = as_array(verts, np.float64)
    f = as_array(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"verts must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must be (F, 3) triangles, got {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"faces index vertices outside [0, {len(v)})")
    if not np.isfinite(v).all():
        raise ValueError("verts contain NaN or Inf")
    return v, f


def _corner_uvs(uvs, face_uvs, faces: np.ndarray, num_verts: int) -> np.ndarray:
    """(F, 3, 2) UVs per face corner, from per-vertex ``uvs`` or ``uvs`` indexed by ``face_uvs``."""
    uv = as_array(uvs, np.float32)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uvs must be (T, 2), got {uv.shape}")
    if face_uvs is None:
        if len(uv) != num_verts:
            raise ValueError(f"per-vertex uvs need one row per vertex ({num_verts}), got {len(uv)}; or pass face_uvs")
        return uv[faces]
    fu = as_array(face_uvs, np.int64)
    if fu.shape != faces.shape:
        raise ValueError(f"face_uvs must have the shape of faces {faces.shape}, got {fu.shape}")
    if fu.min() < 0 or fu.max() >= len(uv):
        raise ValueError(f"face_uvs index uvs outside [0, {len(uv)})")
    return uv[fu]


def _make_mesh_object(verts, faces, uvs=None, face_uvs=None, smooth=True):
    bpy = bpy_module()
    v, f = _checked_geometry(verts, faces)
    mesh = bpy.data.meshes.new("object")
    nv, nf = len(v), len(f)
    mesh.vertices.add(nv)
    mesh.vertices.foreach_set("co", v.astype(np.float32).reshape(-1))
    mesh.loops.add(3 * nf)
    mesh.loops.foreach_set("vertex_index", f.astype(np.int32).reshape(-1))
    mesh.polygons.add(nf)
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * nf, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    if mesh.validate(verbose=False):
        # validate() fixes degenerate/duplicate faces; per-corner data would no longer line up.
        if uvs is not None and len(mesh.polygons) != nf:
            raise ValueError("the mesh has degenerate or duplicate faces (Blender removed some); clean it first")
    if uvs is not None:
        corner = _corner_uvs(uvs, face_uvs, f, nv)
        layer = mesh.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", np.ascontiguousarray(corner, np.float32).reshape(-1))
    mesh.polygons.foreach_set("use_smooth", np.full(len(mesh.polygons), bool(smooth)))
    mesh.update()
    obj = bpy.data.objects.new("object", mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


# ----------------------------------------------------------------------------- environment and camera

def make_world(envmap):
    """A world lit only by ``envmap`` (EXR path or (H, W, 3) linear array, top row first) through an
    Environment Texture node with default mapping at strength 1; returns (world, environment node)."""
    bpy = bpy_module()
    world = bpy.data.worlds.new("world")
    nodes, links = empty_node_tree(world)
    out = nodes.new("ShaderNodeOutputWorld")
    bg = nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = 1.0
    env = nodes.new("ShaderNodeTexEnvironment")
    env.name = "envmap"
    env.interpolation = "Linear"
    env.projection = "EQUIRECTANGULAR"
    links.new(env.outputs["Color"], bg.inputs["Color"])
    links.new(bg.outputs["Background"], out.inputs["Surface"])
    bpy.context.scene.world = world
    _assign_envmap(env, envmap)
    return world, env


def _assign_envmap(env_node, envmap):
    bpy = bpy_module()
    old = env_node.image
    if isinstance(envmap, (str, os.PathLike)):
        img = load_image(envmap, LINEAR_COLORSPACE)
    else:
        arr = as_array(envmap, np.float32)
        if arr.ndim != 3 or arr.shape[-1] != 3:
            raise ValueError(f"envmap must be an EXR path or an (H, W, 3) linear array, got shape {arr.shape}")
        if (arr < 0).any():
            raise ValueError("envmap has negative radiance")
        img = image_from_array("envmap", arr, LINEAR_COLORSPACE)
    env_node.image = img
    if old is not None and old.users == 0:
        bpy.data.images.remove(old)


def _make_camera(scene):
    """A perspective camera whose ``angle`` is the field of view (sensor fit AUTO), made the scene's camera."""
    bpy = bpy_module()
    cam_data = bpy.data.cameras.new("camera")
    cam_data.type = "PERSP"
    cam_data.lens_unit = "FOV"
    cam_data.sensor_fit = "AUTO"
    cam_data.clip_start = 0.01
    cam_data.clip_end = 1.0e5
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    return cam


# ----------------------------------------------------------------------------- public API

def build_scene(verts, faces, *, envmap, settings: RenderSettings | None = None,
                material: PrincipledMaterial | None = None, uvs=None, face_uvs=None, smooth=True) -> CyclesScene:
    """Reset Blender and build the one scene: mesh + Principled material + environment + camera.

    verts (V, 3), faces (F, 3): Blender world coordinates (+Z up), numpy or torch; uvs (T, 2) with
    face_uvs (F, 3) (per-corner, OBJ convention v up) or per-vertex uvs (V, 2); ``smooth`` shading
    interpolates vertex normals. envmap: EXR path or (H, W, 3) linear array, top row first.
    ``material`` defaults to ``PrincipledMaterial()``, ``settings`` to ``RenderSettings()``. The camera is
    placed by :func:`set_camera` (until then it sits at the origin).
    """
    bpy = bpy_module()
    settings = RenderSettings() if settings is None else settings
    material = PrincipledMaterial() if material is None else material
    if not isinstance(settings, RenderSettings) or not isinstance(material, PrincipledMaterial):
        raise TypeError("build_scene takes settings=RenderSettings(...) and material=PrincipledMaterial(...)")
    settings.validate()
    material.validate()
    reset()
    scene = bpy.context.scene
    configure_render(scene, settings)
    obj = _make_mesh_object(verts, faces, uvs, face_uvs, smooth)
    mat = make_material(obj, material, albedo_aov=settings.albedo_aov, has_uvs=uvs is not None)
    world, env = make_world(envmap)
    cam = _make_camera(scene)
    return CyclesScene(scene, obj, cam, mat, world, env, int(settings.resolution), bool(settings.albedo_aov),
                       settings=settings)


def set_camera(cs: CyclesScene, world_to_camera, fov) -> None:
    """Place the camera: ``world_to_camera`` (4, 4) in dibrpp's convention, ``fov`` in radians."""
    from mathutils import Matrix  # noqa: PLC0415  (ships with bpy)

    w2c = as_array(world_to_camera, np.float64)
    if w2c.shape != (4, 4) or not np.isfinite(w2c).all():
        raise ValueError(f"world_to_camera must be a finite (4, 4) matrix, got shape {w2c.shape}")
    rot = w2c[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-4) or np.linalg.det(rot) < 0:
        raise ValueError("world_to_camera must be a rigid transform (orthonormal rotation, det +1)")
    fov = float(fov)
    if not 0.0 < fov < math.pi:
        raise ValueError(f"fov must be in (0, pi) radians, got {fov}")
    c2w = np.linalg.inv(w2c)
    cs.camera.matrix_world = Matrix(c2w.tolist())
    cs.camera.data.angle = fov


def set_envmap(cs: CyclesScene, envmap) -> None:
    """Swap the environment map (EXR path or (H, W, 3) linear array) without rebuilding the scene."""
    _assign_envmap(cs.env_node, envmap)


def set_seed(cs: CyclesScene, seed: int) -> None:
    cs.scene.cycles.seed = int(seed)
