"""Table A, renderer scaling: prints tables and writes Markdown/CSV under --out.

    python -m benchmarks.renderer --out results/bench [--quick] [--repeats 5]

(a) the training workload (32 renders of 64x64, 642-vertex sphere, SG K=32), forward and forward+backward;
(b) shading cost at 256x256 (rasterization cached, G-buffer built in the timing; the compiled SG rows build it
    compiled too, as training does): SG for K in 1..128 and MC for N in 1..1024 (Table A's shape);
(c) rasterization alone for 1k/10k/100k faces at 64^2, 128^2, 256^2 (cost ~ pixels + faces, not their product).
Peak memory is the process's peak RSS above its level before the case (Linux /proc).
"""
from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import torch

from benchmarks.memory import reset_peak_rss, rss_mb
from dibrpp import Cameras, Material, RasterSettings, Renderer, icosphere, rasterize
from dibrpp.cli_args import Parser, check_output_folder, positive_int
from dibrpp.io import DataError
from dibrpp.lights import EnvMap, SGLight
from dibrpp.renderer import build_gbuffer, build_gbuffer_compiled
from dibrpp.shading import MCShader, SGShader
from dibrpp.formatting import format_number, markdown_table, write_csv

SG_FLOP_PER_PIXEL_LOBE = 180  # inner products of the diffuse and specular lobes, RGB


def measure(fn, repeats: int, warmup: int = 1) -> tuple[float, float]:
    """Median seconds per call and peak RSS growth (MB) while calling ``fn``."""
    for _ in range(warmup):
        fn()
    reset_peak_rss()
    base = rss_mb("VmRSS")
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2], max(0.0, rss_mb("VmHWM") - base)


def random_sg_light(k: int, batch: int = 1, seed: int = 0) -> SGLight:
    g = torch.Generator().manual_seed(seed)
    return SGLight(torch.randn(batch, k, 3, generator=g), 5 + 20 * torch.rand(batch, k, generator=g),
                   torch.rand(batch, k, 3, generator=g))


def synthetic_envmap(h: int = 128, w: int = 256) -> EnvMap:
    from dibrpp.conventions import equirect_directions

    d = equirect_directions(h, w)
    sky = 0.4 + 0.6 * d[..., 2:].clamp_min(0) * torch.tensor([0.5, 0.7, 1.0])
    sun = 50 * torch.exp(200 * ((d * torch.nn.functional.normalize(torch.tensor([0.3, 0.5, 0.8]), dim=0)).sum(-1, keepdim=True) - 1))
    return EnvMap((sky + sun).unsqueeze(0))


def bench_training(repeats: int) -> list[dict]:
    # the encoder's template (radius 12) seen like the datasets: distance 60, elevation 27, fov 39.6
    sphere = icosphere(3, radius=12.0)
    cams = Cameras.orbit(60.0, 27.0, torch.arange(32.0) * (360 / 32), 39.6, 64)
    light = random_sg_light(32, batch=32)
    verts = sphere.verts.expand(32, -1, -1).clone().requires_grad_(True)
    tex = torch.rand(32, 64, 128, 3, requires_grad=True)
    lam = light.sharpness.clone().requires_grad_(True)
    rows = []

    for compile in (False, True):
        renderer = Renderer("sg", raster_settings=RasterSettings(cull_backfaces=True), compile=compile)

        def forward():
            mat = Material(albedo=tex, roughness=torch.full((32,), 0.3), specular=torch.full((32,), 0.5), wrap_u=True)
            lt = SGLight(light.axis, lam, light.amplitude)
            return renderer(sphere.with_verts(verts), cams, mat, lt).image

        def fwd():
            with torch.no_grad():
                forward()

        def fwd_bwd():
            forward().sum().backward()

        for name, fn in (("forward", fwd), ("forward+backward", fwd_bwd)):
            t, mem = measure(fn, repeats)
            rows.append({"case": f"training workload: 32 x 64^2, 642 verts, SG K=32{COMPILED[compile]}", "pass": name,
                         "ms": 1000 * t, "peak_mb": mem})
    return rows


