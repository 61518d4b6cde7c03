"""The silhouettes that :func:`dibrpp.raster.rasterize` adds to hard coverage, as functions of tensors.

* :func:`soft_silhouette`: DIB-R's soft mask ``1 - prod_k (1 - exp(-d_k^2 / w^2))`` over the faces near an
  uncovered pixel (d in pixels); 1 on covered pixels.
* :func:`antialiased_coverage`: the image alpha, i.e. the coverage of the front-most geometry filtered by
  Cycles' Blackman-Harris pixel filter: each pixel within the filter's reach of the outline takes the
  signed distance of its centre to the nearest outline edge through the filter's 1D edge response
  (:func:`edge_response`). Differentiable w.r.t. the outline's vertex positions.
* :func:`nearest_covered`: the covered pixel whose colour an uncovered pixel of the antialiased outline takes.

Inputs are pixel-space vertices (pixel centres at integers, rows down), flat (B*H*W,) masks, and the
valid (image, face) pairs of the rasterizer. Candidate search runs without autograd; only the winning
pairs are recomputed differentiably.
"""
from __future__ import annotations

import torch

from .screen import box_pixel_pairs, gather_batched, take, triangle_dist2

# Blackman-Harris window a0 - a1 cos(2 pi t) + a2 cos(4 pi t) - a3 cos(6 pi t) on t in [0, 1].
_BH = (0.35875, 0.48829, 0.14128, 0.01168)
_SPAN_MARGIN_PX = 0.75  # how far past the uncovered pixels' nearest points an outline edge still counts
# neighbours within a 5 x 5 window, nearest first
_NEIGHBOURS = sorted(((dy, dx) for dy in range(-2, 3) for dx in range(-2, 3) if dy or dx), key=lambda o: (o[0] ** 2 + o[1] ** 2, o))


def soft_silhouette(vpix, faces, vb, vf, vpx, mask, soft_width_px: float, soft_radius_px: float, bsz, h, w):
    """Soft mask: 1 on covered pixels, 1 - prod(1 - exp(-d^2/w^2)) over nearby faces elsewhere (d, w in pixels).

    vpix (B, V, 2) differentiable vertices; vb, vf, vpx: the valid (image, face) pairs and their detached
    pixel-space corners (M, 3, 2); mask: flat hard coverage. Faces farther than ``soft_radius_px`` do not count.
    """
    radius_px = soft_radius_px
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
        vb, vf, vpx, lo, hi = take(reach, vb, vf, vpx, lo, hi)
        owner, col, row = box_pixel_pairs(lo, hi, w, h)
        pix = vb[owner] * (h * w) + row * w + col
        keep = mask[pix] == 0
        owner, col, row, pix = take(keep, owner, col, row, pix)
        p = torch.stack([col, row], -1).to(vpx.dtype)
        d2_px = triangle_dist2(p, vpx.index_select(0, owner))
        near = d2_px <= radius_px ** 2
        owner, col, row, pix = take(near, owner, col, row, pix)
    centre = torch.stack([col, row], -1).to(vpix.dtype)
    tri = gather_batched(vpix, vb[owner], faces.index_select(0, vf[owner]))  # (P, 3, 2) differentiable, pixels
    d2 = triangle_dist2(centre, tri)
    prob = torch.exp(-d2 / soft_width_px ** 2).clamp_max(1 - 1e-6)
    log_miss = torch.zeros(bsz * h * w, device=vpix.device, dtype=vpix.dtype).index_add(0, pix, torch.log1p(-prob))
    return torch.where(mask > 0, mask, 1 - torch.exp(log_miss))


def edge_response(s: torch.Tensor, filter_width: float = 1.5) -> torch.Tensor:
    """Filtered coverage of a pixel whose centre lies ``s`` pixels inside a straight edge.

    Cycles' Blackman-Harris pixel filter of ``filter_width`` w spans 2w pixels and is separable; across
    an axis-aligned edge its response is the filter's CDF, in closed form below (monotone, smooth,
    0 at s <= -w, 1/2 at s = 0, 1 at s >= w). For edges at other angles the exact response (the CDF
    of the filter projected on the edge normal) differs from this by at most 0.004.
    """
    a0, a1, a2, a3 = _BH
    t = (s / (2 * filter_width) + 0.5).clamp(0, 1)
    x = 2 * torch.pi * t
    return t - (a1 * torch.sin(x) - a2 / 2 * torch.sin(2 * x) + a3 / 3 * torch.sin(3 * x)) / (2 * torch.pi * a0)


