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
"""
from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from dibrpp.io import DataError, read_exr_channels

__all__ = ["CyclesScene", "PrincipledMaterial", "RenderSettings", "build_scene", "configure_render", "make_world",
           "read_render_exr", "render", "render_scene", "render_still", "reset", "scratch_dir", "set_camera",
           "set_envmap", "set_seed"]

_LINEAR_CS = "Linear Rec.709"


_SCRATCH: str | None = None


def scratch_dir() -> str:
    """One per-process scratch folder for Cycles' EXR output, removed at exit."""
    global _SCRATCH
    if _SCRATCH is None or not os.path.isdir(_SCRATCH):
        import atexit
        import shutil

        _SCRATCH = tempfile.mkdtemp(prefix="dibrpp_cycles_")
        atexit.register(shutil.rmtree, _SCRATCH, True)
    return _SCRATCH


def _bpy():
    try:
        import bpy  # noqa: PLC0415
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "datagen needs Blender as a Python module: `pip install bpy==5.0.1` (Python 3.11, numpy<2), "
            "or `make setup`"
        ) from e
    return bpy


def _np(x, dtype=None) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


# ----------------------------------------------------------------------------- records

_SUBSURFACE_METHODS = ("RANDOM_WALK", "RANDOM_WALK_SKIN", "BURLEY")