COMPILED = {False: " (eager)", True: " (torch.compile)"}


def _sphere_gbuffer(res: int):
    sphere = icosphere(4, radius=1.0)
    cams = Cameras.orbit(3.0, 0.0, 0.0, 45.0, res)
    frags = rasterize(sphere, cams)
    return sphere, cams, frags


def bench_shading(res: int, sg_ks, mc_ns, repeats: int) -> list[dict]:
    sphere, cams, frags = _sphere_gbuffer(res)
    n_pix = int(frags.mask.sum())
    rows = []
    env = synthetic_envmap()
    # MC: the C++ kernel (used where only the env map needs a gradient: its backward gives the map's gradient),
    # then PyTorch's path replay (memory flat in N) and plain autograd (every sample's intermediates kept), both
    # with a roughness gradient too
    for kind, values in (("SG", sg_ks), ("SG-compiled", sg_ks), ("MC-kernel", mc_ns), ("MC", mc_ns),
                         ("MC-plain", mc_ns)):
        for v in values:
            rough = torch.tensor([0.3], requires_grad=kind != "MC-kernel")
            gbuffer = build_gbuffer_compiled if kind == "SG-compiled" else build_gbuffer
            if kind.startswith("SG"):
                shader, base = SGShader(compile=kind == "SG-compiled"), random_sg_light(v)
                make_light = lambda b=base: SGLight(b.axis, b.sharpness, b.amplitude.clone().requires_grad_(True))  # noqa: E731
            else:
                shader = MCShader(spp=v, mis=True, seed=0, replay=kind != "MC-plain", native=kind == "MC-kernel")
                make_light = lambda: EnvMap(env.image.clone().requires_grad_(True))  # noqa: E731

            def run(backward: bool):
                mat = Material(albedo=torch.tensor([[0.6, 0.5, 0.4]]), roughness=rough, specular=0.5)
                with torch.set_grad_enabled(backward):
                    out = shader(gbuffer(sphere, cams, mat, frags), make_light())
                    if backward:
                        out.sum().backward()

            for name, backward in (("forward", False), ("forward+backward", True)):
                reps = repeats if (not kind.startswith("MC") or v <= 64) else 1
                t, mem = measure(lambda: run(backward), reps, warmup=0 if reps == 1 else 1)
                row = {"case": f"{kind} {'N' if kind.startswith('MC') else 'K'}={v}, {res}^2 sphere ({n_pix} px)",
                       "pass": name, "ms": 1000 * t, "peak_mb": mem}
                if not kind.startswith("MC") and not backward:
                    row["flop_bound_ms"] = 1000 * SG_FLOP_PER_PIXEL_LOBE * n_pix * v / peak_flops()
                rows.append(row)
    return rows


def peak_flops() -> float:
    """Nominal fp32 peak of this CPU: cores x 2.5 GHz x 32 FLOP/cycle (AVX2, two FMA units)."""
    return torch.get_num_threads() * 2.5e9 * 32


def bench_raster(resolutions, face_counts, repeats: int) -> list[dict]:
    rows = []
    for faces in face_counts:
        sub = max(0, round(math.log(faces / 20, 4)))
        mesh = icosphere(sub)
        for res in resolutions:
            cams = Cameras.orbit(3.0, 20.0, 30.0, 45.0, res)
            t, mem = measure(lambda: rasterize(mesh, cams), repeats)
            rows.append({"case": f"rasterize {mesh.faces.shape[0]} faces at {res}^2", "pass": "forward", "ms": 1000 * t, "peak_mb": mem})
    return rows


