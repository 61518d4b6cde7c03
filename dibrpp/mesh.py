"""Triangle meshes: a batch of vertex sets sharing one topology, normals, template sphere, Laplacians."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class Meshes:
    """B meshes with the same faces (the encoder deforms one template; a loaded mesh is B = 1).

    verts: (B, V, 3) float; faces: (F, 3) long;
    uvs: optional (T, 2) texture coordinates (u right, v up, as in OBJ) and face_uvs: (F, 3) indices
    into uvs, so seams can split a vertex into several uv corners.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    uvs: torch.Tensor | None = None
    face_uvs: torch.Tensor | None = None

    def __post_init__(self):
        if self.verts.dim() == 2:
            self.verts = self.verts.unsqueeze(0)
        if self.verts.dim() != 3 or self.verts.shape[-1] != 3:
            raise ValueError(f"verts must be (B, V, 3), got {tuple(self.verts.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[-1] != 3:
            raise ValueError(f"faces must be (F, 3), got {tuple(self.faces.shape)}")
        self.faces = self.faces.long()
        if self.faces.numel() and (self.faces.min() < 0 or self.faces.max() >= self.verts.shape[1]):
            raise ValueError("faces index vertices that do not exist")
        if not torch.isfinite(self.verts).all():
            raise ValueError("mesh vertices contain NaN or Inf; clean the mesh (e.g. trimesh's remove_degenerate_faces)")
        if (self.uvs is None) != (self.face_uvs is None):
            raise ValueError("uvs and face_uvs come together")
        if self.face_uvs is not None:
            self.face_uvs = self.face_uvs.long()

    def __len__(self) -> int:
        return self.verts.shape[0]

    @property
    def has_uvs(self) -> bool:
        return self.uvs is not None

    def with_verts(self, verts: torch.Tensor) -> "Meshes":
        return Meshes(verts, self.faces, self.uvs, self.face_uvs)

    def to(self, device) -> "Meshes":
        opt = lambda t: None if t is None else t.to(device)  # noqa: E731
        return Meshes(self.verts.to(device), self.faces.to(device), opt(self.uvs), opt(self.face_uvs))

    def expand(self, batch: int) -> "Meshes":
        """Repeat a single mesh to a batch of ``batch`` (no copy)."""
        if len(self) == batch:
            return self
        if len(self) != 1:
            raise ValueError(f"cannot expand a batch of {len(self)} meshes to {batch}")
        return self.with_verts(self.verts.expand(batch, -1, -1))

    def face_normals(self, unit: bool = True) -> torch.Tensor:
        return face_normals(self.verts, self.faces, unit)

    def vertex_normals(self) -> torch.Tensor:
        return vertex_normals(self.verts, self.faces)


def face_normals(verts: torch.Tensor, faces: torch.Tensor, unit: bool = True) -> torch.Tensor:
    """(B, F, 3) face normals (counter-clockwise winding faces outwards); length 2*area if not unit."""
    v = verts[:, faces]  # (B, F, 3, 3)
    n = torch.linalg.cross(v[:, :, 1] - v[:, :, 0], v[:, :, 2] - v[:, :, 0], dim=-1)
    return torch.nn.functional.normalize(n, dim=-1, eps=1e-12) if unit else n


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) area-weighted vertex normals; isolated vertices get a zero-safe normal."""
    fn = face_normals(verts, faces, unit=False)
    n = torch.zeros_like(verts)
    for k in range(3):
        n = n.index_add(1, faces[:, k], fn)
    return torch.nn.functional.normalize(n, dim=-1, eps=1e-12)


def icosphere(subdivisions: int = 3, radius: float = 1.0, device=None) -> Meshes:
    """Template sphere with equirectangular UVs (642 vertices at 3 subdivisions, 2562 at 4).

    Faces that straddle the u seam get their own uv corners with u shifted past 1, so a texture
    sampled with wrap-around in u is continuous.
    """
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    verts = torch.tensor(ico.vertices, dtype=torch.float32)
    faces = torch.tensor(ico.faces, dtype=torch.long)
    d = torch.nn.functional.normalize(verts, dim=-1)
    u = 0.5 - torch.atan2(d[:, 1], d[:, 0]) / (2 * math.pi)
    v = 1 - torch.acos(d[:, 2].clamp(-1, 1)) / math.pi  # OBJ convention: v up
    corner_u, corner_v = u[faces].clone(), v[faces]
    # Seam: bring all three corners of a face to the same side of the wrap.
    span = corner_u.max(1).values - corner_u.min(1).values
    wrap = span > 0.5
    corner_u[wrap] = torch.where(corner_u[wrap] < 0.5, corner_u[wrap] + 1, corner_u[wrap])
    # Poles: u is undefined there; take the mean u of the face's other corners.
    pole = (d[faces][..., 2].abs() > 1 - 1e-6)
    if pole.any():
        others = (corner_u * (~pole)).sum(1, keepdim=True) / (~pole).sum(1, keepdim=True).clamp_min(1)
        corner_u = torch.where(pole, others.expand_as(corner_u), corner_u)
    uvs = torch.stack([corner_u, corner_v], -1).reshape(-1, 2)
    face_uvs = torch.arange(faces.shape[0] * 3).reshape(-1, 3)
    return Meshes(verts, faces, uvs, face_uvs).to(device)


def torus(major=0.7, minor=0.3, nu=48, nv=24) -> Meshes:
    """A closed, consistently wound torus around +Z, outward-facing (non-convex: its outline has
    T-junctions; the silhouette tests use it)."""
    u = torch.arange(nu) * 2 * math.pi / nu
    v = torch.arange(nv) * 2 * math.pi / nv
    uu, vv = torch.meshgrid(u, v, indexing="ij")
    ring = major + minor * torch.cos(vv)
    verts = torch.stack([ring * torch.cos(uu), ring * torch.sin(uu), minor * torch.sin(vv)], -1).reshape(-1, 3)
    i, j = torch.arange(nu)[:, None], torch.arange(nv)[None, :]
    a, b = i * nv + j, (i + 1) % nu * nv + j
    c, d = (i + 1) % nu * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = torch.cat([torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)])
    return Meshes(verts, faces)


def uniform_laplacian(faces: torch.Tensor, num_verts: int) -> torch.Tensor:
    """Sparse (V, V) uniform Laplacian L = I - D^-1 A; L @ verts is each vertex minus its neighbours' mean."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 0)
    e = torch.cat([e, e.flip(1)], 0)
    e = torch.unique(e, dim=0)
    deg = torch.zeros(num_verts, device=faces.device).index_add(0, e[:, 0], torch.ones(len(e), device=faces.device))
    vals = -1.0 / deg[e[:, 0]].clamp_min(1)
    idx = torch.cat([e.T, torch.arange(num_verts, device=faces.device).expand(2, -1)], 1)
    vals = torch.cat([vals, torch.ones(num_verts, device=faces.device)])
    return torch.sparse_coo_tensor(idx, vals, (num_verts, num_verts), check_invariants=False).coalesce()


