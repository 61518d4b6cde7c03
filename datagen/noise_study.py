"""How noisy is a dataset's Cycles render, and what removes the noise cheapest?

    python -m datagen.noise_study --dataset diffuse --objects 2 --views 2 --out results/noise_diffuse

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
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

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


def _foreground_errors(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    diff = (img[..., :3] - ref[..., :3])[mask]
    mse = float((diff ** 2).mean())
    return math.sqrt(mse), float((np.abs(ref[..., :3][mask])).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m datagen.noise_study", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="diffuse", choices=("metallic", "glossy", "diffuse"))
    ap.add_argument("--objects", type=int, default=2)
    ap.add_argument("--views", type=int, default=2, help="views per object (spread over the dataset's azimuths)")
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), help="subset of: " + "; ".join(VARIANTS))
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    import torch

    from dibrpp.conventions import orbit_world_to_camera
    from dibrpp.io import write_exr

    from . import cycles as C
    from . import generate as G
    from .layout import DatasetLayout

    cfg = G.make_config(args.dataset, resolution=args.resolution)
    p = G.plan(cfg)
    out = Path(args.out)
    assets = DatasetLayout(out / "assets")
    G._THREADS = args.threads
    objs = p["objects"][:args.objects]
    for o in objs:
        G.task_envmap(str(assets.root), cfg, o["envmaps"][0], p["env_kind"][o["envmaps"][0]])
        G.task_object(str(assets.root), cfg, o["index"], o)
    az_all = G.azimuths(cfg)
    pick = [az_all[int(k)] for k in np.linspace(0, len(az_all) - 1, args.views + 2)[1:-1].round()]
    rows = {name: dict(rmse=[], rmse_corrected=[], psnr=[], seconds=[], cpu_seconds=[], rel=[])
            for name in args.variants}
    ref_noise = []
    for o in objs:
        i, env = o["index"], o["envmaps"][0]
        with np.load(assets.mesh_npz(i)) as m:
            mesh = dict(verts=m["verts"], faces=m["faces"], uvs=m["uvs"], face_uvs=m["face_uvs"])
        material = C.PrincipledMaterial.from_dict(o["material"], texture=assets.texture(i))

        def render(settings: dict, az: float, seed: int, warm: bool = True):
            st = C.RenderSettings(resolution=cfg.resolution, max_bounces=cfg.max_bounces, threads=args.threads,
                                  seed=seed, **settings)
            cs = C.build_scene(mesh["verts"], mesh["faces"], envmap=assets.envmap(env), settings=st,
                               material=material, uvs=mesh["uvs"], face_uvs=mesh["face_uvs"])
            w2c = orbit_world_to_camera(torch.tensor(G.CAMERA_DISTANCE, dtype=torch.float64),
                                        G.CAMERA_ELEVATION_DEG, az)
            C.set_camera(cs, w2c.numpy(), G.FOV)
            if warm:  # a dataset renders many views per scene: leave scene sync and BVH out of the view's cost
                cs.scene.cycles.samples = 1
                C.render(cs)
                cs.scene.cycles.samples = st.spp
                cs.render_seconds = 0.0
            cpu = time.process_time()
            img = C.render(cs)["rgba"]
            return img, cs.render_seconds, time.process_time() - cpu

        for v, az in enumerate(pick):
            t0 = time.perf_counter()
            refs = [render(dict(spp=args.ref_spp), az, seed, warm=False)[0] for seed in (1001, 1002)]
            ref = (refs[0] + refs[1]) / 2
            mask = ref[..., 3] > 0.5
            half_diff, mean_fg = _foreground_errors(refs[0], refs[1], mask)
            sigma_ref = half_diff / 2  # std of the 2-render mean: |a - b| / 2
            ref_noise.append(sigma_ref)
            write_exr(out / f"obj_{i:04d}_view_{v}_ref.exr", ref)
            print(f"obj {i} az {az:.1f}: reference {2 * args.ref_spp} spp in {time.perf_counter() - t0:.1f}s, "
                  f"its noise {sigma_ref:.5f}", flush=True)
            for name in args.variants:
                img, secs, cpu = render(VARIANTS[name], az, 7)
                rmse, _ = _foreground_errors(img, ref, mask)
                corr = math.sqrt(max(rmse ** 2 - sigma_ref ** 2, 0.0))
                r = rows[name]
                r["rmse"].append(rmse)
                r["rmse_corrected"].append(corr)
                r["psnr"].append(-20 * math.log10(max(corr, 1e-12)))
                r["rel"].append(corr / mean_fg)
                r["seconds"].append(secs)
                r["cpu_seconds"].append(cpu)
                write_exr(out / f"obj_{i:04d}_view_{v}_{name.split(' (')[0].replace(' ', '_').replace(',', '')}.exr",
                          img)
    summary = {name: {k: float(np.mean(v)) for k, v in r.items()} for name, r in rows.items()}
    base = summary.get("32 spp (default)", {}).get("cpu_seconds")
    lines = ["| render | RMSE (fg, linear) | rel. RMSE | PSNR dB | CPU s/view | wall s/view | CPU vs 32 spp |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for name, s in summary.items():
        lines.append(f"| {name} | {s['rmse_corrected']:.4f} | {100 * s['rel']:.1f} % | {s['psnr']:.1f} | "
                     f"{s['cpu_seconds']:.2f} | {s['seconds']:.2f} | "
                     + (f"{s['cpu_seconds'] / base:.1f}x |" if base else "- |"))
    lines.append(f"\nReference: mean of 2 x {args.ref_spp} spp, own noise {np.mean(ref_noise):.5f} RMSE (removed "
                 f"from the errors above); {args.dataset}, {len(objs)} objects x {len(pick)} views, "
                 f"{cfg.resolution} px, {args.threads} thread(s).")
    out.mkdir(parents=True, exist_ok=True)
    (out / "noise.json").write_text(json.dumps(dict(summary=summary, per_view=rows, reference_noise=ref_noise,
                                                    args=vars(args)), indent=1))
    (out / "noise.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
