"""The training objective (eq. 8 and the regularisers), in two parts:

- :func:`render_plan`: which prediction is rendered in which view, lit by whose light, against which image;
- :func:`loss_terms`: which loss terms apply to those renders, with their weights.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import torch

from dibrpp import Cameras, Renderer
from dibrpp.lights import EnvMap, SGLight
from dibrpp.mesh import laplacian_smoothness
from dibrpp.raster import Fragments
from dibrpp.renderer import RenderOutput
from dibrpp.shading import GBuffer

from .config import SG_LIGHT, TrainConfig
from .losses import foreground_l1, gradient_loss, image_space, soft_iou_loss, supervised_light_loss
from ..model.model_input import encoder_input


@dataclass
class RenderPlan:
    """Index tensors over the 2B predictions / views of a batch (2i + j: item i, view j): render ``src``'s
    shape and material in view ``dst`` lit by ``lit_by``'s light, and compare with view ``dst``'s image."""
    src: torch.Tensor
    dst: torch.Tensor
    lit_by: torch.Tensor


def render_plan(batch_items: int, config: TrainConfig) -> RenderPlan:
    """Eq. 8: every prediction in both views of its pair, lit by the light predicted from the view it is rendered
    in; with ``cross_view_light`` "both" (the default) each cross-view render again under the prediction's own
    light, read from its own view: one world light has to explain the highlights of both views, where the light
    read from the other view can follow its wrong normals."""
    b = batch_items
    src = torch.arange(b * 2).view(b, 2).repeat_interleave(2, dim=1).reshape(-1)  # (b, [i1 i1 i2 i2])
    dst = torch.arange(b * 2).view(b, 2).repeat(1, 2).reshape(-1)  # (b, [v1 v2 v1 v2])
    lit_by = dst.clone()
    cross = src != dst
    if config.cross_view_light == "both":  # ... under each of the two lights (the cross-view renders twice)
        src, dst, lit_by = torch.cat([src, src[cross]]), torch.cat([dst, dst[cross]]), torch.cat([lit_by, src[cross]])
    return RenderPlan(src, dst, lit_by)


def loss_terms(pred, out, target: torch.Tensor, views: Cameras, batch: dict, config: TrainConfig,
               laplacian, independent_rgb: torch.Tensor | None = None) -> tuple[dict, dict]:
    """({term: value}, {term: weight}): eq. 8's image terms on the renders ``out`` against ``target``, the
    regularisers of the prediction ``pred``, and a diagnostic's supervision of the light.
    ``independent_rgb``: the same renders with other MC samples (``TrainConfig.independent_mc_samples``)."""
    space = partial(image_space, clipped=config.image_loss == "clipped")
    rgb, target_rgb = space(out.rgb), space(target[..., :3])
    other = None if independent_rgb is None else space(independent_rgb)
    terms = {
        "image": foreground_l1(rgb, target_rgb, target[..., 3], independent=other),
        "iou": soft_iou_loss(out.silhouette, target[..., 3]),
        "laplacian": laplacian_smoothness(pred.verts, laplacian) / pred.config.template_radius ** 2,
        "gradient": gradient_loss(rgb, target_rgb * target[..., 3:], independent=other),
    }
    weights = {"image": config.w_image, "iou": config.w_iou, "laplacian": config.w_laplacian, "gradient": config.w_gradient}
    if config.supervision in ("light-map", "light-probe"):
        light = pred.light(views.world_to_camera)
        terms["light_supervision"] = supervised_light_loss(light, batch["envmap"], config.supervision.split("-")[1])
        weights["light_supervision"] = 1.0
    return terms, weights


def shade_sun_on_held_surface(renderer: Renderer, frags: Fragments, g: GBuffer, light: SGLight) -> RenderOutput:
    """The render under SG ``light`` whose last lobe is the sun the probe head adds from the mirror cue: the other lobes (the head's own sun among them) shade the predicted surface as usual, that lobe
    shades the same pixels with the surface's normals held (no gradient): it was read off that surface, so
    bending the surface to fit its highlight would only chase the surface's own error. SG shading is linear in
    the lobes, so the image is the full light's."""
    held = GBuffer(replace(g.point, normal=g.point.normal.detach(), view=g.point.view.detach()), g.batch, g.num_images)
    lobes = lambda part: SGLight(light.axis[:, part], light.sharpness[:, part],  # noqa: E731
                                 light.amplitude[:, part]).in_frame(light.world_to_light)
    sky = renderer.shade(frags, g, lobes(slice(None, -1)))
    sun = renderer.shade(frags, held, lobes(slice(-1, None)))
    return RenderOutput(torch.cat([sky.rgb + sun.rgb, sky.image[..., 3:]], -1), frags, g)


def shade_sky_and_sun(renderer: Renderer, frags: Fragments, g: GBuffer, light: tuple[EnvMap, SGLight],
                      second: Renderer | None = None) -> RenderOutput | tuple[RenderOutput, torch.Tensor]:
    """The render under MC's probe sun (:meth:`Prediction.sky_and_sun`): the sky's grid shaded by ``renderer``'s MC,
    the sun's SG lobe in closed form (the SG shading of the paper) on the same G-buffer. Shading is linear in the
    light, so the image is the whole light's; the sun's part and its gradient carry no sampling noise or bias.
    ``second``: an MC renderer with other samples; then also the RGB of the same render shaded by it."""
    sky, sun = light
    lit_by_sky = renderer.shade(frags, g, sky)
    lit_by_sun = Renderer("sg", raster_settings=renderer.raster_settings).shade(frags, g, sun)
    out = RenderOutput(torch.cat([lit_by_sky.rgb + lit_by_sun.rgb, lit_by_sky.image[..., 3:]], -1), frags, g)
    return out if second is None else (out, second.shade(frags, g, sky).rgb + lit_by_sun.rgb)


def multiview_losses(model, renderer: Renderer, batch: dict, config: TrainConfig, laplacian,
                     second: Renderer | None = None) -> tuple[torch.Tensor, dict, dict]:
    """Eq. (8) plus the regularisers. Returns (total, {term: value}, tensors for snapshots). ``second``: the MC
    renderer with other samples under MC's probe sun (``TrainConfig.independent_mc_samples``; without it, one
    render)."""
    img = batch["image"]  # (B, 2, S, S, 4) linear RGB + alpha
    b, s = img.shape[0], img.shape[2]
    flat = img.reshape(b * 2, s, s, 4)
    views = Cameras(batch["world_to_camera"].reshape(b * 2, 4, 4), batch["fov"].reshape(-1), s)
    pred = model(encoder_input(flat), views)  # prediction from every view: index 2i + j
    plan = render_plan(b, config)
    lighting = pred.select(plan.lit_by)
    light = lighting.light(views.world_to_camera[plan.lit_by])
    shade = Renderer.shade
    if config.has_probe_head() and config.shading in SG_LIGHT:  # the SG sun's floor lobe: a held surface
        shade = shade_sun_on_held_surface
    elif config.has_probe_head():  # MC's probe sun (no floor): its SG lobe in closed form, the sky by MC
        shade = partial(shade_sky_and_sun, second=second)  # train passes a second renderer where the config asks
        light = lighting.sky_and_sun(views.world_to_camera[plan.lit_by])
    # a prediction rendered in a view under two lights is rasterized once
    pairs, render_of = torch.unique(plan.src * len(views) + plan.dst, return_inverse=True)
    shape_pred = pred.select(pairs // len(views))
    frags, g = renderer.gbuffer_of_images(shape_pred.meshes(), views[(pairs % len(views)).tolist()],
                                          shape_pred.material(), render_of)
    out = shade(renderer, frags, g, light)
    out, independent_rgb = out if isinstance(out, tuple) else (out, None)  # (a tuple: the second samples' RGB too)
    target = flat[plan.dst]
    terms, weights = loss_terms(pred, out, target, views, batch, config, laplacian, independent_rgb)
    if config.supervision == "albedo":  # each prediction's albedo in its own input view against the GT's there
        own = renderer.render_albedo(pred.meshes(), views, pred.material()).rgb
        terms["albedo_supervision"] = foreground_l1(image_space(own), image_space(batch["albedo"].reshape(own.shape)),
                                                    flat[..., 3])
        weights["albedo_supervision"] = 1.0
    elif config.supervision == "roughness":  # each prediction's roughness against its object's GT
        target_roughness = batch["roughness"].repeat_interleave(2).to(pred.roughness)
        terms["roughness_supervision"] = (pred.roughness.flatten() - target_roughness).abs().mean()
        weights["roughness_supervision"] = 1.0
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms, dict(input=flat, render=out.rgb, alpha=out.alpha, pred=pred, target=target, src=plan.src,
                              world_to_camera=views.world_to_camera)
