"""The paper's evaluation metrics (Sec. E.3, E.6), per image or per sample; lower is better for all.

- image: L1 between GT and re-rendered images in display space (sRGB clipped to [0, 1]), over the whole image
  composited on black, as the public code of DIB-R computes it, and over the GT foreground (ours);
- 2D IoU loss: 1 - IoU of the GT mask and the predicted silhouette (both thresholded at 0.5);
- light / texture: 1 - NCC (eq. 9), NCC(a, b) = sum(a * b) / (|a|_2 |b|_2) -- invariant to a global scale,
  so a predicted light or texture that is right up to intensity scores 0; the light on HDR maps and on LDR
  maps (:func:`ldr_envmap`);
- Chamfer distance between surface samples of the predicted and GT meshes, both scaled so that the GT
  bounding-box diagonal is 1 ("normalized as one", Sec. E.6), mean of the two directed squared distances.

Ours beside them: normals, the light's probes, sky and direction; the albedo's sky blue and the scales are in
:mod:`pipelines.evaluation.albedo_metrics`.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from scipy.spatial import cKDTree

from ..model.light_probe import mirror_directions, pixel_samples


def image_l1_foreground(pred_rgb: torch.Tensor, gt_rgb: torch.Tensor, gt_mask: torch.Tensor) -> torch.Tensor:
    """(B,) mean |pred - gt| over the GT foreground; rgb (B, H, W, 3), mask (B, H, W) in [0, 1]."""
    m = gt_mask.unsqueeze(-1)
    num = ((pred_rgb - gt_rgb).abs() * m).sum((1, 2, 3))
    return num / (3 * m.sum((1, 2, 3))).clamp_min(1e-8)


def image_l1_whole(pred_rgb: torch.Tensor, gt_rgb: torch.Tensor) -> torch.Tensor:
    """(B,) mean |pred - gt| over every pixel and channel of images (B, H, W, 3) composited on black: the
    background counts, as in DIB-R's test code (one mean, not the x3 channel sum of its training loss)."""
    return (pred_rgb - gt_rgb).abs().mean((1, 2, 3))


