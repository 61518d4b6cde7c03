"""Normals read from the input's pixels, for the light probe's mirror cue (variant ``pixel-normals``).

The probe head reads the light through the normals of the predicted surface. Where a metallic car mirrors the sun
(its rounded edges, where the surface turns ~23 degrees within a 64 x 64 pixel) those are 13-14 degrees off, and a
mirror doubles that; one view's global code does not predict them, even when told the GT normals
(docs/experiments.md, entries 19, 33, 34). :class:`PixelNormalNet` is a small U-Net on the input image that
predicts a normal per pixel, in the camera's frame (what a convolution can read off an image does not depend on
where the camera stands), trained against the GT mesh's normals in each input view: 3D supervision, which the
paper does not use. It is fitted once, before the model trains (:func:`fit`; trained jointly from scratch, its
early normals misled the light head, and at the model's learning rate it saw a quarter of the views), kept in the
run folder, and held. Only the probe reads these normals, and only in evaluation: read in training too, the light
was fitted to the rounded mesh it is rendered through, and the probes and the albedo got worse (entries 35, 36).
The model trains as the default does; the mesh, its shading and every other head are the model's.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


LEARNING_RATE = 2e-3  # the one-cycle schedule's peak
FIT_STEPS, FIT_BATCH = 3000, 32  # ~15 min on 2 cores at 64 x 64; ~25 passes over the metallic set's 3840 views
INPUT_CEILING = 4.0  # encoder colour above this (radiance ~20) is a highlight whatever its value: bounded input
MIRROR_X = (-1.0, 1.0, 1.0)  # a camera-frame normal of the image flipped left-right


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2))


def normal_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1 - cos between two normal renders' (``Renderer.render_normals(...).image``: (B, H, W, 4) normal and
    coverage) over the pixels both cover."""
    both = (pred[..., 3] > 0.5) & (target[..., 3] > 0.5)
    cos = (F.normalize(pred[..., :3], dim=-1, eps=1e-12) * target[..., :3]).sum(-1)
    return ((1 - cos) * both).sum() / both.sum().clamp_min(1)


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
        camera = self.camera_normals(images)
        return camera @ world_to_camera[:, None, :3, :3].to(camera)  # n_world = R^T n_camera (rows)

    def camera_normals(self, images: torch.Tensor) -> torch.Tensor:
        """(B, S, S, 3) unit normals in each view's camera frame (x right, y up, z towards the camera)."""
        x = torch.cat([images[:, :3].clamp(0, INPUT_CEILING), images[:, 3:]], 1)
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.avg_pool2d(x, 2))
            skips.append(x)
        x = skips.pop()
        for block in self.up:
            x = block(torch.cat([F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False), skips.pop()], 1))
        facing = x.new_tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)  # where it starts: towards the camera
        return F.normalize(self.out(x) + facing, dim=1, eps=1e-12).permute(0, 2, 3, 1)


def fit(net: PixelNormalNet, images: torch.Tensor, world_to_camera: torch.Tensor, normals: torch.Tensor, seed: int,
        steps: int | None = None, progress: bool = False) -> list[float]:
    """Fit ``net`` to the GT normals of N views: ``images`` (N, 4, S, S) as the encoder sees them, their cameras'
    ``world_to_camera`` (N, 4, 4), ``normals`` (N, S, S, 4) the GT mesh's world-frame normals and coverage
    (TrainingViews' ``normals``). 1 - cos over the covered pixels, Adam in a one-cycle schedule; every other batch
    mirrored left-right (the mirror image of a view is a view of the mirrored car). Batches are drawn from ``seed``.
    ``steps``: FIT_STEPS unless given. Returns the loss every 100 steps."""
    from tqdm import tqdm

    steps = steps or FIT_STEPS
    target = torch.cat([normals[..., :3] @ world_to_camera[:, None, :3, :3].mT.to(normals), normals[..., 3:]], -1)
    opt = torch.optim.Adam(net.parameters(), lr=LEARNING_RATE)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, LEARNING_RATE, total_steps=steps, pct_start=0.05)
    g = torch.Generator().manual_seed(seed)
    losses = []
    for step in tqdm(range(steps), disable=not progress, desc="pixel normals", unit="step"):
        k = torch.randint(len(images), (FIT_BATCH,), generator=g).to(images.device)
        x, y = images[k], target[k]
        if step % 2:
            x, y = x.flip(3), y.flip(2) * y.new_tensor(MIRROR_X + (1.0,))
        pred = net.camera_normals(x)
        loss = normal_loss(torch.cat([pred, y[..., 3:]], -1), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        schedule.step()
        if step % 100 == 0 or step == steps - 1:
            losses.append(loss.item())
    opt.zero_grad(set_to_none=True)  # a fitted net holds no gradient
    return losses
