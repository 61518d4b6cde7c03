"""Renderer studies of the supplementary's Sec. B and C, on a unit sphere under procedural HDR light.

    python -m studies --out results/studies [--quick] [--only A,B,C,DE] [--device cpu|cuda]

A  studies.noise: sample count vs roughness (Fig. A): MC noise against a converged reference for N
   samples per pixel and roughness beta, BRDF sampling alone vs BRDF + env-map sampling with MIS.
B  studies.sg_fit: SG approximation of an env map (Fig. B): fit error of K = 1..128 lobes vs K and
   parameter count.
C  studies.ambiguity: light/material ambiguity (Fig. C): a sharp light on a rough sphere vs a smooth
   light (fitted to match) on a glossy one, compared in PSNR under SG and MC shading.
DE studies.joint_fit: joint optimisation of light, albedo, roughness and specular from 24 views
   (Fig. D, E): SG shading for the table of Fig. E, MC shading for a subset of its rows.

Each study writes Markdown + CSV tables and PNG figures under --out and prints its table. Nothing is
downloaded: the env maps come from studies.common.procedural_envmap. --quick is a tiny version (smoke
test).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from studies import ambiguity, joint_fit, noise, sg_fit

STUDIES = dict(A=noise, B=sg_fit, C=ambiguity, DE=joint_fit)  # each: Sizes, QUICK and run(out, sizes, device)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/studies")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--only", default="A,B,C,DE", help="comma-separated subset of A, B, C, DE")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    for key in (k.strip().upper() for k in args.only.split(",")):
        if key not in STUDIES:
            ap.error(f"unknown study {key!r}; choose from {', '.join(STUDIES)}")
        study = STUDIES[key]
        s = study.QUICK if args.quick else study.Sizes()
        t0 = time.perf_counter()
        print(f"\n== Figure {key} ({'quick' if args.quick else 'default'} sizes, {device}) ==")
        torch.manual_seed(0)
        print(study.run(out, s, device))
        print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
