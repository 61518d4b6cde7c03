"""Training losses (Sec. E.2): multi-view image L1 (eq. 8), soft silhouette IoU, Laplacian smoothness and
a weight-free perceptual stand-in (multi-scale image-gradient L1; no pretrained VGG can be downloaded here).

Images are compared in :func:`hdr_srgb`, the sRGB curve continued above 1: it equals the display space
of the reported image metric below 1, and unlike the clipped display space it keeps gradients in
highlights (a sun reflected in a car is where the light's direction shows, and it is far above 1).
"""
from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from dibrpp.conventions import orbit_world_to_camera

from ..evaluation.metrics import ProbeScene, si_rmse


def hdr_srgb(rgb_linear: torch.Tensor) -> torch.Tensor:
    """Linear HDR -> sRGB encoding without the clip at 1 (monotone, C1 at 1, slope > 0 everywhere)."""
    x = rgb_linear.clamp_min(0.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def image_space(rgb_linear: torch.Tensor, clipped: bool = False) -> torch.Tensor:
    """Where the image losses compare: :func:`hdr_srgb`, or with ``clipped`` the display sRGB of an 8-bit picture
    (clipped at 1: no gradient in highlights), the paper's."""
    return hdr_srgb(rgb_linear.clamp_max(1.0) if clipped else rgb_linear)



def independent_abs(a: torch.Tensor, b: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """|render - target| for two MC renders ``a``, ``b`` of the same image with independent samples: the value is
    their mean, the gradient each one's sign times the other's derivative. With one render the sign and the
    derivative share its noise, so the expected loss holds the noise itself, and training lowers it by blurring
    the light (a sun becomes a glow); with independent samples the gradient is the expected loss's at fixed noise."""
    sign_a, sign_b = (a - target).sign().detach(), (b - target).sign().detach()
    surrogate = (sign_a * b + sign_b * a) / 2
    value = ((a - target).abs() + (b - target).abs()) / 2
    return value.detach() + surrogate - surrogate.detach()


def _abs_error(pred: torch.Tensor, target: torch.Tensor, independent: torch.Tensor | None) -> torch.Tensor:
    return (pred - target).abs() if independent is None else independent_abs(pred, independent, target)


def foreground_l1(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, target_mask: torch.Tensor,
                  independent: torch.Tensor | None = None) -> torch.Tensor:
    """Mean L1 over foreground pixels; images (B, H, W, 3) in the same space, mask (B, H, W). ``independent``: a
    second render of ``pred_rgb``'s with other MC samples (:func:`independent_abs`)."""
    m = target_mask.unsqueeze(-1)
    return (_abs_error(pred_rgb, target_rgb * m, independent) * m).sum() / (3 * m.sum()).clamp_min(1)


def soft_iou_loss(soft_mask: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """1 - soft IoU of a differentiable silhouette and the target mask, averaged over the batch."""
    dims = tuple(range(1, soft_mask.dim()))
    inter = (soft_mask * target_mask).sum(dims)
    union = (soft_mask + target_mask - soft_mask * target_mask).sum(dims)
    return (1 - inter / union.clamp_min(1e-6)).mean()


def gradient_loss(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, scales: int = 3,
                  independent: torch.Tensor | None = None) -> torch.Tensor:
    """L1 between image gradients at several scales: rewards sharp, aligned texture detail. ``independent``: as in
    :func:`foreground_l1`."""
    p, t = pred_rgb.permute(0, 3, 1, 2), target_rgb.permute(0, 3, 1, 2)
    q = None if independent is None else independent.permute(0, 3, 1, 2)
    total = p.new_zeros(())
    for s in range(scales):
        if s:
            p, t = F.avg_pool2d(p, 2), F.avg_pool2d(t, 2)
            q = None if q is None else F.avg_pool2d(q, 2)
        for dim in (2, 3):
            q_diff = None if q is None else torch.diff(q, dim=dim)
            total = total + _abs_error(torch.diff(p, dim=dim), torch.diff(t, dim=dim), q_diff).mean()
    return total / scales


@functools.lru_cache(maxsize=1)
def _probe_scene() -> ProbeScene:
    """The probe spheres seen from four directions around the horizon, 20 degrees above it."""
    return ProbeScene(orbit_world_to_camera(torch.tensor(3.0), 20.0, torch.tensor([0.0, 90.0, 180.0, 270.0])), resolution=16)


def supervised_light_loss(light, envmaps: torch.Tensor, kind: str) -> torch.Tensor:
    """The diagnostic light supervision of the 2B world-frame predicted lights (2i + j: item i, view j) by the
    items' GT world-frame env maps (B, H, W, 3). "map": L1 of log(1 + radiance) over the map; "probe": si-RMSE
    of the rough-metal probe sphere (the light metric itself) seen from four directions."""
    if kind == "map":
        env = envmaps.repeat_interleave(2, 0)
        pred_env = light.to_envmap(env.shape[1], env.shape[2]).image
        return (torch.log1p(pred_env) - torch.log1p(env)).abs().mean()
    if kind != "probe":
        raise ValueError(f"the light is supervised on the 'map' or the 'probe' here, got {kind!r}")
    scene = _probe_scene()
    metal = lambda table, k: scene.render_table(table[k:k + 1].expand(len(scene.view), -1, -1, -1), ["metal"])["metal"]  # noqa: E731
    gt = [metal(envmaps, i) for i in range(len(envmaps))]  # once per item: both its views share the map
    pred_table = light.to_envmap(envmaps.shape[1], envmaps.shape[2]).image
    return torch.stack([si_rmse(metal(pred_table, k), gt[k // 2]).mean() for k in range(len(pred_table))]).mean()
