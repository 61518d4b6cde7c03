"""``python -m dibrpp render``: render a mesh under an HDR environment map. ``python -m dibrpp build-kernels``:
build the C++ kernels (:mod:`dibrpp.native`).

Bad input prints one line ``error: ...`` and exits with status 2, writing nothing.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

from .cli_args import Parser, check_writable, unit_rgb

MAX_SPP = 16384  # samples per pixel: far past where MC noise stops showing
MAX_SAMPLES = 2 ** 30  # samples in one render: ~1024² pixels at 1024 spp, an hour or more on 2 cores


class CLIError(Exception):
    pass


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="python -m dibrpp", description="DIB-R++ hybrid differentiable renderer")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    r = sub.add_parser("render", help="render a mesh under an environment map")
    r.add_argument("--mesh", required=True, help="OBJ/PLY/GLB (anything trimesh reads)")
    colour = r.add_mutually_exclusive_group()
    colour.add_argument("--texture", help="sRGB PNG albedo texture (uses the mesh's UVs)")
    colour.add_argument("--albedo", type=unit_rgb, default=(0.8, 0.8, 0.8), metavar="R,G,B",
                        help="linear base colour (default: 0.8,0.8,0.8)")
    r.add_argument("--roughness", type=float, default=0.5, help="Principled Roughness in [0, 1]")
    r.add_argument("--metallic", type=float, default=0.0, help="Principled Metallic in [0, 1]")
    r.add_argument("--specular", type=float, default=0.5, help="Principled Specular IOR Level (0.5 => F0 = 0.04)")
    r.add_argument("--envmap", help="equirectangular HDR environment map (.exr); required unless --albedo-only")
    r.add_argument("--shading", choices=["mc", "sg", "sh"], default="mc",
                   help="Monte-Carlo, Spherical Gaussians or spherical harmonics")
    r.add_argument("--spp", type=int, default=256, help="samples per pixel (mc)")
    r.add_argument("--sg-lobes", type=int, default=32, help="number of SG lobes fitted to the env map (sg)")
    r.add_argument("--distance", type=float, default=3.0,
                   help="orbit camera distance from the origin; beyond the mesh's radius about it (a dataset's "
                        "object, in [-18, 18]: 60)")
    r.add_argument("--elevation", type=float, default=0.0, help="degrees")
    r.add_argument("--azimuth", type=float, default=0.0, help="degrees")
    r.add_argument("--fov", type=float, default=40.0, help="full field of view in degrees (Blender's camera angle)")
    r.add_argument("--resolution", type=int, default=256, help="square image side in pixels")
    r.add_argument("--albedo-only", action="store_true", help="render the unlit base colour")
    r.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="torch device of the render")
    r.add_argument("--seed", type=int, default=0, help="random seed of the MC sampler")
    r.add_argument("--out", required=True, help="output image: .exr (linear RGBA) or .png (sRGB preview)")
    sub.add_parser("build-kernels", help="build dibrpp's C++ kernels now (make setup does), not at the first render")
    return parser


def _check_out(out: str) -> None:
    """A .exr / .png file name in an existing folder this process can write to (checked now, not after
    the render)."""
    if Path(out).suffix.lower() not in (".exr", ".png"):
        raise CLIError(f"--out {out}: use a .exr (linear RGBA) or .png (sRGB) file name")
    if Path(out).is_dir():
        raise CLIError(f"--out {out}: is a folder; give a file name inside it")
    out_dir = Path(out).resolve().parent
    if not out_dir.is_dir():
        raise CLIError(f"--out {out}: folder {out_dir} does not exist")
    check_writable("--out", out, out_dir)


def _check(args) -> None:
    for flag, path in (("--mesh", args.mesh), ("--texture", args.texture), ("--envmap", args.envmap)):
        if path is not None and Path(path).is_dir():
            raise CLIError(f"{flag} {path}: is a folder; {flag} takes one file")
        if path is not None and not Path(path).is_file():
            raise CLIError(f"{flag} {path}: no such file")
    _check_out(args.out)
    for name in ("roughness", "metallic", "specular", "distance", "elevation", "azimuth", "fov"):
        if not math.isfinite(getattr(args, name)):
            raise CLIError(f"--{name} {getattr(args, name)}: must be a finite number")
    for name, lo, hi in (("roughness", 0, 1), ("metallic", 0, 1), ("specular", 0, 1)):
        value = getattr(args, name)
        if not lo <= value <= hi:
            raise CLIError(f"--{name} {value}: must be in [{lo}, {hi}]")
    if args.resolution <= 0 or args.resolution > 8192:
        raise CLIError(f"--resolution {args.resolution}: must be in 1..8192")
    if not 1 <= args.spp <= MAX_SPP:
        raise CLIError(f"--spp {args.spp}: must be in 1..{MAX_SPP}")
    if args.shading == "mc" and args.spp * args.resolution ** 2 > MAX_SAMPLES:
        raise CLIError(f"--spp {args.spp} at --resolution {args.resolution}: {args.spp * args.resolution ** 2:.3g} "
                       f"samples, more than {MAX_SAMPLES:.3g} (hours on a CPU); lower one of them")
    if args.sg_lobes <= 0:
        raise CLIError(f"--sg-lobes {args.sg_lobes}: must be positive")
    if not 0 < args.fov < 180:
        raise CLIError(f"--fov {args.fov}: must be in (0, 180) degrees")
    if args.distance <= 0:
        raise CLIError(f"--distance {args.distance}: must be positive")
    if not args.albedo_only and not args.envmap:
        raise CLIError("--envmap is required (or pass --albedo-only)")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise CLIError("--device cuda: no CUDA device is available to torch here; use --device cpu")


def _check_equirect(path, env) -> None:
    if env.width != 2 * env.height or env.height < 2:
        raise CLIError(f"--envmap {path}: {env.width} x {env.height} pixels is not an equirectangular map (width "
                       "must be exactly twice the height); convert it to a 2:1 latitude-longitude map")


def _check_mesh(args, mesh) -> None:
    """Refuse a mesh that would render as nothing (no triangle with area) or a camera inside it (everything)."""
    verts = mesh.verts[0].double()
    corners = verts[mesh.faces]
    areas = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1).norm(dim=-1)
    size = float((verts.amax(0) - verts.amin(0)).norm())
    if not (areas > 1e-12 * size ** 2).any():  # relative: float rounding leaves collinear corners a tiny area
        raise CLIError(f"--mesh {args.mesh}: the mesh has no triangle with area (all {len(mesh.faces)} have "
                       "repeated or collinear corners); there is nothing to render")
    # The camera orbits the origin; outside this sphere every vertex lies in front of it.
    radius = float(verts.norm(dim=-1).max())
    if args.distance <= radius:
        raise CLIError(f"--distance {args.distance:g}: the camera at distance {args.distance:g} is inside the mesh's "
                       f"bounds (radius {radius:.3g} around the origin it looks at); pass --distance larger than "
                       f"{radius:.3g}, e.g. {3 * radius:.3g}")


def render_command(args) -> None:
    from . import io
    from .brdf import Material
    from .camera import Cameras
    from .conventions import srgb_to_linear
    from .renderer import Renderer

    _check(args)
    device = torch.device(args.device)
    mesh = io.load_mesh(args.mesh, device=device, with_uvs=bool(args.texture))
    _check_mesh(args, mesh)
    if args.texture:
        tex = srgb_to_linear(torch.from_numpy(io.read_png(args.texture)[..., :3])).unsqueeze(0).to(device)
        albedo = tex
    else:
        albedo = torch.tensor([args.albedo], device=device)
    material = Material(albedo=albedo, roughness=args.roughness, metallic=args.metallic, specular=args.specular)
    cameras = Cameras.orbit(args.distance, args.elevation, args.azimuth, args.fov, args.resolution, device=device)
    what = "albedo" if args.albedo_only else args.shading + (f", {args.spp} spp" if args.shading == "mc" else "")
    print(f"rendering {args.mesh} at {args.resolution}x{args.resolution} ({what})", flush=True)
    if args.albedo_only:
        image = Renderer("sg").render_albedo(mesh, cameras, material).image[0]
    else:
        from .lights import EnvMap, fit_sg_to_envmap, project_envmap_to_sh

        env = EnvMap.from_exr(args.envmap).to(device)
        _check_equirect(args.envmap, env)
        if args.shading == "sg":
            print(f"fitting {args.sg_lobes} SG lobes to {args.envmap}", flush=True)
        light = {"mc": lambda: env, "sg": lambda: fit_sg_to_envmap(env, args.sg_lobes),
                 "sh": lambda: project_envmap_to_sh(env)}[args.shading]()
        with torch.no_grad():
            image = Renderer(args.shading, spp=args.spp, seed=args.seed)(mesh, cameras, material, light).image[0]
    try:
        io.write_image(args.out, image)
    except OSError as e:  # e.g. the disk filled up or the folder changed during the render
        raise CLIError(f"--out {args.out}: cannot write the image ({e})") from None
    print(f"wrote {args.out}")


def main(argv=None) -> int:
    from .io import DataError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "render":
            render_command(args)
        elif args.command == "build-kernels":
            from .native import build

            return build()
    except (CLIError, DataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0