@dataclass
class PrincipledMaterial:
    """One Principled BSDF (GGX), in Cycles' own parameters (see DESIGN.md, "Material").

    ``base_color`` is linear RGB; a ``texture`` (sRGB 8-bit PNG path, or an (H, W, 3) float array of
    sRGB values in [0, 1], top row first) replaces it and needs UVs on the mesh. ``specular_ior_level``
    0.5 means F0 = 0.04 (IOR 1.5), 0 removes the specular lobe. ``subsurface_weight`` > 0 turns on
    subsurface scattering (``subsurface_method``, ``subsurface_radius`` per RGB channel times
    ``subsurface_scale``, in scene units).
    """

    base_color: tuple = (0.8, 0.8, 0.8)
    texture: object = None
    roughness: float = 0.5
    metallic: float = 0.0
    specular_ior_level: float = 0.5
    subsurface_weight: float = 0.0
    subsurface_radius: tuple = (1.0, 0.2, 0.1)
    subsurface_scale: float = 0.05
    subsurface_method: str = "RANDOM_WALK"

    def validate(self) -> None:
        for name in ("roughness", "metallic"):
            val = getattr(self, name)
            if not 0.0 <= float(val) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {val}")
        if float(self.specular_ior_level) < 0:
            raise ValueError(f"specular_ior_level must be >= 0, got {self.specular_ior_level}")
        if float(self.subsurface_weight) < 0 or float(self.subsurface_scale) < 0:
            raise ValueError("subsurface_weight and subsurface_scale must be >= 0")
        if len(tuple(self.subsurface_radius)) != 3:
            raise ValueError(f"subsurface_radius must have 3 values (R, G, B), got {self.subsurface_radius}")
        if self.subsurface_method not in _SUBSURFACE_METHODS:
            raise ValueError(f"subsurface_method must be one of {', '.join(_SUBSURFACE_METHODS)}, "
                             f"got {self.subsurface_method!r}")

    @classmethod
    def from_dict(cls, values: dict, **overrides) -> "PrincipledMaterial":
        """From a dataset's material record (roughness, metallic, specular_ior_level, subsurface_*), plus
        ``overrides`` (e.g. ``texture=``); an unknown key is an error, not silently dropped."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown material parameter(s) {unknown}; known: {sorted(known)}")
        return cls(**{**values, **overrides})


@dataclass
class RenderSettings:
    """How Cycles renders: image size, samples, light paths, pixel filter, film and device.

    ``resolution`` is the image height (and width, unless ``width`` is set: panoramas are 2:1).
    ``max_bounces`` bounds every kind of bounce (total, diffuse, glossy, transmission).
    ``filter_width`` is the Blackman-Harris pixel filter's width in pixels (0.01 = pixel centres).
    ``clamp_indirect``: Cycles' indirect sample clamp (0 = unclamped, the unbiased truth).
    ``adaptive_threshold`` > 0 turns on Cycles' adaptive sampling (noise threshold; ``spp`` is then the
    maximum, ``adaptive_min_samples`` the minimum, 0 = automatic). ``denoise`` runs OpenImageDenoise on
    the shaded render with albedo and normal guides (never on the albedo render).
    ``threads`` = 0 lets Cycles use every core. ``albedo_aov`` adds the albedo render to :func:`render`.
    """

    resolution: int = 64
    spp: int = 64
    seed: int = 0
    max_bounces: int = 1
    filter_width: float = 1.5
    film_transparent: bool = True
    width: int | None = None
    clamp_indirect: float = 0.0
    adaptive_threshold: float = 0.0
    adaptive_min_samples: int = 0
    denoise: bool = False
    device: str = "CPU"
    threads: int = 0
    albedo_aov: bool = False

    def validate(self) -> None:
        if int(self.resolution) <= 0 or (self.width is not None and int(self.width) <= 0):
            raise ValueError(f"resolution must be a positive number of pixels, got {self.resolution}"
                             + (f" x {self.width}" if self.width is not None else ""))
        if int(self.spp) <= 0:
            raise ValueError(f"spp must be positive, got {self.spp}")
        if int(self.max_bounces) < 0:
            raise ValueError(f"max_bounces must be >= 0, got {self.max_bounces}")
        if not 0.01 <= float(self.filter_width) <= 10.0:
            raise ValueError(f"filter_width must be in [0.01, 10] pixels (Cycles' range), got {self.filter_width}")
        if self.device not in ("CPU", "GPU"):
            raise ValueError(f"device must be 'CPU' or 'GPU', got {self.device!r}")
        if float(self.adaptive_threshold) < 0 or int(self.adaptive_min_samples) < 0:
            raise ValueError("adaptive_threshold and adaptive_min_samples must be >= 0")
        if float(self.clamp_indirect) < 0:
            raise ValueError(f"clamp_indirect must be >= 0 (0 = off), got {self.clamp_indirect}")


def _split_kwargs(kwargs: dict) -> tuple[dict, dict]:
    """Keyword arguments -> (PrincipledMaterial fields, RenderSettings fields); anything else is an error."""
    mat_keys = {f.name for f in fields(PrincipledMaterial)}
    set_keys = {f.name for f in fields(RenderSettings)}
    unknown = sorted(set(kwargs) - mat_keys - set_keys)
    if unknown:
        raise TypeError(f"unknown argument(s) {unknown}; material: {sorted(mat_keys)}; settings: {sorted(set_keys)}")
    return ({k: v for k, v in kwargs.items() if k in mat_keys}, {k: v for k, v in kwargs.items() if k in set_keys})

# ----------------------------------------------------------------------------- scene handle

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


# ----------------------------------------------------------------------------- building blocks

def reset() -> None:
    """Empty Blender: factory settings without the default cube/camera/light, all images freed."""
    bpy = _bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for img in list(bpy.data.images):
        bpy.data.images.remove(img)


def _image_from_array(name: str, pixels: np.ndarray, colorspace: str):
    """A float bpy image from an (H, W, C) array given top row first (bpy stores bottom row first)."""
    bpy = _bpy()
    arr = _np(pixels, np.float32)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{name}: expected an (H, W, 3) or (H, W, 4) image, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: image contains NaN or Inf")
    h, w = arr.shape[:2]
    if arr.shape[-1] == 3:
        arr = np.concatenate([arr, np.ones((h, w, 1), np.float32)], -1)
    img = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=True)
    img.colorspace_settings.name = colorspace
    img.pixels.foreach_set(np.ascontiguousarray(arr[::-1]).reshape(-1))
    img.pack()  # keep the pixels with the .blend data; Cycles reads packed/generated buffers alike
    return img


def _load_image(path, colorspace: str):
    bpy = _bpy()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such image file")
    try:
        img = bpy.data.images.load(str(path.resolve()), check_existing=False)
    except RuntimeError as e:
        raise DataError(f"{path}: Blender cannot read this image ({e})") from e
    img.colorspace_settings.name = colorspace
    return img


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _texture_image(texture):
    """bpy image for a colour texture: PNG path (sRGB, Cycles decodes) or float sRGB array."""
    if isinstance(texture, (str, os.PathLike)):
        return _load_image(texture, "sRGB")
    arr = _np(texture, np.float32)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"texture must be a PNG path or an (H, W, 3) sRGB array in [0, 1], got shape {arr.shape}")
    # Decode sRGB here with the same formula as dibrpp.conventions.srgb_to_linear (exact, no 8-bit
    # quantisation) and hand Cycles linear floats: identical to Cycles decoding an sRGB texture.
    return _image_from_array("texture", _srgb_to_linear(arr), _LINEAR_CS)


def _make_mesh_object(verts, faces, uvs=None, face_uvs=None, smooth=True):
    bpy = _bpy()
    v = _np(verts, np.float64)
    f = _np(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"verts must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must be (F, 3) triangles, got {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"faces index vertices outside [0, {len(v)})")
    if not np.isfinite(v).all():
        raise ValueError("verts contain NaN or Inf")
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
        uv = _np(uvs, np.float32)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uvs must be (T, 2), got {uv.shape}")
        if face_uvs is None:
            if len(uv) != nv:
                raise ValueError(f"per-vertex uvs need one row per vertex ({nv}), got {len(uv)}; or pass face_uvs")
            corner = uv[f]
        else:
            fu = _np(face_uvs, np.int64)
            if fu.shape != f.shape:
                raise ValueError(f"face_uvs must have the shape of faces {f.shape}, got {fu.shape}")
            if fu.min() < 0 or fu.max() >= len(uv):
                raise ValueError(f"face_uvs index uvs outside [0, {len(uv)})")
            corner = uv[fu]
        layer = mesh.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", np.ascontiguousarray(corner, np.float32).reshape(-1))
    mesh.polygons.foreach_set("use_smooth", np.full(len(mesh.polygons), bool(smooth)))
    mesh.update()
    obj = bpy.data.objects.new("object", mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _empty_node_tree(owner):
    """(nodes, links) of a new material's or world's node tree, emptied of Blender's default nodes."""
    nodes, links = owner.node_tree.nodes, owner.node_tree.links
    for n in list(nodes):
        nodes.remove(n)
    return nodes, links


