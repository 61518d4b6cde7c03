"""How noisy is a dataset's Cycles render, and what removes the noise cheapest?

    python -m studies.noise_study --dataset diffuse --objects 2 --views 2 --out results/noise_diffuse

Renders a few views of the dataset's own objects, materials and env maps (the assets are made exactly as
``python -m datagen`` makes them, into ``--out/assets``) with several render settings, and compares each
with a high-spp reference of the same view: RMSE and PSNR (peak 1, linear radiance) over the foreground
(reference alpha > 0.5), and Cycles' render time. The reference is the mean of two renders with
different seeds; their difference measures the reference's own noise, which is removed from the errors
(``rmse_corrected``: errors add in quadrature). Cost is the process's CPU seconds inside Cycles' render
call (all its threads, the denoiser's included), which a loaded machine disturbs less than wall time,
after a 1-spp warm-up render of the same scene (a dataset renders 12-24 views per scene, so scene
sync and BVH build are not a view's cost).
Writes ``noise.json`` and ``noise.md`` (a table).

Needs ``bpy`` (it renders with :mod:`datagen.cycles`); like every study it imports no learning code.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dibrpp.cli_args import Parser, check_output_folder, positive_int
from dibrpp.io import DataError

VARIANTS = {  # name: RenderSettings fields on top of the dataset's own
    "32 spp (default)": dict(spp=32),
    "64 spp": dict(spp=64),
    "128 spp": dict(spp=128),
    "256 spp": dict(spp=256),
    "adaptive 0.01, <=256 spp": dict(spp=256, adaptive_threshold=0.01),
    "adaptive 0.02, <=128 spp": dict(spp=128, adaptive_threshold=0.02),
    "16 spp + OIDN": dict(spp=16, denoise=True),
    "32 spp + OIDN": dict(spp=32, denoise=True),
    "64 spp + OIDN": dict(spp=64, denoise=True),
}
BASELINE = "32 spp (default)"  # the table's cost column is relative to this variant
REFERENCE_SEEDS = (1001, 1002)
VARIANT_SEED = 7
MEASURES = ("rmse", "rmse_corrected", "psnr", "seconds", "cpu_seconds", "rel")


def build_parser() -> Parser:
    ap = Parser(prog="python -m studies.noise_study", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="diffuse", choices=("metallic", "glossy", "diffuse"),
                    help="whose objects, materials, env maps and render settings")
    ap.add_argument("--objects", type=positive_int, default=2, metavar="N", help="objects of the dataset")
    ap.add_argument("--views", type=positive_int, default=2, metavar="N",
                    help="views per object (spread over the dataset's azimuths)")
    ap.add_argument("--resolution", type=positive_int, default=64, metavar="N", help="image side in pixels")
    ap.add_argument("--ref-spp", type=positive_int, default=1024, metavar="N",
                    help="samples per pixel of each of the reference's two renders")
    ap.add_argument("--threads", type=positive_int, default=1, metavar="N", help="Cycles render threads")
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS), metavar="NAME",
                    help="subset of: " + "; ".join(VARIANTS) + " (default: all)")
    ap.add_argument("--out", required=True, metavar="DIR", help="results folder (made if missing)")
    return ap


def parse_args(argv=None):
    """The arguments, --out checked too (a file or an unwritable folder is an error line before any render)."""
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        check_output_folder("--out", Path(args.out))
    except DataError as e:
        ap.error(str(e))
    return args


@dataclass
class StudyObject:
    """One of the dataset's objects under its first env map, ready to render from any azimuth."""

    index: int
    mesh: dict
    material: object  # datagen.cycles.PrincipledMaterial
    envmap: Path
    cfg: object  # datagen.config.Config
    threads: int


def make_objects(cfg, count: int, assets_root: Path, threads: int) -> list[StudyObject]:
    """The first ``count`` objects of the dataset, with their first env map, made as datagen makes them."""
    from datagen import cycles
    from datagen.layout import DatasetLayout
    from datagen.plan import plan
    from datagen.tasks import task_envmap, task_object

    p = plan(cfg)
    assets = DatasetLayout(assets_root)
    objects = []
    for o in p["objects"][:count]:
        i, env = o["index"], o["envmaps"][0]
        task_envmap(str(assets.root), cfg, env, p["env_kind"][env], threads=threads)
        task_object(str(assets.root), cfg, i, o)
        with np.load(assets.mesh_npz(i)) as m:
            mesh = dict(verts=m["verts"], faces=m["faces"], uvs=m["uvs"], face_uvs=m["face_uvs"])
        material = cycles.PrincipledMaterial.from_dict(o["material"], texture=assets.texture(i))
        objects.append(StudyObject(i, mesh, material, assets.envmap(env), cfg, threads))
    return objects


def pick_azimuths(cfg, views: int) -> list[float]:
    """``views`` of the dataset's azimuths, spread evenly and leaving out both ends."""
    from datagen.plan import azimuths

    all_azimuths = azimuths(cfg)
    return [all_azimuths[int(k)] for k in np.linspace(0, len(all_azimuths) - 1, views + 2)[1:-1].round()]


