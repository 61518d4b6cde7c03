"""Normals read from the input's pixels, for the light probe's mirror cue (variant ``pixel-normals``).

The probe head reads the light through the normals of the predicted surface. Where a metallic car mirrors the sun
(its rounded edges, where the surface turns ~23 degrees within a 64 x 64 pixel) those are 13-14 degrees off, and a
mirror doubles that; one view's global code does not predict them, even when told the GT normals
(docs/experiments.md, entries 19, 33, 34). :class:`PixelNormalNet` is a small U-Net on the input image that
predicts a normal per pixel, in the camera's frame (what a convolution can read off an image does not depend on
where the camera stands), trained against the GT mesh's normals in each input view: 3D supervision, which the
paper does not use. Only the probe reads these normals, detached (they learn from their supervision alone); the
mesh, its shading and every other head are the model's as before.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

LEARNING_RATE = 2e-3  # its own Adam rate: a separate model, trained by its own loss (entry 35 measured it at this)
INPUT_CEILING = 4.0  # encoder colour above this (radiance ~20) is a highlight whatever its value: bounded input


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2))


class PixelNormalNet(nn.Module):
    """(B, 4, S, S) encoder input -> (B, S, S, 3) world-frame unit normals, one per pixel (S a multiple of 8)."""

    def __init__(self, width: int = 16):
        super().__init__()
        w = width
        self.down = nn.ModuleList([_block(4, w), _block(w, 2 * w), _block(2 * w, 4 * w), _block(4 * w, 8 * w)])
        self.up = nn.ModuleList([_block(12 * w, 4 * w), _block(6 * w, 2 * w), _block(3 * w, w)])
        self.out = nn.Conv2d(w, 3, 1)

    def forward(self, images: torch.Tensor, world_to_camera: torch.Tensor) -> torch.Tensor:
        """``world_to_camera`` (B, 4, 4) or (B, 3, 3): each input view's camera."""
        x = torch.cat([images[:, :3].clamp(0, INPUT_CEILING), images[:, 3:]], 1)
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.avg_pool2d(x, 2))
            skips.append(x)
        x = skips.pop()
        for block in self.up:
            x = block(torch.cat([F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False), skips.pop()], 1))
        # camera frame (x right, y up, z towards the camera): starts facing the camera
        camera = F.normalize(self.out(x) + x.new_tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1), dim=1, eps=1e-12)
        rotation = world_to_camera[:, :3, :3].to(camera)
        return torch.einsum("bchw,bcd->bhwd", camera, rotation)  # n_world = R^T n_camera
