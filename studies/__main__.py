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

import sys
import time
from pathlib import Path

import torch

from dibrpp.cli_args import Parser, check_output_folder, non_negative_int
from dibrpp.io import DataError
from studies import ambiguity, joint_fit, noise, sg_fit

STUDIES = dict(A=noise, B=sg_fit, C=ambiguity, DE=joint_fit)  # each: Sizes, QUICK and run(out, sizes, device)


def build_parser() -> Parser:
    ap = Parser(prog="python -m studies", description=__doc__)
    ap.add_argument("--out", default="results/studies", metavar="DIR", help="results folder (made if missing)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--only", default="A,B,C,DE", help="comma-separated subset of A, B, C, DE")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="torch device of the renders")
    ap.add_argument("--threads", type=non_negative_int, default=0, metavar="N",
                    help="torch CPU threads; 0: as many as torch chooses (default: 0)")
    return ap


def chosen_studies(only: str) -> list[str]:
    """The keys of ``--only``, in its order; a DataError naming an unknown one."""
    keys = [k.strip().upper() for k in only.split(",")]
    unknown = [k for k in keys if k not in STUDIES]
    if unknown:
        raise DataError(f"--only {only}: unknown study {unknown[0]!r}; choose from {', '.join(STUDIES)}")
    return keys


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        keys = chosen_studies(args.only)
        check_output_folder("--out", Path(args.out))
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    for key in keys:
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
