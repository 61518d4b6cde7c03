"""The template sphere the encoder deforms: its mirror symmetry and where each texel of its UV texture lies."""
from __future__ import annotations

import torch

from dibrpp import conventions
from dibrpp.mesh import Meshes


def mirror_index(verts: torch.Tensor) -> torch.Tensor:
    """(V,) index of each template vertex's mirror image under y -> -y (the icosphere is symmetric)."""
    mirrored = verts * verts.new_tensor([1.0, -1.0, 1.0])
    d, idx = torch.cdist(mirrored, verts, compute_mode="donot_use_mm_for_euclid_dist").min(1)
    if float(d.max()) > 1e-4 * float(verts.norm(dim=-1).max()):
        raise ValueError("the template is not mirror-symmetric about the XZ plane")
    return idx


def texel_barycentrics(template: Meshes, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For each texel of an equirect (height, width) texture on the template sphere: the face its
    direction hits and the barycentrics, so texel positions follow any deformation of the template."""
    d = conventions.equirect_directions(height, width).reshape(-1, 3)  # texel centre -> direction (Blender's mapping)
    tri = template.verts[0][template.faces]  # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    # ray o=0, dir d against every face (Moller-Trumbore), the nearest hit with barycentrics >= 0
    e1, e2 = b - a, c - a
    p = torch.linalg.cross(d[:, None], e2[None], dim=-1)  # (T, F, 3)
    det = (p * e1[None]).sum(-1)
    inv = 1.0 / torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    s = -a[None]
    u = (s * p).sum(-1) * inv
    q = torch.linalg.cross(s, e1[None].expand_as(s), dim=-1)
    v = (d[:, None] * q).sum(-1) * inv
    t = (e2[None] * q).sum(-1) * inv
    ok = (u >= -1e-5) & (v >= -1e-5) & (u + v <= 1 + 1e-5) & (t > 0)
    face = torch.where(ok, t, torch.full_like(t, float("inf"))).argmin(1)
    rows = torch.arange(d.shape[0])
    uu, vv = u[rows, face].clamp(0, 1), v[rows, face].clamp(0, 1)
    bary = torch.stack([1 - uu - vv, uu, vv], -1)
    return face, bary / bary.sum(-1, keepdim=True)