# The supplementary's Table A: shading time (ms) of a 256^2 sphere on the paper's GPU (its "1204" read as 1024).
PAPER_TABLE_A = {"MC": {1: 4.0, 4: 3.7, 16: 5.0, 64: 9.1, 256: 28.3, 1024: 292.5},
                 "SG": {1: 2.6, 2: 2.8, 4: 2.6, 8: 2.6, 16: 2.9, 32: 2.9, 64: 2.5, 128: 2.7}}


def table_a(rows: list[dict]) -> str:
    """The paper's Table A layout: shading time per K (SG) and N (MC), ours beside the paper's GPU row."""
    def value(case_prefix, v, pass_, key="ms"):
        hit = [r for r in rows if r["case"].startswith(f"{case_prefix}={v},") and r["pass"] == pass_]
        return format_number(hit[0][key] if hit else None, f".{2 if key == 'flop_bound_ms' else 0}f")

    parts = []
    for kind, sym in (("SG", "K"), ("MC", "N")):
        vals = list(PAPER_TABLE_A[kind])
        body = []
        variants = ([("SG", "eager"), ("SG-compiled", "compiled")] if kind == "SG"
                    else [("MC-kernel", "with MIS, C++ kernel (env-map gradient)"), ("MC", "with MIS, path replay"),
                          ("MC-plain", "with MIS, plain autograd")])
        for prefix, label in variants:
            for pass_ in ("forward", "forward+backward"):
                body.append([f"ours {label}, {pass_} (ms)"] + [value(f"{prefix} {sym}", v, pass_) for v in vals])
        if kind == "SG":
            body.append(["FLOP bound, forward (ms)"] + [value("SG K", v, "forward", "flop_bound_ms") for v in vals])
        body.append(["paper, GPU, forward (ms)"] + [f"{t:.1f}" for t in PAPER_TABLE_A[kind].values()])
        parts.append(markdown_table([f"{kind}, {sym}", *vals], body, "l" + "r" * len(vals)))
    return "\n\n".join(parts)


def write_tables(rows: list[dict], out: Path) -> str:
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "renderer.csv", rows, ["case", "pass", "ms", "peak_mb", "flop_bound_ms"])
    text = markdown_table(["case", "pass", "time (ms)", "peak RSS (MB)", "SG FLOP bound (ms)"],
                          [[r["case"], r["pass"], f"{r['ms']:.1f}", f"{r['peak_mb']:.0f}",
                            format_number(r.get("flop_bound_ms"), ".2f", missing="")] for r in rows], "llrrr")
    (out / "renderer.md").write_text(text + "\n")
    summary = table_a(rows)
    (out / "table_a.md").write_text(summary + "\n")
    return text + "\n\nTable A (shading only, 256^2 sphere; the paper's row is its GPU):\n\n" + summary


def main(argv=None) -> int:
    ap = Parser(prog="python -m benchmarks.renderer", description=__doc__)
    ap.add_argument("--out", default="results/bench", metavar="DIR", help="results folder (made if missing)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes, one repeat (smoke test)")
    ap.add_argument("--repeats", type=positive_int, default=5, metavar="N", help="timed repeats of each case")
    args = ap.parse_args(argv)
    try:
        check_output_folder("--out", Path(args.out))
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    torch.manual_seed(0)
    if args.quick:
        rows = bench_training(1) + bench_shading(32, [1, 4], [1, 4], 1) + bench_raster([32], [1000], 1)
    else:
        rows = (bench_training(args.repeats)
                + bench_shading(256, [1, 2, 4, 8, 16, 32, 64, 128], [1, 4, 16, 64, 256, 1024], args.repeats)
                + bench_raster([64, 128, 256], [1000, 10000, 100000], args.repeats))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device cpu, pid {os.getpid()}")
    print(write_tables(rows, Path(args.out)))
    print(f"\nSG FLOP bound assumes {SG_FLOP_PER_PIXEL_LOBE} FLOP per pixel-lobe at a nominal {peak_flops() / 1e9:.0f} GFLOP/s.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