def render_view(obj: StudyObject, settings: dict, az: float, seed: int, warm: bool = True):
    """(RGBA image, Cycles wall seconds, process CPU seconds) of one view rendered with ``settings``."""
    import torch

    from datagen import cycles
    from datagen.layout import DEFAULT_CAMERA
    from dibrpp.conventions import orbit_world_to_camera

    st = cycles.RenderSettings(resolution=obj.cfg.resolution, max_bounces=obj.cfg.max_bounces, threads=obj.threads,
                               seed=seed, **settings)
    cs = cycles.build_scene(obj.mesh["verts"], obj.mesh["faces"], envmap=obj.envmap, settings=st,
                            material=obj.material, uvs=obj.mesh["uvs"], face_uvs=obj.mesh["face_uvs"])
    cam = DEFAULT_CAMERA
    w2c = orbit_world_to_camera(torch.tensor(cam.distance, dtype=torch.float64), cam.elevation_deg, az)
    cycles.set_camera(cs, w2c.numpy(), cam.fov)
    if warm:  # a dataset renders many views per scene: leave scene sync and BVH out of the view's cost
        cs.scene.cycles.samples = 1
        cycles.render(cs)
        cs.scene.cycles.samples = st.spp
        cs.render_seconds = 0.0
    cpu = time.process_time()
    img = cycles.render(cs)["rgba"]
    return img, cs.render_seconds, time.process_time() - cpu


def foreground_errors(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(RMSE of ``img`` against ``ref``, mean of ``ref``) over the foreground ``mask``, RGB only."""
    diff = (img[..., :3] - ref[..., :3])[mask]
    mse = float((diff ** 2).mean())
    return math.sqrt(mse), float((np.abs(ref[..., :3][mask])).mean())


@dataclass
class Reference:
    image: np.ndarray
    mask: np.ndarray  # foreground: reference alpha > 0.5
    noise: float  # RMSE of the 2-render mean itself: |a - b| / 2
    mean_foreground: float


def render_reference(obj: StudyObject, az: float, spp: int) -> Reference:
    """The mean of two ``spp`` renders with different seeds, and its own noise."""
    a, b = (render_view(obj, dict(spp=spp), az, seed, warm=False)[0] for seed in REFERENCE_SEEDS)
    ref = (a + b) / 2
    mask = ref[..., 3] > 0.5
    half_diff, mean_fg = foreground_errors(a, b, mask)
    return Reference(ref, mask, half_diff / 2, mean_fg)


def measure(img: np.ndarray, ref: Reference) -> dict:
    """The errors of one render against the reference, the reference's own noise removed."""
    rmse, _ = foreground_errors(img, ref.image, ref.mask)
    corrected = math.sqrt(max(rmse ** 2 - ref.noise ** 2, 0.0))
    return dict(rmse=rmse, rmse_corrected=corrected, psnr=-20 * math.log10(max(corrected, 1e-12)),
                rel=corrected / ref.mean_foreground)


def variant_file_name(name: str) -> str:
    return name.split(" (")[0].replace(" ", "_").replace(",", "")


def study_view(obj: StudyObject, v: int, az: float, args, rows: dict, out: Path) -> float:
    """Render view ``v`` of ``obj`` as reference and in every variant; add the measures to ``rows``; returns
    the reference's noise."""
    from dibrpp.io import write_exr

    t0 = time.perf_counter()
    ref = render_reference(obj, az, args.ref_spp)
    write_exr(out / f"obj_{obj.index:04d}_view_{v}_ref.exr", ref.image)
    print(f"obj {obj.index} az {az:.1f}: reference {2 * args.ref_spp} spp in {time.perf_counter() - t0:.1f}s, "
          f"its noise {ref.noise:.5f}", flush=True)
    for name in args.variants:
        img, secs, cpu = render_view(obj, VARIANTS[name], az, VARIANT_SEED)
        for key, value in dict(measure(img, ref), seconds=secs, cpu_seconds=cpu).items():
            rows[name][key].append(value)
        write_exr(out / f"obj_{obj.index:04d}_view_{v}_{variant_file_name(name)}.exr", img)
    return ref.noise


def table(summary: dict, ref_noise: list, args, objects: int, views: int, resolution: int) -> list[str]:
    """The Markdown table of ``summary`` (mean measures per variant) and its note."""
    base = summary.get(BASELINE, {}).get("cpu_seconds")
    lines = ["| render | RMSE (fg, linear) | rel. RMSE | PSNR dB | CPU s/view | wall s/view | CPU vs 32 spp |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for name, s in summary.items():
        lines.append(f"| {name} | {s['rmse_corrected']:.4f} | {100 * s['rel']:.1f} % | {s['psnr']:.1f} | "
                     f"{s['cpu_seconds']:.2f} | {s['seconds']:.2f} | "
                     + (f"{s['cpu_seconds'] / base:.1f}x |" if base else "- |"))
    lines.append(f"\nReference: mean of 2 x {args.ref_spp} spp, own noise {np.mean(ref_noise):.5f} RMSE (removed "
                 f"from the errors above); {args.dataset}, {objects} objects x {views} views, "
                 f"{resolution} px, {args.threads} thread(s).")
    return lines


def main(argv=None) -> int:
    from datagen.config import make_config

    args = parse_args(argv)
    out = Path(args.out)
    cfg = make_config(args.dataset, resolution=args.resolution)
    objects = make_objects(cfg, args.objects, out / "assets", args.threads)
    views = pick_azimuths(cfg, args.views)
    rows = {name: {key: [] for key in MEASURES} for name in args.variants}
    ref_noise = [study_view(obj, v, az, args, rows, out) for obj in objects for v, az in enumerate(views)]
    summary = {name: {k: float(np.mean(v)) for k, v in r.items()} for name, r in rows.items()}
    lines = table(summary, ref_noise, args, len(objects), len(views), cfg.resolution)
    out.mkdir(parents=True, exist_ok=True)
    (out / "noise.json").write_text(json.dumps(dict(summary=summary, per_view=rows, reference_noise=ref_noise,
                                                    args=vars(args)), indent=1))
    (out / "noise.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
