"""What ``pipelines.predict`` shows a user: one picture of a prediction (the input as the model saw it, the shape,
the albedo, the light, the object relit from other views) and a self-contained HTML page around it."""
from __future__ import annotations

import base64
import html
from pathlib import Path

import torch

from dibrpp.display import display_image, tonemap_envmap
from dibrpp.formatting import pyplot, save_figure
from dibrpp.io import atomic_path

OVERVIEW, REPORT = "overview.png", "report.html"


def on_white(rgba: torch.Tensor, linear: bool = True) -> torch.Tensor:
    """(H, W, 3) display colour of an RGBA image over a white page (``linear``: radiance, shown in sRGB)."""
    rgb = display_image(rgba[..., :3]) if linear else rgba[..., :3]
    alpha = rgba[..., 3:].clamp(0, 1)
    return (rgb.clamp(0, 1) * alpha + (1 - alpha)).clamp(0, 1)


def write_overview(path: Path, title: str, model_input: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor,
                   envmap: torch.Tensor, novel_views: list[torch.Tensor],
                   true_light: tuple[torch.Tensor, str] | None = None) -> Path:
    """One row: the input as framed for the model (linear RGBA), the predicted shape (world normals, RGBA in
    [-1, 1]), its albedo (linear RGBA), its light (an HDR equirect, tone-mapped), the light the image was taken
    under where it is known (its map and its panel's title), and novel views (linear RGBA)."""
    normal_colour = torch.cat([normals[..., :3] * 0.5 + 0.5, normals[..., 3:]], -1)
    panels = [("input (as the model sees it)", on_white(model_input)), ("shape (normals)", on_white(normal_colour, False)),
              ("albedo", on_white(albedo)), ("light (env map, up at the top)", tonemap_envmap(envmap).clamp(0, 1))]
    if true_light is not None:
        panels.append((true_light[1], tonemap_envmap(true_light[0]).clamp(0, 1)))
    panels += [(f"relit, view {i + 1}", on_white(v)) for i, v in enumerate(novel_views)]
    plt = pyplot()
    ratios = [2 if image.shape[1] > 1.5 * image.shape[0] else 1 for _, image in panels]  # env maps are 2:1
    fig, axes = plt.subplots(1, len(panels), figsize=(2.3 * sum(ratios), 2.7), gridspec_kw=dict(width_ratios=ratios))
    for ax, (name, image) in zip(axes, panels):
        ax.imshow(image.numpy())
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, dpi=110)


def write_report(out: Path, material: dict) -> Path:
    """``report.html`` in ``out``: the overview and the novel views embedded, the material, links to the files."""
    def img(name: str) -> str:
        data = base64.b64encode((out / name).read_bytes()).decode()
        return f'<p><img alt="{name}" src="data:image/png;base64,{data}" style="max-width:100%"></p>'

    rows = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(str(v))}</td></tr>"
                   for k, v in material.items())
    files = " · ".join(f'<a href="{name}">{name}</a>' for name in
                       ("model.glb", "mesh.obj", "texture.png", "envmap.exr", "envmap.hdr", "material.json",
                        "novel_views.png", OVERVIEW))
    page = (f"<!doctype html><meta charset=utf-8><title>dibrpp prediction: {html.escape(material['input'])}</title>"
            "<body style='font-family:sans-serif;margin:1em 2%'>"
            f"<h1>Prediction from {html.escape(material['input'])}</h1>{img(OVERVIEW)}"
            f"<h2>Relit from other views</h2>{img('novel_views.png')}"
            f"<h2>Material and camera</h2><table border=1 cellpadding=3>{rows}</table>"
            f"<h2>Files</h2><p>{files}</p></body>")
    with atomic_path(out / REPORT) as tmp:
        tmp.write_text(page)
    return out / REPORT
