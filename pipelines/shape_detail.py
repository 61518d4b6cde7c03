"""A shape detail read from pixel-aligned image features (the structure the texture and the light were given).

The encoder's global shape comes from one 512-d code: a smooth car whose normals miss the breaks (hood,
windscreen) that the mirror directions depend on. :class:`PixelAlignedDetail` decodes the encoder's feature
pyramid back up to half the input's resolution (a U-Net's up path: every pixel's features carry the whole
image's context and its own neighbourhood; PIFu, Saito et al. ICCV 2019), looks each vertex of the global shape
up where it projects in the input view (its mirror vertex too: cars are mirror-symmetric, and the other side of
the car may face the camera when this one does not), and displaces it along its normal by a bounded amount.
A displacement along the normal changes the surface, not where its vertices sit on it. The displacements are
low-passed over the mesh (a few steps of averaging with the neighbours), and the detail reads the encoder's
features without training them: trained through the detail, the encoder got worse even on its training views
and even with the normals supervised; the low-pass alone did not mend that, the two together did
(docs/experiments.md, entry 20). It starts at zero: the global shape. A variant that lost (entry 20), kept as the
structure to measure at a larger compute budget.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dibrpp.camera import Cameras
from dibrpp.mesh import vertex_normals

from .model_input import input_grid

MAX_DISPLACEMENT = 3.0  # world units (objects span [-18, 18])
SMOOTHING_STEPS = 3  # each: a vertex's displacement halfway to its neighbours' mean
CODE = 32  # channels of the global code each vertex also sees


def _up_block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2, inplace=True))


class PixelAlignedDetail(nn.Module):
    """Per-vertex displacements along the normal from the input's pixel-aligned features."""

    def __init__(self, width: int, laplacian: torch.Tensor, code: int = 512):
        """``laplacian``: the template's uniform Laplacian (sparse (V, V), dibrpp.mesh.uniform_laplacian)."""
        super().__init__()
        step = torch.eye(laplacian.shape[0]) - 0.5 * laplacian.to_dense()
        self.register_buffer("smoothing", torch.linalg.matrix_power(step, SMOOTHING_STEPS), persistent=False)
        w = width
        # the up path: level 3 (8w, S/16) -> S/8 (+ level 2) -> S/4 (+ level 1) -> S/2 (+ stem)
        self.up = nn.ModuleList([_up_block(8 * w + 4 * w, 4 * w), _up_block(4 * w + 2 * w, 2 * w),
                                 _up_block(2 * w + w, w)])
        self.code = nn.Linear(code, CODE)
        seen = w + 4 + 1  # features, the input's colour and alpha, how squarely the vertex faces the camera
        self.mlp = nn.Sequential(nn.Linear(2 * seen + 3 + CODE, 128), nn.LeakyReLU(0.2, inplace=True),
                                 nn.Linear(128, 128), nn.LeakyReLU(0.2, inplace=True), nn.Linear(128, 1))
        nn.init.zeros_(self.mlp[-1].weight)  # the detail starts at zero: the global shape
        nn.init.zeros_(self.mlp[-1].bias)

    def features(self, levels: list[torch.Tensor]) -> torch.Tensor:
        """(B, w, S/2, S/2) features from the pyramid [stem, level 1, level 2, level 3] (finest first)."""
        x = levels[-1]
        for block, skip in zip(self.up, reversed(levels[:-1])):
            x = block(torch.cat([F.interpolate(x, size=skip.shape[-2:], mode="nearest"), skip], 1))
        return x

    def forward(self, verts: torch.Tensor, faces: torch.Tensor, mirror: torch.Tensor, template_dirs: torch.Tensor,
                images: torch.Tensor, levels: list[torch.Tensor], code: torch.Tensor,
                cameras: Cameras) -> torch.Tensor:
        """Each vertex's displacement (B, V, 3) from the global shape ``verts`` (given detached: the look-up is
        not a path for the global shape to learn through); ``mirror``: each vertex's mirror image about XZ."""
        b, v = verts.shape[:2]
        normals = vertex_normals(verts, faces)
        to_camera = F.normalize(cameras.centers.to(verts).unsqueeze(1) - verts, dim=-1)
        facing = (normals * to_camera).sum(-1, keepdim=True).clamp_min(0)
        grid = input_grid(verts, cameras).unsqueeze(2)  # (B, V, 1, 2)
        # the encoder's features read, not trained, by the detail: its per-vertex gradients would reach the
        # global code every other head reads (entry 20: through it even the supervised normals got worse)
        levels, code = [x.detach() for x in levels], code.detach()
        seen = torch.cat([F.grid_sample(x, grid, align_corners=False, padding_mode="zeros")
                          for x in (self.features(levels), images)], 1).squeeze(-1).mT  # (B, V, C)
        seen = torch.cat([seen * (facing > 0), facing], -1)
        x = torch.cat([seen, seen[:, mirror], template_dirs.expand(b, v, 3),
                       self.code(code).unsqueeze(1).expand(b, v, -1)], -1)
        d = self.smoothing @ (MAX_DISPLACEMENT * torch.tanh(self.mlp(x) / MAX_DISPLACEMENT))  # (B, V, 1)
        d = 0.5 * (d + d[:, mirror])  # symmetric, as the shape is
        return d * normals
