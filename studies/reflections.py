"""How much of a glossy object's reflection looks the same from two views of the dataset's camera ring?

A multi-view image loss (or any term comparing an object's views) can only tell paint from reflection where
the reflection changes between the views: the part that any two views share is, for the loss, paint. This
diagnostic measures that part on a dataset's training objects under their own env maps. Per object, the
GT mesh, albedo and material are rendered by dibrpp (MC, env-map light) in 24 views twice: with the albedo
(the radiance) and with a black albedo (the specular reflection alone). Every foreground pixel is binned to
its texel of the GT UV map (found by rendering a texture that holds its own coordinates); for every ordered
pair of views that both see a texel, the darker view's reflection is what no view comparison can move out of
the albedo. Values are clipped at 1 before binning (the display range: a sun's glint would otherwise
outweigh the whole sky). Reported per camera set-up, for upward-facing texels (hood, roof; normal z > 0.7)
and the rest:

- ``kept_by_darker_view``: sum of min(reflection in view a, in view b) / sum of their mean;
- ``reflection_share``: sum of the mean reflection / sum of the mean radiance;
- ``reflection_share_cycles``: the same with the radiance of the dataset's Cycles images (dataset ring only:
  a check of the dibrpp radiance against the renderer that made the data).

    python -m studies.reflections --dataset data/glossy --out results/studies [--objects 12] [--spp 256]

Writes ``reflections.md`` / ``.csv`` and ``reflections.png`` (one object: Cycles views and reflections).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from dibrpp import Cameras, Material, Renderer
from dibrpp.cli_args import Parser, check_output_folder, non_negative_int, positive_int
from dibrpp.display import display_image
from dibrpp.lights import EnvMap
from dibrpp.io import DataError
from datagen.reader import MultiViewDataset
from studies.common import image_grid, write_study_table

UP_NORMAL_Z = 0.7
CLIP = 1.0


@dataclass
class Sizes:
    objects: int = 12
    spp: int = 256
    bins: tuple = (16, 32)  # texel bins (v, u) of the GT UV map
    spread_elevations: tuple = (5.0, 60.0)  # the second camera set-up: the ring's azimuths at these elevations
    seed: int = 0


QUICK = Sizes(objects=2, spp=16, bins=(8, 16))


def texel_means(values: torch.Tensor, uv: torch.Tensor, mask: torch.Tensor, bins: tuple) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view mean of ``values`` (V, H, W) over the pixels of each UV bin. uv (V, H, W, 2) in [0, 1],
    mask (V, H, W). Returns means and pixel counts, both (V, bins[0] * bins[1])."""
    bh, bw = bins
    idx = (uv[..., 1].clamp(0, 1 - 1e-6) * bh).long() * bw + (uv[..., 0].clamp(0, 1 - 1e-6) * bw).long()
    v = values.shape[0]
    sums, counts = values.new_zeros(v, bh * bw), values.new_zeros(v, bh * bw)
    for k in range(v):
        sums[k].index_add_(0, idx[k][mask[k]], values[k][mask[k]])
        counts[k].index_add_(0, idx[k][mask[k]], torch.ones_like(values[k][mask[k]]))
    return sums / counts.clamp_min(1), counts


def pair_sums(reflection: torch.Tensor, radiance: torch.Tensor, seen: torch.Tensor, select: torch.Tensor) -> torch.Tensor:
    """Sums over ordered pairs of distinct views (a, b) and texels seen by both and in ``select`` (V, V, T):
    [min(R_a, R_b), (R_a + R_b) / 2, (L_a + L_b) / 2] for reflection R and radiance L, all (V, T)."""
    v = reflection.shape[0]
    both = seen[:, None] & seen[None, :] & ~torch.eye(v, dtype=torch.bool)[..., None] & select
    darker = torch.minimum(reflection[:, None], reflection[None, :])
    mean_r = 0.5 * (reflection[:, None] + reflection[None, :])
    mean_l = 0.5 * (radiance[:, None] + radiance[None, :])
    return torch.stack([(darker * both).sum(), (mean_r * both).sum(), (mean_l * both).sum()])


def uv_texture(height: int = 64, width: int = 128) -> torch.Tensor:
    """(1, H, W, 3): a texture whose value is its own (u, v) coordinate (row 0 is v = 1: top row first)."""
    v, u = torch.meshgrid(torch.linspace(1, 0, height), torch.linspace(0, 1, width), indexing="ij")
    return torch.stack([u, v, torch.zeros_like(u)], -1)[None]