def iou_loss(pred_mask: torch.Tensor, gt_mask: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """(B,) 1 - |P and G| / |P or G| of masks (B, H, W) binarised at ``threshold`` (0 if both are empty)."""
    p, g = pred_mask > threshold, gt_mask > threshold
    inter = (p & g).sum((1, 2)).double()
    union = (p | g).sum((1, 2)).double()
    return torch.where(union > 0, 1 - inter / union.clamp_min(1), torch.zeros_like(union)).to(pred_mask.dtype)


def ncc_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B,) 1 - NCC (eq. 9) over everything but the batch dimension."""
    a, b = a.reshape(a.shape[0], -1).double(), b.reshape(b.shape[0], -1).double()
    ncc = (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1)).clamp_min(1e-30)
    return (1 - ncc).float()


def ldr_envmap(env: torch.Tensor) -> torch.Tensor:
    """(B, H, W, 3) HDR maps as LDR ones: each divided by its own mean radiance (over texels and channels) and
    clipped to [0, 1], so what is brighter than the mean (a sun, a lamp, the bright sky around them) saturates.
    Linear, no sRGB curve. Negative radiance (SH rings) counts as 0."""
    env = env.clamp_min(0)
    return (env / env.mean((1, 2, 3), keepdim=True).clamp_min(1e-30)).clamp_max(1)


def envmap_losses(pred_env: torch.Tensor, gt_env: torch.Tensor) -> dict:
    """{"light_hdr", "light_ldr": (B,)}: 1 - NCC (eq. 9) of equirect maps (B, H, W, 3) as they are and as
    LDR maps (:func:`ldr_envmap`)."""
    return {"light_hdr": ncc_loss(pred_env, gt_env), "light_ldr": ncc_loss(ldr_envmap(pred_env), ldr_envmap(gt_env))}


def chamfer_distance(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                     samples: int = 10_000, seed: int = 0) -> float:
    """Symmetric Chamfer distance between the surfaces, in units of the GT bounding-box diagonal."""
    scale = float(np.linalg.norm(gt_verts.max(0) - gt_verts.min(0)))
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError("the GT mesh is empty or degenerate; cannot normalise the Chamfer distance")
    pts = []
    for v, f in ((pred_verts, pred_faces), (gt_verts, gt_faces)):
        mesh = trimesh.Trimesh(np.asarray(v, np.float64) / scale, np.asarray(f), process=False)
        pts.append(np.asarray(trimesh.sample.sample_surface(mesh, samples, seed=seed)[0]))
    d_pg = cKDTree(pts[1]).query(pts[0])[0]
    d_gp = cKDTree(pts[0]).query(pts[1])[0]
    return float(0.5 * (np.mean(d_pg ** 2) + np.mean(d_gp ** 2)))


# ----------------------------------------------------------------------------- light, by what it does to surfaces
# Eq. 9 compares env maps texel by texel, and on HDR maps the sun dominates it: a constant map scores about
# as well as a model. Light-estimation work instead renders probe spheres under the true and the predicted
# light and compares the renders scale-invariantly, and measures the light's colour and main direction.

PROBES = {  # Principled parameters of the probe spheres (albedo, roughness, metallic, specular)
    "diffuse": (0.8, 1.0, 0.0, 0.0),
    "metal": (0.9, 0.4, 1.0, 0.5),
    "mirror": (1.0, 0.0, 1.0, 0.5),
}


class ProbeScene:
    """Unit probe spheres seen orthographically along the viewing axes of ``world_to_camera`` (B, 4, 4),
    rendered under any light by :meth:`render`.

    Noise-free: the diffuse and rough-metal spheres sum dibrpp's BRDF (times cosine) against every texel of
    the light tabulated as an ``env_height`` x 2 ``env_height`` map (area-averaged from 64 x 128, so a sun is
    not missed); the mirror (metal, albedo 1, so Fresnel is 1) shows the light in the reflected direction.
    The BRDF weights depend on the views only, so they are computed once for all lights compared.
    """

    def __init__(self, world_to_camera: torch.Tensor, resolution: int = 24, env_height: int = 24):
        from dibrpp.brdf import ShadingPoint, alpha_from_roughness
        from dibrpp.conventions import equirect_directions

        self.batch, self.resolution, self.env_height = world_to_camera.shape[0], resolution, env_height
        rot = world_to_camera[:, :3, :3].float()
        xs = (torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution * 2 - 1
        y, x = torch.meshgrid(-xs, xs, indexing="ij")  # row 0 at the top
        self.inside = (x * x + y * y) < 1
        n_cam = torch.stack([x, y, torch.sqrt((1 - x * x - y * y).clamp_min(0))], -1)[self.inside]  # +Z: to the viewer
        self.normal = n_cam @ rot  # camera -> world is R^T n, in row-vector form n R
        self.view = rot[:, 2].unsqueeze(1).expand_as(self.normal)  # the camera's +Z axis in the world
        dirs = equirect_directions(env_height, 2 * env_height).reshape(-1, 3)
        theta = (torch.arange(env_height) + 0.5) * math.pi / env_height
        solid = (math.pi / env_height) ** 2 * torch.sin(theta).repeat_interleave(2 * env_height)
        p = self.normal.shape[1]
        self.weights = {}  # probe -> (B, P, T, 3): BRDF x cosine x solid angle of each texel
        for name, (albedo, roughness, metallic, specular) in PROBES.items():
            if name == "mirror":
                continue
            self.weights[name] = torch.stack([ShadingPoint(
                normal=self.normal[k], view=self.view[k], albedo=torch.full((p, 3), albedo),
                alpha=alpha_from_roughness(torch.full((p,), roughness)), metallic=torch.full((p,), float(metallic)),
                specular=torch.full((p,), float(specular))).eval(dirs.unsqueeze(0).expand(p, -1, -1))
                for k in range(self.batch)]) * solid.view(1, 1, -1, 1)

    def render(self, light, table: torch.Tensor | None = None) -> dict:
        """{probe: (B, H, W, 4) linear RGBA} under ``light`` (EnvMap, SGLight or SHLight; world frame)."""
        if table is None:  # the light tabulated in the world frame, (B, 64, 128, 3)
            table = light.to_envmap(64, 128).image
        out = self.render_table(table)
        reflect = 2 * (self.normal * self.view).sum(-1, keepdim=True) * self.normal - self.view
        out["mirror"] = self._image(light.eval(reflect).clamp_min(0))
        return {name: out[name] for name in PROBES}

    def render_table(self, table: torch.Tensor, names=("diffuse", "metal")) -> dict:
        """{probe: (B, H, W, 4)} of the diffuse and rough-metal spheres under a tabulated world-frame light
        (B, h, w, 3), e.g. a GT env map (the mirror needs the light itself)."""
        h = self.env_height
        table = table.clamp_min(0)  # SH rings can dip below 0; no light is negative
        table = torch.nn.functional.adaptive_avg_pool2d(table.permute(0, 3, 1, 2), (h, 2 * h)).permute(0, 2, 3, 1)
        radiance = table.reshape(self.batch, 1, -1, 3)
        return {name: self._image((self.weights[name] * radiance).sum(2)) for name in names}

    def _image(self, rgb: torch.Tensor) -> torch.Tensor:
        image = rgb.new_zeros(self.batch, self.resolution, self.resolution, 4)
        image[:, self.inside] = torch.cat([rgb, torch.ones_like(rgb[..., :1])], -1)
        return image


def _foreground(pred_rgba, gt_rgba):
    m = (gt_rgba[..., 3:] > 0.5).to(gt_rgba.dtype)
    return ((pred_rgba[..., :3] * m).reshape(len(m), -1).double(), (gt_rgba[..., :3] * m).reshape(len(m), -1).double())


def si_scale(pred_rgba: torch.Tensor, gt_rgba: torch.Tensor) -> torch.Tensor:
    """(B,) the scale s minimising |s P - G| over the GT foreground (least squares)."""
    p, g = _foreground(pred_rgba, gt_rgba)
    return ((p * g).sum(1) / (p * p).sum(1).clamp_min(1e-30)).to(pred_rgba.dtype)


def si_rmse(pred_rgba: torch.Tensor, gt_rgba: torch.Tensor) -> torch.Tensor:
    """(B,) scale-invariant relative RMSE: min_s |s P - G| / |G| over the GT foreground (one scale for
    all three channels, so a wrong colour counts). 0: identical up to intensity; 1: no better than black."""
    p, g = _foreground(pred_rgba, gt_rgba)
    s = si_scale(pred_rgba, gt_rgba).double()
    return ((s[:, None] * p - g).norm(dim=1) / g.norm(dim=1).clamp_min(1e-30)).float()


def colour_angle_deg(a_rgb: torch.Tensor, b_rgb: torch.Tensor) -> torch.Tensor:
    """(B,) angle in degrees between two RGB colours (B, 3): 0 for the same chromaticity at any intensity."""
    cos = torch.nn.functional.cosine_similarity(a_rgb.double(), b_rgb.double(), dim=-1, eps=1e-30)
    return torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).float()


def mean_colour(rgba: torch.Tensor) -> torch.Tensor:
    """(B, 3) mean colour of the covered pixels of (B, H, W, 4) renders (a diffuse probe: the irradiance's colour)."""
    m = (rgba[..., 3:] > 0.5).to(rgba.dtype)
    return (rgba[..., :3] * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1)


def dominant_direction(env: torch.Tensor, height: int = 16, cone_deg: float = 20.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Main light direction of world-frame equirect maps (B, H, W, 3): the power-weighted mean direction of
    the cells (of a ``height`` x 2 ``height`` grid) within ``cone_deg`` of the cell that sends the most power,
    and the fraction of the total power that cell sends. Returns ((B, 3) unit directions, (B,) fractions)."""
    from dibrpp.conventions import LUMINANCE_WEIGHTS, equirect_directions

    b, h, w, _ = env.shape
    lum = (env * env.new_tensor(LUMINANCE_WEIGHTS)).sum(-1)
    theta = (torch.arange(h, dtype=env.dtype) + 0.5) * math.pi / h
    power = lum * torch.sin(theta).view(1, -1, 1)  # radiance x solid angle
    cells = torch.nn.functional.adaptive_avg_pool2d(power.unsqueeze(1), (height, 2 * height)).flatten(1)
    grid = equirect_directions(height, 2 * height, dtype=env.dtype).reshape(-1, 3)
    best = cells.argmax(1)
    near = (grid[best] @ grid.T) >= math.cos(math.radians(cone_deg))  # (B, cells): a cone around the peak
    mean = torch.nn.functional.normalize(((cells * near).unsqueeze(-1) * grid).sum(1), dim=-1)
    return mean, cells.gather(1, best[:, None])[:, 0] / cells.sum(1).clamp_min(1e-30)


def normal_error_deg(pred: torch.Tensor, pred_alpha: torch.Tensor, gt: torch.Tensor, gt_alpha: torch.Tensor,
                     within: float = 10.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Per view, the median angle (degrees) between predicted and GT unit normals (B, H, W, 3) over the pixels
    both cover (alpha > 0.5), and the share of those pixels within ``within`` degrees; NaN where none."""
    pred, gt = F.normalize(pred, dim=-1, eps=1e-12), F.normalize(gt, dim=-1, eps=1e-12)
    angle = torch.rad2deg(torch.arccos((pred * gt).sum(-1).clamp(-1, 1)))
    both = (pred_alpha > 0.5) & (gt_alpha > 0.5)
    medians, shares = [], []
    for a, m in zip(angle, both):
        v = a[m]
        medians.append(median(v).to(a.dtype))
        shares.append((v <= within).float().mean() if len(v) else a.new_tensor(float("nan")))
    return torch.stack(medians), torch.stack(shares)


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(...) angle in degrees between unit vectors (..., 3)."""
    return torch.rad2deg(torch.arccos((a * b).sum(-1).clamp(-1, 1)))


# The light beyond the sun: a sky over a ground. Each map is split at the horizon without its sun and the sun's glow
# (the cells within SKY_SUN_CONE_DEG of its dominant direction); a sky is at least SKY_BRIGHTER times as bright as
# its ground and SKY_BLUER bluer (blue chromaticity b / (r + g + b)). A constant map has neither.
SKY_SUN_CONE_DEG, SKY_BRIGHTER, SKY_BLUER = 25.0, 1.25, 0.01


def sky_and_ground(env: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3) and (B, 3): the mean radiance (by solid angle) of world-frame equirect maps (B, H, W, 3) above and
    below the horizon, without the cells within SKY_SUN_CONE_DEG of each map's dominant direction."""
    from dibrpp.conventions import equirect_directions, equirect_solid_angles

    b, h, w, _ = env.shape
    dirs = equirect_directions(h, w, dtype=env.dtype).reshape(-1, 3)
    solid = equirect_solid_angles(h, w, dtype=env.dtype).expand(h, w).reshape(1, -1)
    sun = dominant_direction(env)[0]
    weight = solid * ((sun @ dirs.T) < math.cos(math.radians(SKY_SUN_CONE_DEG)))
    radiance = env.reshape(b, -1, 3)

    def mean(side: torch.Tensor) -> torch.Tensor:
        ws = weight * side
        return (radiance * ws[..., None]).sum(1) / ws.sum(1, keepdim=True).clamp_min(1e-12)

    up = dirs[:, 2] > 0
    return mean(up), mean(~up)


def sky_contrast(env: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) how many times as bright as its ground the sky of each map is, and (B,) how much bluer."""
    from dibrpp.conventions import LUMINANCE_WEIGHTS

    sky, ground = sky_and_ground(env)
    lum = sky.new_tensor(LUMINANCE_WEIGHTS)
    blue = lambda c: c[:, 2] / c.sum(-1).clamp_min(1e-12)  # noqa: E731
    return (sky @ lum) / (ground @ lum).clamp_min(1e-12), blue(sky) - blue(ground)


def has_sky(ratio: torch.Tensor, bluer: torch.Tensor) -> torch.Tensor:
    """(B,) whether :func:`sky_contrast`'s ratio and blueness make a sky over a ground."""
    return (ratio >= SKY_BRIGHTER) & (bluer >= SKY_BLUER)


def has_sky_like_gt(ratio: torch.Tensor, bluer: torch.Tensor, gt_bluer: torch.Tensor) -> torch.Tensor:
    """(B,) the light target's test: a sky as much brighter than its ground as :func:`has_sky` asks, and at least half
    as much bluer as the GT's sky (``gt_bluer``, :func:`sky_contrast`'s) is than its ground."""
    return (ratio >= SKY_BRIGHTER) & (bluer >= 0.5 * gt_bluer)


# A map has a dominant light (a sun, or a window or lamp in a room) when one cell of the 16 x 32 grid sends
# at least this fraction of its power (measured on the default maps: skies with a clear sun 0.25-0.82,
# hazy skies 0.01-0.04, rooms 0.05-0.30).
SUN_FRACTION = 0.2


def light_metrics(pred_light, gt_env, scene: "ProbeScene") -> dict:
    """Per-view light metrics (name -> (B,)) of a predicted light against the GT env map, both in the world
    frame (EnvMap, SGLight or SHLight), seen in the views of ``scene``: si-RMSE of the three probes, the
    colour angle of the diffuse probe (the irradiance's colour) and the angle between the dominant light
    directions (NaN where the GT map has no dominant light)."""
    gt_table, pred_table = gt_env.to_envmap(64, 128).image, pred_light.to_envmap(64, 128).image
    gt, pred = scene.render(gt_env, gt_table), scene.render(pred_light, pred_table)
    out = {f"probe_{k}": si_rmse(pred[k], gt[k]) for k in PROBES}
    out["colour_deg"] = colour_angle_deg(mean_colour(pred["diffuse"]), mean_colour(gt["diffuse"]))
    d_gt, frac = dominant_direction(gt_table)
    d_pred, _ = dominant_direction(pred_table)
    out["direction_deg"] = torch.where(frac >= SUN_FRACTION, angle_deg(d_pred, d_gt), torch.full_like(frac, float("nan")))
    return out


def constant_light_references(gt_env: torch.Tensor, scene: "ProbeScene") -> dict:
    """What every light metric gives a constant env map (no prediction at all) against the GT maps (B, H, W, 3), by
    the same functions that score a prediction: {"light_hdr_constant", "light_ldr_constant", "probe_..._constant",
    "colour_deg_constant", "direction_deg_constant": (B,)}. A constant map has no direction: its reference is
    the guess "the light comes from straight above" (NaN where the GT map has no dominant light)."""
    from dibrpp.lights import EnvMap

    out = envmap_losses(torch.ones_like(gt_env), gt_env)
    out.update(light_metrics(EnvMap(gt_env.new_ones(len(gt_env), 8, 16, 3)), EnvMap(gt_env), scene))
    d_gt, frac = dominant_direction(gt_env)
    up = gt_env.new_tensor([0.0, 0.0, 1.0]).expand(len(gt_env), 3)
    out["direction_deg"] = torch.where(frac >= SUN_FRACTION, angle_deg(up, d_gt), torch.full_like(frac, float("nan")))
    return {f"{k}_constant": v for k, v in out.items()}


SUN_PIXEL_DEG = 10.0  # a pixel "mirrors the sun" where the GT surface's mirror direction is this close to it


def normal_turn_deg(normals: torch.Tensor, weight: torch.Tensor, size: int) -> torch.Tensor:
    """(B, N) per covered pixel, the largest angle (degrees) between its normal and a covered 4-neighbour's: how far
    the surface turns within one pixel, so what a pixel's misplacement costs there. normals (B, N, 3) unit, weight
    (B, N) coverage (> 0.5: covered), N = size * size pixels; 0 where no neighbour is covered."""
    n, covered = normals.view(-1, size, size, 3), weight.view(-1, size, size) > 0.5
    turn = normals.new_zeros(n.shape[:3])
    for dim in (1, 2):  # each pair of neighbours along rows, then columns
        a, b = (slice(None),) * dim + (slice(1, None),), (slice(None),) * dim + (slice(None, -1),)
        pair = angle_deg(n[a], n[b]) * (covered[a] & covered[b])
        turn[a] = torch.maximum(turn[a], pair)
        turn[b] = torch.maximum(turn[b], pair)
    return turn.view(weight.shape)


def normal_errors(pred_meshes, gt_meshes: list, cameras, rgba: torch.Tensor, sun: torch.Tensor,
                  pixel_normals: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 3) per view, the median angle (degrees) between the predicted and the GT surface's normals over the
    pixels both cover, and over those of them where the GT surface mirrors the ``sun`` (B, 3); and how far the GT
    surface turns within a pixel there (:func:`normal_turn_deg`, median): the error a pixel's misplacement of the
    predicted surface costs at the sun's pixels. NaN where no pixel mirrors the sun. ``pixel_normals``
    (B, S, S, 3): world-frame normals measured instead of the predicted surface's, on the pixels it covers."""
    radiance, alpha = rgba[..., :3], rgba[..., 3]
    pred_n, _, _, pred_w = pixel_samples(pred_meshes, cameras, radiance, alpha)
    if pixel_normals is not None:
        pred_n = pixel_normals.flatten(1, 2)
    gt = [pixel_samples(m, cameras[[k]], radiance[k:k + 1], alpha[k:k + 1]) for k, m in enumerate(gt_meshes)]
    gt_n, gt_v, gt_w = (torch.cat([g[i] for g in gt]) for i in (0, 1, 3))
    angle = angle_deg(pred_n, gt_n)
    both = (pred_w > 0.5) & (gt_w > 0.5)
    at_sun = both & (angle_deg(mirror_directions(gt_n, gt_v), sun[:, None].expand_as(gt_n)) <= SUN_PIXEL_DEG)
    turn = normal_turn_deg(gt_n, gt_w, cameras.resolution)
    nan = angle.new_tensor(float("nan"))
    return torch.stack([torch.stack([median(a[m]).to(a.dtype) if m.any() else nan for a, m in ((e, b), (e, s), (t, s))])
                        for e, t, b, s in zip(angle, turn, both, at_sun)])


def median(values: torch.Tensor) -> torch.Tensor:
    """The median of ``values``, NaN ignored: the mean of the two middle values of an even count (torch's
    ``median`` / ``nanmedian`` return the lower one, which the intervals' ``np.median`` does not); NaN if none."""
    values = values.double().flatten()
    return torch.nanquantile(values, 0.5) if values.numel() else values.new_tensor(math.nan)


def direction_summary(errors_deg: np.ndarray, samples: np.ndarray, resamples: int = 2000, seed: int = 0) -> dict:
    """The dominant-light direction errors (degrees) of the test views with a dominant light, summarised with
    95 % intervals: their median and the shares within 25 and 45 degrees. The views of one sample (an object under
    one map) are not independent draws, and a test split holds few sunny maps, so the intervals resample whole
    samples (a cluster bootstrap; ``samples`` gives each view's). {"median", "within_25", "within_45": value,
    "..._ci": [low, high]}; NaN where there is no view."""
    errors, samples = np.asarray(errors_deg, dtype=float), np.asarray(samples)
    stats = {"median": np.median, "within_25": lambda e: float(np.mean(e <= 25)), "within_45": lambda e: float(np.mean(e <= 45))}
    if not len(errors):
        return {k: v for name in stats for k, v in ((name, math.nan), (name + "_ci", [math.nan, math.nan]))}
    groups = [errors[samples == s] for s in np.unique(samples)]
    draws = np.random.default_rng(seed).integers(0, len(groups), (resamples, len(groups)))
    out = {}
    for name, stat in stats.items():
        boot = [stat(np.concatenate([groups[i] for i in d])) for d in draws]
        out[name], out[name + "_ci"] = float(stat(errors)), [float(x) for x in np.percentile(boot, [2.5, 97.5])]
    return out
