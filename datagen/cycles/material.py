"""The surface: one Principled BSDF (GGX) in Cycles' own parameters, its colour texture, and the base-colour
emission output that renders the albedo ground truth."""
from __future__ import annotations

import os
from dataclasses import dataclass, fields

import numpy as np

from .blender import LINEAR_COLORSPACE, as_array, bpy_module, empty_node_tree, image_from_array, load_image

SUBSURFACE_METHODS = ("RANDOM_WALK", "RANDOM_WALK_SKIN", "BURLEY")
# Node names that render() switches between for the albedo pass.
SHADED_OUTPUT, ALBEDO_OUTPUT = "output", "albedo_output"


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
        if self.subsurface_method not in SUBSURFACE_METHODS:
            raise ValueError(f"subsurface_method must be one of {', '.join(SUBSURFACE_METHODS)}, "
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

    def base_rgb(self) -> tuple:
        """``base_color`` as three floats (ValueError otherwise)."""
        color = tuple(float(c) for c in as_array(self.base_color, np.float64).reshape(-1))
        if len(color) != 3:
            raise ValueError(f"base_color must be linear RGB (3 values), got {color}")
        return color


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def texture_image(texture):
    """bpy image for a colour texture: PNG path (sRGB, Cycles decodes) or float sRGB array."""
    if isinstance(texture, (str, os.PathLike)):
        return load_image(texture, "sRGB")
    arr = as_array(texture, np.float32)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"texture must be a PNG path or an (H, W, 3) sRGB array in [0, 1], got shape {arr.shape}")
    # Decode sRGB here with the same formula as dibrpp.conventions.srgb_to_linear (exact, no 8-bit
    # quantisation) and hand Cycles linear floats: identical to Cycles decoding an sRGB texture.
    return image_from_array("texture", srgb_to_linear(arr), LINEAR_COLORSPACE)


def _principled_bsdf(nodes, m: PrincipledMaterial):
    """The Principled BSDF node with every input the project does not use turned off."""
    bsdf = nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.name = "Principled BSDF"
    bsdf.distribution = "GGX"
    bsdf.subsurface_method = m.subsurface_method
    inp = bsdf.inputs
    inp["Base Color"].default_value = (*m.base_rgb(), 1.0)
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
    return bsdf


def _texture_node(nodes, links, texture, bsdf):
    """An image texture node feeding the BSDF's base colour; returns its colour socket."""
    tex = nodes.new("ShaderNodeTexImage")
    tex.name = "texture"
    tex.image = texture_image(texture)
    tex.interpolation = "Linear"
    tex.extension = "REPEAT"
    links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return tex.outputs["Color"]


def _albedo_output(nodes, links, colour_socket, base_rgb: tuple) -> None:
    """A second material output that emits the base colour (texture or base_color, linear) at strength 1;
    render() switches to it for an albedo-only pass.

    Not the Diffuse Color pass, which is base colour x (1 - metallic); and not a shader AOV: the bpy 5.0.1
    wheel writes no render pass but Combined, neither to write_still EXRs nor to compositor File Output
    nodes, so an AOV cannot be read back.
    """
    emit = nodes.new("ShaderNodeEmission")
    emit.name = "albedo_emission"
    emit.inputs["Strength"].default_value = 1.0
    if colour_socket is not None:
        links.new(colour_socket, emit.inputs["Color"])
    else:
        emit.inputs["Color"].default_value = (*base_rgb, 1.0)
    out = nodes.new("ShaderNodeOutputMaterial")
    out.name = ALBEDO_OUTPUT
    out.target = "CYCLES"
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    out.is_active_output = False


def make_material(obj, m: PrincipledMaterial, *, albedo_aov: bool, has_uvs: bool):
    """Give ``obj`` a new material holding ``m`` (and, with ``albedo_aov``, the albedo output)."""
    bpy = bpy_module()
    mat = bpy.data.materials.new("material")
    nodes, links = empty_node_tree(mat)
    out = nodes.new("ShaderNodeOutputMaterial")
    out.target = "CYCLES"
    out.name = SHADED_OUTPUT
    bsdf = _principled_bsdf(nodes, m)
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    colour_socket = None
    if m.texture is not None:
        if not has_uvs:
            raise ValueError("a texture needs uvs (per-vertex, or with face_uvs)")
        colour_socket = _texture_node(nodes, links, m.texture, bsdf)
    if albedo_aov:
        _albedo_output(nodes, links, colour_socket, m.base_rgb())
        out.is_active_output = True
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    return mat
