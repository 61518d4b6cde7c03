"""What the encoder predicts for a batch of images, and how it becomes the renderer's objects.

:class:`Prediction` holds the shape, texture, material and light the encoder predicted (light in the input camera's
frame, or its probe frame) and turns them into meshes, materials and world-frame lights; :func:`white_balance` keeps
a light's mean radiance grey. ``LIGHT_KINDS``: which light each shading method predicts.
"""
from __future__ import annotations

import math
import torch

from dibrpp.brdf import Material
from dibrpp.lights import EnvMap, SGLight, SHLight
from dibrpp.mesh import Meshes
from dibrpp.sg import sg_integral

from .light_probe import world_to_probe

LIGHT_KINDS = {"mc": "env", "sg": "sg", "sh": "sh", "sh-sg": "sg"}


def white_balance(light: dict, kind: str) -> dict:
    """Scale each colour channel so that the light's mean radiance over the sphere is grey."""
    if kind == "sg":
        total = sg_integral(light["sharpness"], light["amplitude"]).sum(1)  # (B, 3)
    elif kind == "sh":
        total = light["coeffs"][:, 0].clamp_min(1e-4)  # the DC term is the mean radiance (up to a constant)
    else:
        env_height = light["image"].shape[1]
        theta = (torch.arange(env_height, device=light["image"].device) + 0.5) * math.pi / env_height
        w = torch.sin(theta).view(1, -1, 1, 1)
        total = (light["image"] * w).sum((1, 2))
    gain = total.mean(-1, keepdim=True) / total.clamp_min(1e-8)  # (B, 3)
    keys = {"sg": ("amplitude",), "sh": ("coeffs",), "env": ("image", "sky", "sun_amplitude")}[kind]
    scale = lambda t: t * gain.view((-1,) + (1,) * (t.dim() - 2) + (3,))  # noqa: E731
    return {**light, **{key: scale(light[key]) for key in keys if key in light}}  # MC's probe sun: its parts alike


class Prediction:
    """What the encoder predicts for a batch of B images (``config``: the encoder's ModelConfig); converts to
    renderer objects."""

    def __init__(self, verts, texture, roughness, specular, metallic, light_params, config, template: Meshes,
                 facing: torch.Tensor | None = None, pixel_normals: torch.Tensor | None = None):
        self.verts, self.texture = verts, texture
        # (B, Ht, Wt): how squarely each texel faced the input camera (0: away); None for the global texture
        self.facing = facing
        # (B, S, S, 3): the probe's world-frame normals per input pixel (probe_normals "pixels"), else None
        self.pixel_normals = pixel_normals
        self.roughness, self.specular, self.metallic = roughness, specular, metallic
        self.light_params, self.config, self.template = light_params, config, template

    def meshes(self) -> Meshes:
        return self.template.with_verts(self.verts)

    def material(self) -> Material:
        return Material(albedo=self.texture, roughness=self.roughness, metallic=self.metallic,
                        specular=self.specular, wrap_u=True)

    def light(self, world_to_camera: torch.Tensor):
        """The predicted light in the world: it was predicted in the frame of the input camera whose
        world-to-camera transform is ``world_to_camera`` ((B, 4, 4) or (B, 3, 3)) (the probe head: in that
        camera's probe frame, light_probe.CAMERA_TO_PROBE)."""
        p = self.light_params
        frame = world_to_probe(world_to_camera) if self.config.light_head == "probe" else world_to_camera[:, :3, :3]
        kind = LIGHT_KINDS[self.config.shading]
        if kind == "sg":
            light = SGLight(p["axis"], p["sharpness"], p["amplitude"])
        elif kind == "sh":
            light = SHLight(p["coeffs"])
        else:
            light = EnvMap(p["image"])
        return light.in_frame(frame)

    def sky_and_sun(self, world_to_camera: torch.Tensor) -> tuple[EnvMap, SGLight] | None:
        """MC's probe sun apart from its sky (None for any other light): the sky's grid and the sun's SG lobe, in the
        world (:meth:`light` holds both on one grid). Training shades the sun in closed form and the sky by MC: with
        a few samples per pixel the MC estimate's gradient under-weights a compact source against the sky
        (docs/experiments.md, entry 28)."""
        p = self.light_params
        if "sun_amplitude" not in p:
            return None
        frame = world_to_probe(world_to_camera)
        sun = SGLight(p["sun_axis"].unsqueeze(1), p["sun_sharpness"], p["sun_amplitude"].unsqueeze(1))
        return EnvMap(p["sky"]).in_frame(frame), sun.in_frame(frame)

    def _replace(self, fn, light_params: dict | None = None) -> "Prediction":
        """A prediction with ``fn`` applied to every tensor (and the light's parameters replaced, if given)."""
        light = light_params if light_params is not None else {k: fn(v) for k, v in self.light_params.items()}
        optional = lambda t: None if t is None else fn(t)  # noqa: E731
        return Prediction(fn(self.verts), fn(self.texture), fn(self.roughness), fn(self.specular), fn(self.metallic),
                          light, self.config, self.template, optional(self.facing), optional(self.pixel_normals))

    def to(self, device) -> "Prediction":
        """The prediction with its tensors and template on ``device``."""
        moved = self._replace(lambda t: t.to(device))
        moved.template = self.template.to(device)
        return moved

    def detached(self) -> "Prediction":
        return self._replace(torch.Tensor.detach)

    def with_light(self, light_params: dict) -> "Prediction":
        return self._replace(lambda t: t, light_params)

    def select(self, idx) -> "Prediction":
        return self._replace(lambda t: t[idx])