def _make_material(obj, m: PrincipledMaterial, *, albedo_aov: bool, has_uvs: bool):
    bpy = _bpy()
    mat = bpy.data.materials.new("material")
    nodes, links = _empty_node_tree(mat)
    out = nodes.new("ShaderNodeOutputMaterial")
    out.target = "CYCLES"
    out.name = "output"
    bsdf = nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.name = "Principled BSDF"
    bsdf.distribution = "GGX"
    bsdf.subsurface_method = m.subsurface_method
    inp = bsdf.inputs
    color = tuple(float(c) for c in _np(m.base_color, np.float64).reshape(-1))
    if len(color) != 3:
        raise ValueError(f"base_color must be linear RGB (3 values), got {color}")
    inp["Base Color"].default_value = (*color, 1.0)
    inp["Roughness"].default_value = float(m.roughness)
    inp["Metallic"].default_value = float(m.metallic)
    inp["Specular IOR Level"].default_value = float(m.specular_ior_level)
    inp["IOR"].default_value = 1.5
    inp["Subsurface Weight"].default_value = float(m.subsurface_weight)
    inp["Subsurface Radius"].default_value = tuple(float(r) for r in m.subsurface_radius)
    inp["Subsurface Scale"].default_value = float(m.subsurface_scale)
    inp["Coat Weight"].default_value = 0.0
    inp["Sheen Weight"].default_value = 0.0
    inp["Transmission Weight"].default_value = 0.0
    inp["Emission Strength"].default_value = 0.0
    inp["Alpha"].default_value = 1.0
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    colour_socket = None
    if m.texture is not None:
        if not has_uvs:
            raise ValueError("a texture needs uvs (per-vertex, or with face_uvs)")
        tex = nodes.new("ShaderNodeTexImage")
        tex.name = "texture"
        tex.image = _texture_image(m.texture)
        tex.interpolation = "Linear"
        tex.extension = "REPEAT"
        links.new(tex.outputs["Color"], inp["Base Color"])
        colour_socket = tex.outputs["Color"]
    if albedo_aov:
        # Albedo ground truth: a second material output that emits the base colour (texture or
        # base_color, linear) at strength 1; render() switches to it for an albedo-only pass.
        # (Not the Diffuse Color pass, which is base colour x (1 - metallic); and not a shader AOV:
        # the bpy 5.0.1 wheel writes no render pass but Combined, neither to write_still EXRs nor to
        # compositor File Output nodes, so an AOV cannot be read back.)
        emit = nodes.new("ShaderNodeEmission")
        emit.name = "albedo_emission"
        emit.inputs["Strength"].default_value = 1.0
        if colour_socket is not None:
            links.new(colour_socket, emit.inputs["Color"])
        else:
            emit.inputs["Color"].default_value = (*color, 1.0)
        aout = nodes.new("ShaderNodeOutputMaterial")
        aout.name = "albedo_output"
        aout.target = "CYCLES"
        links.new(emit.outputs["Emission"], aout.inputs["Surface"])
        aout.is_active_output = False
        out.is_active_output = True
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    return mat