def mesh_edges(faces: torch.Tensor, num_verts: int):
    """Unique undirected edges (E, 2) and, per face, the edge index of its sides (F, 3): side i joins corners i, i+1."""
    a, b = faces, faces.roll(-1, 1)
    key = torch.minimum(a, b) * num_verts + torch.maximum(a, b)
    uniq, inverse = torch.unique(key.reshape(-1), return_inverse=True)
    return torch.stack([uniq // num_verts, uniq % num_verts], 1), inverse.view(-1, 3)


def argmin_by(key: torch.Tensor, value: torch.Tensor, size: int) -> torch.Tensor:
    """Indices of the entries with the smallest ``value`` for each distinct ``key`` in [0, size) (ties: first)."""
    n = value.numel()
    best = torch.full((size,), float("inf"), device=value.device, dtype=value.dtype)
    best = best.scatter_reduce(0, key, value, "amin")
    cand = (value <= best.index_select(0, key)).nonzero(as_tuple=True)[0]
    first = torch.full((size,), n, device=value.device, dtype=torch.long)
    first = first.scatter_reduce(0, key.index_select(0, cand), cand, "amin")
    return first[first < n]


def contour_edges(face_edges: torch.Tensor, valid: torch.Tensor, area: torch.Tensor, n_edges: int):
    """(image, edge) index pairs of each image's contour edges: edges with one valid face, or whose valid
    faces are wound both ways on screen (front and back), or non-manifold ones.

    face_edges (F, 3) from :func:`mesh_edges`; valid, area (B, F): the faces that rasterize and their signed
    screen areas."""
    bsz = valid.shape[0]
    pos = (valid & (area > 0)).to(torch.int32)
    neg = (valid & (area < 0)).to(torch.int32)
    idx = face_edges.reshape(-1)
    n_pos = torch.zeros(bsz, n_edges, dtype=torch.int32, device=valid.device).index_add_(1, idx, pos.repeat_interleave(3, 1))
    n_neg = torch.zeros(bsz, n_edges, dtype=torch.int32, device=valid.device).index_add_(1, idx, neg.repeat_interleave(3, 1))
    n_valid = n_pos + n_neg
    contour = (n_valid == 1) | (n_valid > 2) | ((n_pos > 0) & (n_neg > 0))
    return contour.nonzero(as_tuple=True)


def _pixels_near_segments(seg: torch.Tensor, seg_image: torch.Tensor, reach: float, h: int, w: int):
    """(segment, pixel) pairs closer than ``reach`` pixels, for segments seg (M, 2, 2) of images seg_image (M,).

    Returns the segment index, flat pixel index, pixel centre (P, 2), the parameter along the segment of the
    centre's projection on its line (unclamped) and the squared distance to the segment."""
    lo = torch.ceil(seg.amin(1) - reach).long()
    hi = torch.floor(seg.amax(1) + reach).long()
    owner, col, row = box_pixel_pairs(lo, hi, w, h)
    p = torch.stack([col, row], -1).to(seg.dtype)
    seg_o = seg.index_select(0, owner)
    a, ab = seg_o[:, 0], seg_o[:, 1] - seg_o[:, 0]
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-20)
    d2 = ((p - a - t.clamp(0, 1).unsqueeze(-1) * ab) ** 2).sum(-1)
    near = d2 < reach ** 2
    owner, col, row, p, t, d2 = take(near, owner, col, row, p, t, d2)
    pix = seg_image.index_select(0, owner) * (h * w) + row * w + col
    return owner, pix, p, t, d2


def _nearest_seen_foot(length, o_owner, o_t, i_owner, i_t, offset: float):
    """For each covered (pixel, edge) pair (i_owner, i_t), the nearest point of the same edge where that edge
    is the nearest edge of an uncovered pixel (o_owner, o_t), found by one sorted search over the keys
    edge x stride + arc length. Returns (found on the same edge, its edge parameter ``foot``, the edge's length)."""
    stride = float(length.max()) + 2 * offset + 1
    seen, _ = (o_owner.double() * stride + o_t.double() * length.index_select(0, o_owner) + offset).sort()
    i_len = length.index_select(0, i_owner)
    base = i_owner.double() * stride + offset
    key = base + i_t.double() * i_len
    j = torch.searchsorted(seen, key)
    lo_key, hi_key = seen.index_select(0, (j - 1).clamp_min(0)), seen.index_select(0, j.clamp_max(len(seen) - 1))
    near_key = torch.where((key - lo_key).abs() < (hi_key - key).abs(), lo_key, hi_key)
    same_edge = (near_key - base).abs() <= i_len + 2 * offset
    return same_edge, (near_key - base) / i_len, i_len


def _visible_spans(seg, o_owner, o_t, i_pix, i_owner, i_p, i_t, reach: float, size: int):
    """The outline edge of each covered pixel within reach, restricted to its visible span.

    Covered pixels see an edge only where it bounds the uncovered region: near the points where it is the
    nearest edge of an uncovered pixel. Each covered (pixel, edge) pair uses the part of the edge within
    ``_SPAN_MARGIN_PX`` of the nearest such point, so that the hidden continuation of an edge past a
    T-junction does not darken the interior; a pixel then keeps its nearest such span. Returns
    (pixel, edge, centre, span start, span end) per covered pixel, spans as edge parameters in [0, 1].
    """
    if not (o_owner.numel() and i_pix.numel()):
        return i_pix[:0], i_owner[:0], i_p[:0], i_t[:0], i_t[:0]
    length = (seg[:, 1] - seg[:, 0]).norm(dim=-1).clamp_min(1e-10).double()
    same_edge, foot, i_len = _nearest_seen_foot(length, o_owner, o_t, i_owner, i_t, 2 * (reach + _SPAN_MARGIN_PX))
    i_pix, i_owner, i_p, i_t, i_len, foot = take(same_edge, i_pix, i_owner, i_p, i_t, i_len, foot)
    margin = _SPAN_MARGIN_PX / i_len
    t_lo, t_hi = (foot - margin).clamp(0, 1).to(i_t.dtype), (foot + margin).clamp(0, 1).to(i_t.dtype)
    clip = torch.minimum(torch.maximum(i_t, t_lo), t_hi)
    i_seg = seg.index_select(0, i_owner)
    d2_in = ((i_p - i_seg[:, 0] - clip.unsqueeze(-1) * (i_seg[:, 1] - i_seg[:, 0])) ** 2).sum(-1)
    i_pix, i_owner, i_p, t_lo, t_hi, d2_in = take(d2_in < reach ** 2, i_pix, i_owner, i_p, t_lo, t_hi, d2_in)
    return take(argmin_by(i_pix, d2_in, size), i_pix, i_owner, i_p, t_lo, t_hi)


def _distance_to_span(centre, a, b, span_lo, span_hi):
    """Distance (P,) from points centre (P, 2) to the span [span_lo, span_hi] (edge parameters) of segments
    [a, b]: to the line inside the span, to the span's nearest end outside. Differentiable w.r.t. a and b."""
    ab, ap = b - a, centre - a
    len2 = (ab * ab).sum(-1)
    t = (ap * ab).sum(-1) / len2.clamp_min(1e-20)
    line = (ab[:, 0] * ap[:, 1] - ab[:, 1] * ap[:, 0]).abs() / len2.clamp_min(1e-20).sqrt()
    end = a + torch.minimum(torch.maximum(t.detach(), span_lo), span_hi).unsqueeze(-1) * ab
    point = ((centre - end) ** 2).sum(-1).clamp_min(1e-20).sqrt()
    return torch.where((t > span_lo) & (t < span_hi), line, point)


def antialiased_coverage(vpix, faces, valid, area, mask, filter_width: float, bsz, h, w):
    """Anti-aliased coverage: the edge response of the signed distance to the nearest outline edge.

    Outline candidates are the :func:`contour_edges` of each image. An uncovered pixel's distance to the
    nearest contour edge is its exact distance to the covered region (the region's boundary lies on
    contour edges). A covered pixel's distance to the outline is that to the nearest contour edge,
    restricted to the span where that edge bounds the uncovered region (:func:`_visible_spans`). A pixel
    near two outline edges (a corner, a sliver) sees only the nearer one. Pixels beyond the filter's reach
    keep the hard mask.

    vpix (B, V, 2) differentiable pixel-space vertices; valid, area (B, F); mask: flat (B*H*W,) hard coverage.
    Returns the flat (B*H*W,) coverage, and the flat indices of the uncovered pixels it reaches.
    """
    reach = float(filter_width)
    edges, face_edges = mesh_edges(faces, vpix.shape[1])
    with torch.no_grad():
        cb, ce = contour_edges(face_edges, valid, area, edges.shape[0])
        seg = gather_batched(vpix.detach(), cb, edges.index_select(0, ce))  # (M, 2, 2)
        owner, pix, p, t, d2 = _pixels_near_segments(seg, cb, reach, h, w)
        inside = mask.index_select(0, pix) > 0
        size = bsz * h * w
        # uncovered pixels: the nearest contour edge (its distance is the distance to the covered region)
        o_pix, o_owner, o_p, o_t, o_d2 = take(~inside, pix, owner, p, t, d2)
        o_pix, o_owner, o_p, o_t = take(argmin_by(o_pix, o_d2, size), o_pix, o_owner, o_p, o_t)
        i_pix, i_owner, i_p, t_lo, t_hi = _visible_spans(seg, o_owner, o_t, *take(inside, pix, owner, p, t), reach, size)
        n_out = len(o_pix)
        win_owner, win_pix, centre = torch.cat([o_owner, i_owner]), torch.cat([o_pix, i_pix]), torch.cat([o_p, i_p])
        span_lo = torch.cat([torch.zeros_like(o_t), t_lo])
        span_hi = torch.cat([torch.ones_like(o_t), t_hi])
        sign = torch.cat([-torch.ones_like(o_t), torch.ones_like(t_lo)]).to(vpix.dtype)
    # differentiable signed distance (pixels) of each reached pixel centre to its outline edge's span
    ends = gather_batched(vpix, cb[win_owner], edges.index_select(0, ce[win_owner]))  # (P, 2, 2)
    dist = _distance_to_span(centre, ends[:, 0], ends[:, 1], span_lo, span_hi)
    alpha = edge_response(sign * dist, filter_width)
    coverage = mask.index_put((win_pix,), alpha)
    reached = win_pix[:n_out][alpha[:n_out].detach() > 0]
    return coverage, reached


def _nearest_in_window(pix: torch.Tensor, packed: torch.Tensor, offsets, h: int, w: int):
    """First entry >= 0 of the flat image ``packed`` at ``offsets`` (dy, dx) around flat pixels ``pix``; -1 if none."""
    img, rem = pix // (h * w), pix % (h * w)
    row, col = rem // w, rem % w
    off = torch.tensor(offsets, device=pix.device)
    r, c = row.unsqueeze(1) + off[:, 0], col.unsqueeze(1) + off[:, 1]
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    nb = packed[img.unsqueeze(1) * (h * w) + r.clamp(0, h - 1) * w + c.clamp(0, w - 1)]
    nb = torch.where(inside, nb, torch.full_like(nb, -1))
    first = (nb >= 0).to(torch.int8).argmax(1, keepdim=True)
    return nb.gather(1, first).squeeze(1)


def nearest_covered(edge_pix, covered, bsz, h, w):
    """For uncovered pixels ``edge_pix``, the packed index of the nearest covered pixel in a 5 x 5 window.

    Returns the pixels that have one and that index (into ``covered``)."""
    device = covered.device
    with torch.no_grad():
        packed = torch.full((bsz * h * w,), -1, dtype=torch.long, device=device)
        packed[covered] = torch.arange(covered.numel(), device=device)
        src = _nearest_in_window(edge_pix, packed, _NEIGHBOURS[:8], h, w)  # 3 x 3 first: almost always enough
        far = (src < 0).nonzero(as_tuple=True)[0]
        if far.numel():
            src[far] = _nearest_in_window(edge_pix[far], packed, _NEIGHBOURS[8:], h, w)
        keep = src >= 0
    return edge_pix[keep], src[keep]
