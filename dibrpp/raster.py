"""DIB-R style rasterization in pure torch (CPU and CUDA alike).

Covered pixels: hard visibility (nearest surface wins), perspective-correct barycentrics that carry
gradients to the vertex positions. Uncovered pixels: the soft silhouette
``1 - prod_k (1 - exp(-d_k^2 / sigma))`` over the faces within ``soft_radius`` (NDC) of the pixel.

Scaling: faces are expanded into (face, pixel) candidate pairs over their screen bounding boxes, so
work and memory grow with the covered area plus the number of faces, never with their product.
All candidate enumeration and the depth test run without autograd; only the winning pairs are
recomputed differentiably.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .camera import Cameras
from .mesh import Meshes

NEAR_DEPTH = 1e-4  # faces with a vertex closer than this (or behind the camera) are dropped


@dataclass
class RasterSettings:
    sigma: float = 1.0 / 7000.0  # soft-silhouette width in NDC^2 (DIB-R's value)
    soft_radius: float = 0.02  # faces farther than this from a pixel (NDC) do not touch its soft mask
    soft: bool = True  # compute the soft silhouette (needed for silhouette gradients)
    # Skip faces wound clockwise on screen. Exact and ~2x faster for closed, consistently wound
    # meshes (the template sphere); keep False for meshes of unknown winding.
    cull_backfaces: bool = False


@dataclass
class Fragments:
    """What the rasterizer hands to the shaders.

    Dense views are (B, H, W, ...); the packed views list only the N covered pixels, which is what
    shading works on: ``pix`` are flat indices into B*H*W, ``batch`` their image index.
    """

    face_idx: torch.Tensor  # (B, H, W) long, -1 where nothing is covered
    mask: torch.Tensor  # (B, H, W) float, hard coverage
    soft_mask: torch.Tensor  # (B, H, W) float, 1 on covered pixels, soft silhouette elsewhere
    depth: torch.Tensor  # (B, H, W) view depth, 0 where uncovered (differentiable)
    pix: torch.Tensor  # (N,) flat pixel index of covered pixels
    batch: torch.Tensor  # (N,) image index of covered pixels
    pix_face: torch.Tensor  # (N,) visible face
    bary: torch.Tensor  # (N, 3) perspective-correct barycentrics (differentiable)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.face_idx.shape)

    def interpolate(self, values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Packed (N, C) interpolation of per-corner values.

        values: (B, T, C) per image or (T, C) shared; index: (F, 3) rows of ``values`` at each face
        corner (the mesh faces for per-vertex values, face_uvs for UVs).
        """
        corners = index[self.pix_face]  # (N, 3)
        if values.dim() == 3:
            v = values[self.batch.unsqueeze(1), corners]  # (N, 3, C)
        else:
            v = values[corners]
        return (v * self.bary.unsqueeze(-1)).sum(1)

    def to_image(self, packed: torch.Tensor, background: float = 0.0) -> torch.Tensor:
        """Scatter packed (N, C) values into a dense (B, H, W, C) image."""
        b, h, w = self.shape
        out = packed.new_full((b * h * w, packed.shape[-1]), background)
        out = out.index_put((self.pix,), packed)
        return out.view(b, h, w, -1)


def _face_pairs(lo: torch.Tensor, hi: torch.Tensor, width: int, height: int):
    """Enumerate (face, pixel) pairs over inclusive integer pixel boxes lo/hi (M, 2) as (col, row).

    Returns (owner index into the M boxes, col, row) for every pixel of every box.
    """
    lo = lo.clamp_min(0)
    hi = torch.stack([hi[:, 0].clamp_max(width - 1), hi[:, 1].clamp_max(height - 1)], 1)
    size = (hi - lo + 1).clamp_min(0)
    counts = size[:, 0] * size[:, 1]
    owner = torch.repeat_interleave(torch.arange(len(counts), device=lo.device), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=lo.device) - start[owner]
    box_w = size[owner, 0].clamp_min(1)
    col = lo[owner, 0] + local % box_w
    row = lo[owner, 1] + local // box_w
    return owner, col, row


def _edge_barycentrics(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """Screen-space barycentrics of points p (..., 2) in triangles (a, b, c); also the signed area."""
    area = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])
    w0 = (b[..., 0] - p[..., 0]) * (c[..., 1] - p[..., 1]) - (b[..., 1] - p[..., 1]) * (c[..., 0] - p[..., 0])
    w1 = (c[..., 0] - p[..., 0]) * (a[..., 1] - p[..., 1]) - (c[..., 1] - p[..., 1]) * (a[..., 0] - p[..., 0])
    safe = torch.where(area.abs() < 1e-20, torch.full_like(area, 1e-20), area)
    b0, b1 = w0 / safe, w1 / safe
    return torch.stack([b0, b1, 1 - b0 - b1], -1), area