def make_world(envmap):
    """A world lit only by ``envmap`` (EXR path or (H, W, 3) linear array, top row first) through an
    Environment Texture node with default mapping at strength 1; returns (world, environment node)."""
    bpy = _bpy()
    world = bpy.data.worlds.new("world")
    nodes, links = _empty_node_tree(world)
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
    bpy = _bpy()
    old = env_node.image
    if isinstance(envmap, (str, os.PathLike)):
        img = _load_image(envmap, _LINEAR_CS)
    else:
        arr = _np(envmap, np.float32)
        if arr.ndim != 3 or arr.shape[-1] != 3:
            raise ValueError(f"envmap must be an EXR path or an (H, W, 3) linear array, got shape {arr.shape}")
        if (arr < 0).any():
            raise ValueError("envmap has negative radiance")
        img = _image_from_array("envmap", arr, _LINEAR_CS)
    env_node.image = img
    if old is not None and old.users == 0:
        bpy.data.images.remove(old)


def configure_render(scene, settings: RenderSettings) -> None:
    """Apply ``settings`` to a bpy scene: Cycles on CPU (or GPU), fixed seed, Blackman-Harris filter, no
    light tree / guiding / caustic tricks, Standard view transform (linear output), 32-bit multilayer EXR
    output. Works on any scene (the one :func:`build_scene` makes, or one built by hand with bpy)."""
    settings.validate()
    st = settings
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x = r.resolution_y = int(st.resolution)
    if st.width is not None:
        r.resolution_x = int(st.width)
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = bool(st.film_transparent)
    r.use_persistent_data = True  # keep the BVH/images between the views of one scene
    r.use_compositing = False
    r.use_sequencer = False
    r.threads_mode = "FIXED" if st.threads else "AUTO"
    if st.threads:
        r.threads = int(st.threads)
    c = scene.cycles
    c.device = st.device
    c.samples = int(st.spp)
    c.use_adaptive_sampling = float(st.adaptive_threshold) > 0
    if c.use_adaptive_sampling:
        c.adaptive_threshold = float(st.adaptive_threshold)
        c.adaptive_min_samples = int(st.adaptive_min_samples)
    c.use_denoising = bool(st.denoise)
    if st.denoise:
        c.denoiser = "OPENIMAGEDENOISE"
        c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        c.denoising_prefilter = "ACCURATE"
        c.denoising_quality = "HIGH"
    c.use_light_tree = False
    c.use_guiding = False
    c.seed = int(st.seed)
    c.use_animated_seed = False
    c.pixel_filter_type = "BLACKMAN_HARRIS"
    c.filter_width = float(st.filter_width)
    c.max_bounces = int(st.max_bounces)
    c.diffuse_bounces = int(st.max_bounces)
    c.glossy_bounces = int(st.max_bounces)
    c.transmission_bounces = int(st.max_bounces)
    c.volume_bounces = 0
    c.transparent_max_bounces = 8
    c.blur_glossy = 0.0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = float(st.clamp_indirect)
    c.use_fast_gi = False
    c.use_camera_cull = False
    c.use_distance_cull = False
    c.texture_limit_render = "OFF"
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = False
    im = r.image_settings
    im.media_type = "MULTI_LAYER_IMAGE"
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"
    im.exr_codec = "NONE"
    if st.device == "GPU":
        _enable_gpu()