def run_dataset(dataset: str, out: Path, s: Sizes) -> str:
    ds = MultiViewDataset(dataset, split="train", views_per_item=1, with_envmap=True)
    cam = ds.camera_setup
    n_views = len(cam.azimuths_deg)
    azimuths = torch.tensor(cam.azimuths_deg, dtype=torch.float32)
    spread = torch.empty(n_views).uniform_(*s.spread_elevations, generator=torch.Generator().manual_seed(s.seed))
    setups = {f"dataset ring ({cam.elevation_deg:g} deg)": torch.full((n_views,), cam.elevation_deg),
              f"elevations {s.spread_elevations[0]:g}-{s.spread_elevations[1]:g} deg": spread}
    renderer = Renderer("mc", spp=s.spp, seed=s.seed)
    parts = ("upward", "other")
    totals = {(name, part, src): torch.zeros(3) for name in setups for part in parts for src in ("dibrpp", "cycles")}
    step = max(1, len(ds.samples) // s.objects)
    figure = None
    for obj, env in ds.samples[::step][: s.objects]:
        mesh = ds.mesh(obj).expand(n_views)
        params = ds.material_params(obj)
        light = EnvMap(ds.envmap(env)[None])
        for name, elevations in setups.items():
            cams = Cameras.orbit(cam.distance, elevations, azimuths, cam.fov_deg, ds.resolution)
            uv = renderer.render_albedo(mesh, cams, Material(albedo=uv_texture()))
            mask = uv.alpha > 0.99
            normal_z = renderer.render_normals(mesh, cams).rgb[..., 2]
            reflection = renderer(mesh, cams, Material(albedo=torch.zeros(1, 3), **params), light).rgb
            radiance = renderer(mesh, cams, Material(albedo=ds.texture(obj)[None], **params), light).rgb
            lum = lambda x: x.mean(-1).clamp_max(CLIP)  # noqa: E731
            r_t, count = texel_means(lum(reflection), uv.rgb[..., :2], mask, s.bins)
            l_t, _ = texel_means(lum(radiance), uv.rgb[..., :2], mask, s.bins)
            nz, _ = texel_means(normal_z, uv.rgb[..., :2], mask, s.bins)
            seen = count >= 2
            up = 0.5 * (nz[:, None] + nz[None, :]) > UP_NORMAL_Z
            for part, select in zip(parts, (up, ~up)):
                totals[(name, part, "dibrpp")] += pair_sums(r_t, l_t, seen, select)
            if name.startswith("dataset"):
                cycles = torch.stack([ds.view_image(obj, env, v) for v in range(n_views)])  # linear
                c_t, _ = texel_means(lum(cycles[..., :3]), uv.rgb[..., :2], mask, s.bins)
                for part, select in zip(parts, (up, ~up)):
                    totals[(name, part, "cycles")] += pair_sums(r_t, c_t, seen, select)
                if figure is None:
                    pick = [0, n_views // 4]
                    figure = [[display_image(cycles[v, ..., :3]) for v in pick] +
                              [display_image(reflection[v]) for v in pick]]
    rows = []
    for name in setups:
        for part in parts:
            t, c = totals[(name, part, "dibrpp")], totals[(name, part, "cycles")]
            rows.append(dict(cameras=name, texels=part, kept_by_darker_view=float(t[0] / t[1]),
                             reflection_share=float(t[1] / t[2]),
                             reflection_share_cycles=float(c[1] / c[2]) if c[2] > 0 else float("nan")))
    image_grid(figure, out / "reflections.png", None,
               ["Cycles, view 0", f"Cycles, view {n_views // 4}", "reflection, view 0", f"reflection, view {n_views // 4}"],
               "GT object: the dataset's images and dibrpp's specular reflection alone")
    note = (f"{s.objects} training objects of {dataset}, each under its env map; dibrpp MC at {s.spp} spp; "
            f"texels binned {s.bins[0]}x{s.bins[1]} on the GT UV map, values clipped at {CLIP:g}. "
            "kept_by_darker_view: share of the reflection the darker of two views still shows (what no "
            "comparison of views can take out of the albedo); reflection_share: share of the radiance that is "
            "reflection (radiance by dibrpp; _cycles: by the dataset's Cycles images).")
    return write_study_table(rows, out, "reflections", note)


def build_parser() -> Parser:
    ap = Parser(prog="python -m studies.reflections", description=__doc__)
    ap.add_argument("--dataset", default="data/glossy", metavar="DIR", help="dataset folder (python -m datagen)")
    ap.add_argument("--out", default="results/studies", metavar="DIR", help="results folder (made if missing)")
    ap.add_argument("--objects", type=positive_int, default=Sizes.objects, metavar="N", help="training objects")
    ap.add_argument("--spp", type=positive_int, default=Sizes.spp, metavar="N", help="MC samples per pixel")
    ap.add_argument("--threads", type=non_negative_int, default=0, metavar="N",
                    help="torch CPU threads; 0: as many as torch chooses (default: 0)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    try:
        check_output_folder("--out", out)
        if args.threads:
            torch.set_num_threads(args.threads)
        out.mkdir(parents=True, exist_ok=True)
        print(run_dataset(args.dataset, out, Sizes(objects=args.objects, spp=args.spp)))
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