def _segment_dist2(p, a, b):
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-20)
    q = a + t.clamp(0, 1).unsqueeze(-1) * ab
    return ((p - q) ** 2).sum(-1)


def _triangle_dist2(p, tri):
    """Squared distance (N,) from points p (N, 2) to the boundary of triangles tri (N, 3, 2)."""
    d = torch.stack([_segment_dist2(p, tri[:, i], tri[:, (i + 1) % 3]) for i in range(3)], -1)
    return d.min(-1).values


def rasterize(meshes: Meshes, cameras: Cameras, settings: RasterSettings | None = None) -> Fragments:
    """Rasterize B meshes (or one mesh broadcast) with B cameras into :class:`Fragments`."""
    settings = settings or RasterSettings()
    meshes = meshes.expand(len(cameras))
    if len(meshes) != len(cameras):
        raise ValueError(f"{len(meshes)} meshes for {len(cameras)} cameras")
    ndc, depth = cameras.project(meshes.verts)  # (B, V, 2), (B, V)
    faces = meshes.faces
    bsz, res = len(cameras), cameras.resolution
    h = w = res
    device = ndc.device
    n_faces = faces.shape[0]

    with torch.no_grad():
        tri_ndc = ndc[:, faces]  # (B, F, 3, 2)
        tri_z = depth[:, faces]  # (B, F, 3)
        px = torch.stack([(tri_ndc[..., 0] + 1) * 0.5 * w - 0.5, (1 - tri_ndc[..., 1]) * 0.5 * h - 0.5], -1)
        area = ((px[..., 1, 0] - px[..., 0, 0]) * (px[..., 2, 1] - px[..., 0, 1])
                - (px[..., 1, 1] - px[..., 0, 1]) * (px[..., 2, 0] - px[..., 0, 0]))
        valid = (tri_z > NEAR_DEPTH).all(-1) & (area.abs() > 1e-10) & torch.isfinite(px).all(-1).all(-1)
        if settings.cull_backfaces:
            valid &= area < 0  # counter-clockwise in NDC (y up) is clockwise in pixel rows (y down)
        vb, vf = valid.nonzero(as_tuple=True)  # valid (image, face) pairs
        vpx = px[vb, vf]  # (M, 3, 2) pixel-space vertices (pixel centres at integers)
        lo = torch.ceil(vpx.amin(1)).long()
        hi = torch.floor(vpx.amax(1)).long()
        owner, col, row = _face_pairs(lo, hi, w, h)
        p = torch.stack([col, row], -1).to(vpx.dtype)
        bary_s, _ = _edge_barycentrics(p, vpx[owner, 0], vpx[owner, 1], vpx[owner, 2])
        inside = (bary_s >= -1e-6).all(-1)
        owner, bary_s = owner[inside], bary_s[inside]
        pix = vb[owner] * (h * w) + row[inside] * w + col[inside]
        inv_z = (bary_s / tri_z[vb[owner], vf[owner]]).sum(-1)
        z = 1.0 / inv_z
        # depth test: nearest z per pixel, ties broken by the lowest face index
        zmin = torch.full((bsz * h * w,), float("inf"), device=device, dtype=z.dtype)
        zmin = zmin.scatter_reduce(0, pix, z, "amin")
        front = z <= zmin[pix]
        fid = torch.full((bsz * h * w,), n_faces, device=device, dtype=torch.long)
        fid = fid.scatter_reduce(0, pix[front], vf[owner[front]], "amin")
        covered = (fid < n_faces).nonzero(as_tuple=True)[0]
        win_face = fid[covered]
        win_batch = covered // (h * w)

    # Differentiable barycentrics of the winners (screen space, then perspective-correct).
    tri = ndc[win_batch.unsqueeze(1), faces[win_face]]  # (N, 3, 2)
    tz = depth[win_batch.unsqueeze(1), faces[win_face]]  # (N, 3)
    rem = covered % (h * w)
    centre = torch.stack([(2 * (rem % w) + 1).to(ndc.dtype) / w - 1, 1 - (2 * (rem // w) + 1).to(ndc.dtype) / h], -1)
    bary_screen, _ = _edge_barycentrics(centre, tri[:, 0], tri[:, 1], tri[:, 2])
    persp = bary_screen / tz
    inv_depth = persp.sum(-1, keepdim=True)
    bary = persp / inv_depth

    face_idx = torch.full((bsz * h * w,), -1, device=device, dtype=torch.long).index_put((covered,), win_face)
    mask = torch.zeros(bsz * h * w, device=device, dtype=ndc.dtype).index_put((covered,), torch.ones_like(win_face, dtype=ndc.dtype))
    depth_img = torch.zeros(bsz * h * w, device=device, dtype=ndc.dtype).index_put((covered,), (1.0 / inv_depth).squeeze(-1))

    if settings.soft:
        soft = _soft_silhouette(ndc, faces, vb, vf, vpx, mask, settings, bsz, h, w)
    else:
        soft = mask
    shape = (bsz, h, w)
    return Fragments(face_idx.view(shape), mask.view(shape), soft.view(shape), depth_img.view(shape),
                     covered, win_batch, win_face, bary)


def _soft_silhouette(ndc, faces, vb, vf, vpx, mask, settings: RasterSettings, bsz, h, w):
    """Soft mask: 1 on covered pixels, 1 - prod(1 - exp(-d^2/sigma)) over nearby faces elsewhere."""
    radius_px = settings.soft_radius * 0.5 * w
    with torch.no_grad():
        lo = torch.ceil(vpx.amin(1) - radius_px).long()
        hi = torch.floor(vpx.amax(1) + radius_px).long()
        # Only faces whose reach contains an uncovered pixel matter: count them with a summed-area table.
        empty = (mask.view(bsz, h, w) == 0).to(torch.int32)
        sat = torch.nn.functional.pad(empty.cumsum(1).cumsum(2), (1, 0, 1, 0))
        c0, r0 = lo[:, 0].clamp(0, w), lo[:, 1].clamp(0, h)
        c1, r1 = (hi[:, 0] + 1).clamp(0, w), (hi[:, 1] + 1).clamp(0, h)
        n_empty = sat[vb, r1, c1] - sat[vb, r0, c1] - sat[vb, r1, c0] + sat[vb, r0, c0]
        reach = (n_empty > 0).nonzero(as_tuple=True)[0]
        vb, vf, vpx, lo, hi = vb[reach], vf[reach], vpx[reach], lo[reach], hi[reach]
        owner, col, row = _face_pairs(lo, hi, w, h)
        pix = vb[owner] * (h * w) + row * w + col
        keep = mask[pix] == 0
        owner, col, row, pix = owner[keep], col[keep], row[keep], pix[keep]
        p = torch.stack([col, row], -1).to(vpx.dtype)
        d2_px = _triangle_dist2(p, vpx[owner])
        near = d2_px <= radius_px ** 2
        owner, col, row, pix = owner[near], col[near], row[near], pix[near]
    centre = torch.stack([(2 * col + 1).to(ndc.dtype) / w - 1, 1 - (2 * row + 1).to(ndc.dtype) / h], -1)
    tri = ndc[vb[owner].unsqueeze(1), faces[vf[owner]]]  # (P, 3, 2) differentiable
    d2 = _triangle_dist2(centre, tri)
    prob = torch.exp(-d2 / settings.sigma).clamp_max(1 - 1e-6)
    log_miss = torch.zeros(bsz * h * w, device=ndc.device, dtype=ndc.dtype).index_add(0, pix, torch.log1p(-prob))
    return torch.where(mask > 0, mask, 1 - torch.exp(log_miss))


def sample_texture(texture: torch.Tensor, uv: torch.Tensor, batch: torch.Tensor, wrap_u: bool = False) -> torch.Tensor:
    """Bilinear, differentiable lookup of texture (B, Ht, Wt, C) at uv (N, 2) (OBJ convention: v up).

    ``batch`` (N,) selects each sample's texture (use zeros for a single texture). Edges clamp;
    ``wrap_u`` wraps columns (the template sphere's seam).
    """
    _, th, tw, _ = texture.shape
    x = uv[:, 0] * tw - 0.5
    y = (1 - uv[:, 1]) * th - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0).unsqueeze(-1), (y - y0).unsqueeze(-1)
    x0, y0 = x0.long(), y0.long()

    def col(i):
        return i % tw if wrap_u else i.clamp(0, tw - 1)

    def row(i):
        return i.clamp(0, th - 1)

    t00 = texture[batch, row(y0), col(x0)]
    t01 = texture[batch, row(y0), col(x0 + 1)]
    t10 = texture[batch, row(y0 + 1), col(x0)]
    t11 = texture[batch, row(y0 + 1), col(x0 + 1)]
    return (t00 * (1 - fx) + t01 * fx) * (1 - fy) + (t10 * (1 - fx) + t11 * fx) * fy