def _enable_gpu():
    bpy = _bpy()
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for backend in ("OPTIX", "CUDA", "HIP", "METAL", "ONEAPI"):
        try:
            prefs.compute_device_type = backend
        except TypeError:
            continue
        prefs.get_devices()
        gpus = [d for d in prefs.devices if d.type == backend]
        if gpus:
            for d in prefs.devices:
                d.use = d.type == backend
            return
    raise RuntimeError("device='GPU' but Cycles found no GPU backend; use device='CPU'")


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
    bpy = _bpy()
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
    mat = _make_material(obj, material, albedo_aov=settings.albedo_aov, has_uvs=uvs is not None)
    world, env = make_world(envmap)
    cam_data = bpy.data.cameras.new("camera")
    cam_data.type = "PERSP"
    cam_data.lens_unit = "FOV"
    cam_data.sensor_fit = "AUTO"
    cam_data.clip_start = 0.01
    cam_data.clip_end = 1.0e5
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    return CyclesScene(scene, obj, cam, mat, world, env, int(settings.resolution), bool(settings.albedo_aov),
                       settings=settings)


def set_camera(cs: CyclesScene, world_to_camera, fov) -> None:
    """Place the camera: ``world_to_camera`` (4, 4) in dibrpp's convention, ``fov`` in radians."""
    from mathutils import Matrix  # noqa: PLC0415  (ships with bpy)

    w2c = _np(world_to_camera, np.float64)
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


def _render_file(scene, path: Path) -> Path:
    """Render ``scene``'s active camera into the EXR ``path``; returns the path Blender wrote."""
    bpy = _bpy()
    path.parent.mkdir(parents=True, exist_ok=True)
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True, scene=scene.name)
    if not path.is_file() and Path(str(path) + ".exr").is_file():  # Blender appends a missing extension
        path = Path(str(path) + ".exr")
    return path


def render_still(scene=None, name: str = "still") -> np.ndarray:
    """Render the active camera of a bpy scene (default: the current one) set up by
    :func:`configure_render`; returns its Combined RGBA (H, W, 4) float32, linear, top row first."""
    scene = _bpy().context.scene if scene is None else scene
    path = _render_file(scene, Path(scratch_dir()) / f"{name}.exr")
    try:
        return read_render_exr(path)
    finally:
        path.unlink(missing_ok=True)


def _render_to(cs: CyclesScene, path: Path) -> Path:
    t0 = time.perf_counter()
    path = _render_file(cs.scene, path)
    cs.render_seconds += time.perf_counter() - t0
    cs.renders += 1
    return path


def _set_albedo_mode(cs: CyclesScene, on: bool) -> None:
    """Switch the material to its base-colour emission output, without bounces (and back)."""
    nodes = cs.material.node_tree.nodes
    nodes["albedo_output"].is_active_output = on
    nodes["output"].is_active_output = not on
    cs.material.cycles.emission_sampling = "NONE" if on else "AUTO"
    c = cs.scene.cycles
    keys = ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces", "use_denoising")
    if on:
        cs._saved_bounces = {k: getattr(c, k) for k in keys}
        for k in keys:
            setattr(c, k, 0 if k != "use_denoising" else False)  # the albedo is noise-free: never denoised
    else:
        for k, v in getattr(cs, "_saved_bounces", {}).items():
            setattr(c, k, v)


def render(cs: CyclesScene, exr_path=None) -> dict:
    """Render the current camera; returns {'rgba': (R, R, 4) float32 linear, top row first[, 'albedo']}.

    With ``albedo_aov`` the albedo is a second, cheap render of the same camera, samples and seed in
    which the object emits its linear base colour (no lighting, no bounces): a pixel holds the
    pixel-filtered base colour times coverage (premultiplied, 0 on the background), the same as a
    Cycles colour AOV would. ``exr_path``: keep Cycles' EXR of the shaded render there (else a
    temporary file that is deleted).
    """
    tmp = Path(cs.tmpdir)
    keep = exr_path is not None
    path = _render_to(cs, Path(exr_path) if keep else tmp / "render.exr")
    try:
        out = {"rgba": read_render_exr(path)}
    finally:
        if not keep and path.exists():
            path.unlink()
    if cs.albedo_aov:
        _set_albedo_mode(cs, True)
        try:
            apath = _render_to(cs, tmp / "albedo.exr")
            try:
                out["albedo"] = read_render_exr(apath)[..., :3]
            finally:
                if apath.exists():
                    apath.unlink()
        finally:
            _set_albedo_mode(cs, False)
    return out


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


def render_scene(verts, faces, *, world_to_camera, fov, envmap, material: PrincipledMaterial | None = None,
                 settings: RenderSettings | None = None, uvs=None, face_uvs=None, smooth=True, **params) -> dict:
    """Render one object under an environment map with Cycles, in one call; see the module docstring.

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
