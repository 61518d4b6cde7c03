"""python -m datagen --dataset {metallic,glossy,diffuse} --out DIR [--envmaps DIR [--procedural-envmaps N]] [options]"""
from __future__ import annotations

import argparse
import sys

from dibrpp.cli_args import Parser, elevation_list, non_negative_int, positive_int, unit_fraction


def preset_default(key: str) -> str:
    """What a preset-driven flag defaults to: "default: from --preset: 32 with default (64 for diffuse); ..."."""
    from .config import DATASET_DEFAULTS, PRESETS

    parts = []
    for name in sorted(PRESETS):
        extra = [f"{v[key]} for {ds}" for ds, v in DATASET_DEFAULTS.items() if name == "default" and key in v]
        parts.append(f"{PRESETS[name][key]} with {name}" + (f" ({', '.join(extra)})" if extra else ""))
    return "default: from --preset: " + "; ".join(parts)


def _preset_flags(p: argparse.ArgumentParser) -> None:
    """The sizes a preset sets; given, they override it."""
    sized = dict(num_objects="objects", num_envmaps="number of procedural env maps (without --envmaps)",
                 envs_per_object="env maps each object is rendered under", resolution="image side in pixels",
                 spp="Cycles samples per pixel", texture_size="side of the procedural textures in pixels",
                 envmap_height="env map height (width is twice that)",
                 grid="marching-cubes grid of the procedural shapes")
    for key, text in sized.items():
        p.add_argument("--" + key.replace("_", "-"), type=positive_int, metavar="N",
                       help=f"{text} ({preset_default(key)})")
    p.add_argument("--views", type=positive_int, metavar="N",
                   help="views per object (default: 24; 12 front views for diffuse)")
    p.add_argument("--max-bounces", type=non_negative_int, metavar="N",
                   help=f"Cycles light bounces ({preset_default('max_bounces')})")
    p.add_argument("--elevations", type=elevation_list, metavar="DEG[,DEG...]",
                   help="camera elevations in degrees that the views take in turn, starting one later on each next "
                        "object, so that every azimuth is seen from every elevation (default: every view at 27); "
                        "e.g. 12,22,32,42 (make data-glossy-elevations)")


def build_parser() -> argparse.ArgumentParser:
    from .config import DATASETS, PRESETS

    p = Parser(prog="python -m datagen", description=(
        "Generate a procedural DIB-R++ dataset (metallic / glossy cars, diffuse heads) with Blender Cycles. "
        "Deterministic, resumable (rerun the same command), shardable."))
    p.add_argument("--dataset", required=True, choices=DATASETS,
                   help="what to make: metallic or glossy cars, or diffuse (subsurface) heads")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created; reruns resume into it)")
    p.add_argument("--preset", default="default", choices=sorted(PRESETS),
                   help="default: small, for 2 cores; paper: the paper's sizes (485 objects, 256 px)")
    p.add_argument("--envmaps", metavar="DIR",
                   help="light with your own equirect HDRIs: every .exr / .hdr file of DIR (sorted by name; 2:1, "
                        "Blender's orientation: +Z up, +X at the centre), resampled to --envmap-height; "
                        "instead of the procedural maps")
    p.add_argument("--procedural-envmaps", type=non_negative_int, metavar="N",
                   help="with --envmaps: add N procedural maps to the files (default 0); each kind is split 4:1")
    p.add_argument("--outdoor-share", type=unit_fraction, metavar="F",
                   help="share of the procedural env maps that are outdoor skies, the rest rooms (default 0.6; 1: "
                        "skies only, e.g. a test set with many suns)")
    _preset_flags(p)
    p.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=None,
                   help="denoise the shaded renders with OpenImageDenoise (albedo + normal guides); default: on for "
                        "the diffuse set (64 spp), off for the others")
    p.add_argument("--seed", type=non_negative_int, default=0, metavar="N",
                   help="seed of every random choice (shapes, materials, maps, splits, Cycles)")
    p.add_argument("--workers", type=positive_int, default=2, metavar="N",
                   help="worker processes (bpy is not thread-safe)")
    p.add_argument("--cycles-device", choices=("cpu", "gpu"), default="cpu",
                   help="where Cycles renders the views: cpu, or gpu (OptiX, CUDA, HIP, Metal or oneAPI, whichever "
                        "Cycles finds); env maps, shapes and textures are made on the CPU either way, so only the "
                        "views' noise differs between devices")
    p.add_argument("--recycle", type=positive_int, default=4, metavar="N",
                   help="tasks per worker process before it is replaced")
    p.add_argument("--shard", default="0/1", metavar="I/N", help="i/n: generate only objects with index %% n == i")
    p.add_argument("--no-preview", action="store_true",
                   help="do not write preview.png, the contact sheet (a few objects' views, their albedo, env "
                        "maps) written once every sample is done")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def check_gpu() -> None:
    """Refuse ``--cycles-device gpu`` before anything is written where Cycles finds no GPU (asked in a worker
    process, as every render is: the parent does not load bpy)."""
    from .cycles.settings import gpu_backend
    from .workers import completed

    if next(completed([(gpu_backend, ())], workers=1, threads=0, recycle=1)) is None:
        raise ValueError("--cycles-device gpu: Cycles finds no GPU on this machine (OptiX, CUDA, HIP, Metal, "
                         "oneAPI); render with --cycles-device cpu")


def main(argv=None) -> int:
    from dibrpp.io import DataError

    from .config import make_config, parse_shard
    from .generate import generate

    args = build_parser().parse_args(argv)
    try:
        cfg = make_config(args.dataset, args.preset, num_objects=args.num_objects, num_envmaps=args.num_envmaps,
                          envs_per_object=args.envs_per_object, views=args.views, resolution=args.resolution,
                          spp=args.spp, seed=args.seed, texture_size=args.texture_size,
                          envmap_height=args.envmap_height, max_bounces=args.max_bounces,
                          grid=args.grid, envmaps=args.envmaps, procedural_envmaps=args.procedural_envmaps,
                          denoise=args.denoise, outdoor_share=args.outdoor_share, elevations=args.elevations)
        shard = parse_shard(args.shard)
        if args.cycles_device == "gpu":
            check_gpu()
        stats = generate(cfg, args.out, workers=args.workers, shard=shard, recycle=args.recycle,
                         progress=not args.quiet, preview=not args.no_preview,
                         cycles_device=args.cycles_device.upper())
    except (ValueError, DataError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    spv = stats["seconds_per_view"]
    ov = stats["render_overhead"]
    print(f"{cfg.dataset}: {stats['rendered_views']} views rendered, {stats['skipped_samples']} samples already done, "
          f"wall {stats['wall_s']:.1f}s" + (f", {spv:.2f}s/view per worker, overhead {100 * ov:.1f}% above Cycles"
                                              if spv else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