def cotangent_laplacian(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Sparse (V, V) cotangent Laplacian of one mesh (verts (V, 3)): L_ij = -(cot a + cot b)/2, rows sum to 0."""
    v = verts[faces]  # (F, 3, 3)
    rows, cols, vals = [], [], []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        a, b = v[:, j] - v[:, i], v[:, k] - v[:, i]  # angle at corner i is opposite edge (j, k)
        cot = (a * b).sum(-1) / torch.linalg.cross(a, b, dim=-1).norm(dim=-1).clamp_min(1e-12)
        rows += [faces[:, j], faces[:, k]]
        cols += [faces[:, k], faces[:, j]]
        vals += [-0.5 * cot, -0.5 * cot]
    rows, cols, vals = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    n = verts.shape[0]
    diag = torch.zeros(n, dtype=verts.dtype, device=verts.device).index_add(0, rows, -vals)
    idx = torch.cat([torch.stack([rows, cols]), torch.arange(n, device=verts.device).expand(2, -1)], 1)
    return torch.sparse_coo_tensor(idx, torch.cat([vals, diag]), (n, n), check_invariants=False).coalesce()


def laplacian_smoothness(verts: torch.Tensor, laplacian: torch.Tensor) -> torch.Tensor:
    """Mean squared norm of L @ verts over vertices, averaged over the batch (verts (B, V, 3))."""
    lv = torch.stack([torch.sparse.mm(laplacian, v) for v in verts])
    return lv.pow(2).sum(-1).mean()
