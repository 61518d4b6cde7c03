"""Where runs place a known sun as it goes round: the example car (``datagen.example_scene``) rendered by Cycles
under the example sky, its sun turned about the vertical in ``--turns`` steps, seen from the example photo's camera
(15 degrees up, 80 units away, the car small and off-centre: ``make demo``'s input at turn 0) and from each run's
training camera; every view read by every run as ``predict`` reads a photo, and the angle between the predicted
and the true sun measured (the eval's dominant direction).

    python -m pipelines.light_turns --runs models/glossy-sg models/metallic-sg --out results/light-turns

One photo under one sun is one draw: the angle depends on where the sun stands relative to the camera. The median
over the turns is the photo's number a model can be compared by. Writes into --out: ``light_turns.md`` (per run and
camera: the median angle over the turns, the share within 25 degrees, the worst turn, turn 0),
``light_turns.json`` (every turn), ``light_turns.png`` (the angle against the sun's azimuth from the camera's, and
every predicted map under the true one, both suns marked) and ``renders/`` (the Cycles views: kept, so a second
call with the same turns and samples renders nothing).
"""
from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

import numpy as np
import torch

from datagen import example_scene as scene
from dibrpp.cli_args import Parser, check_output_folder, int_in
from dibrpp.display import tonemap_envmap
from dibrpp.formatting import markdown_table, pyplot, save_figure
from dibrpp.io import DataError, atomic_path, read_exr, write_exr

from .evaluation.metrics import dominant_direction
from .photo_input import read_view, sun_angle_deg
from .training.runs import load_camera, load_run, run_folder

TARGET_DEG = 25.0  # the light's target for the example photo (a sun within 25 degrees)
CAMERAS = ("photo", "training")


def sun_azimuths(turns: int) -> list[float]:
    """The true sun's azimuth (degrees) at each turn: the example's, then turned by 360 / turns a step."""
    return [scene.SUN_AZIMUTH + 360.0 * k / turns for k in range(turns)]


def relative_azimuth(sun_azimuth: float) -> float:
    """The sun's azimuth from the camera's, in [-180, 180): 0 is the sun behind the camera (the car lit from the
    front), -180 the sun behind the car."""
    return (sun_azimuth - scene.PHOTO_AZIMUTH + 180.0) % 360.0 - 180.0


def camera_setup(name: str, trained: dict) -> dict:
    """The orbit camera (distance, elevation_deg, fov_deg) a view of camera ``name`` is read with: the photo at its
    own elevation and the training distance, as ``make demo`` reads it (re-framed); the training view as trained."""
    return dict(trained, elevation_deg=scene.PHOTO_ELEVATION) if name == "photo" else dict(trained)


def render_path(folder: Path, name: str, trained: dict, turn: int, turns: int, spp: int) -> Path:
    """The cached Cycles view of camera ``name`` at ``turn`` of ``turns`` (named by everything that sets it)."""
    if name == "photo":
        key = "photo"
    else:
        key = f"training-el{trained['elevation_deg']:g}-d{trained['distance']:g}-s{trained['image_size']}"
    return folder / "renders" / f"{key}-spp{spp}-turn{turn}of{turns}.exr"


def render_view(path: Path, name: str, trained: dict, env: np.ndarray, spp: int, car) -> Path:
    """Render (once) the car under the sky ``env`` from camera ``name`` into ``path``."""
    if path.exists():
        return path
    if name == "photo":
        rgba = scene.photo(*car, env, spp)
    else:
        rgba = scene.render_car(*car, env, trained["distance"], trained["elevation_deg"], scene.PHOTO_AZIMUTH,
                                trained["fov_deg"], trained["image_size"], spp)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(path, rgba)
    return path


@torch.no_grad()
def read_turn(run, trained: dict, name: str, image: Path, true: torch.Tensor) -> dict:
    """One run's reading of one view taken under ``true``: the predicted world-frame map and the angle between its
    sun and the true."""
    setup = camera_setup(name, trained)
    rgba = torch.from_numpy(np.ascontiguousarray(read_exr(image, "RGBA"))).float()
    pred, cam, _ = read_view(run.model, rgba, image, trained, setup, scene.PHOTO_AZIMUTH, say=lambda _: None)
    predicted = pred.light(cam.world_to_camera).to_envmap(64, 128).image[0]
    return dict(predicted=predicted, true=true, angle=sun_angle_deg(predicted, true))


def summary(angles: list[float]) -> dict:
    return dict(median_deg=statistics.median(angles), within_target=sum(a <= TARGET_DEG for a in angles) / len(angles),
                worst_deg=max(angles), turn0_deg=angles[0])


def measure(runs: list[Path], out: Path, turns: int, spp: int, say=print) -> tuple[dict, dict]:
    """Render what is missing and read every view with every run: ({run: {camera: {turns: [...], the summary}}},
    {(run, camera, turn): (the predicted map, the true map)} for the figure)."""
    car = scene.car_mesh()
    azimuths = sun_azimuths(turns)
    skies = [scene.sky(sun_azimuth=a) for a in azimuths]  # the true light of each turn, made once
    results, maps = {}, {}
    for run_dir in runs:
        run = load_run(run_dir)
        trained = dict(load_camera(run_dir), image_size=run.model.config.image_size)
        results[str(run_dir)] = {}
        for name in CAMERAS:
            rows = []
            for k, azimuth in enumerate(azimuths):
                path = render_path(out, name, trained, k, turns, spp)
                if not path.exists():
                    say(f"rendering the {name} camera's view, turn {k + 1} of {turns} (Cycles, {spp} spp)")
                image = render_view(path, name, trained, skies[k], spp, car)
                reading = read_turn(run, trained, name, image, torch.from_numpy(skies[k]))
                rows.append(dict(turn=k, sun_azimuth_deg=azimuth % 360.0, relative_azimuth_deg=relative_azimuth(azimuth),
                                 angle_deg=round(reading["angle"], 2)))
                maps[str(run_dir), name, k] = reading["predicted"], reading["true"]
            results[str(run_dir)][name] = dict(turns=rows, **summary([r["angle_deg"] for r in rows]))
            say(f"{run_dir}, {name} camera: median {results[str(run_dir)][name]['median_deg']:.1f} degrees over "
                f"{turns} turns")
    return results, maps


def table(results: dict, turns: int) -> str:
    rows = [(run, name, f"{r['median_deg']:.1f}", f"{100 * r['within_target']:.0f} %", f"{r['worst_deg']:.1f}",
             f"{r['turn0_deg']:.1f}") for run, cameras in results.items() for name, r in cameras.items()]
    return markdown_table(("run", "camera", f"sun, median over {turns} turns (°)", f"within {TARGET_DEG:g}°",
                           "worst turn (°)", "turn 0, the example photo's sun (°)"), rows, "llrrrr")


def sun_pixel(env: torch.Tensor) -> tuple[float, float]:
    """(column, row) of a map's dominant direction, for marking it on the map's picture."""
    from dibrpp.conventions import direction_to_equirect_uv

    d = dominant_direction(env[None])[0][0]
    u, v = direction_to_equirect_uv(d).tolist()
    return u * env.shape[1] - 0.5, v * env.shape[0] - 0.5


def figure(path: Path, results: dict, maps: dict, turns: int) -> Path:
    """Top: the angle against the sun's azimuth from the camera's, per run and camera. Below: the true maps in the
    first row, then each run and camera's predicted map per turn (true sun: a circle; predicted: a cross)."""
    plt = pyplot()
    keys = [(run, name) for run, cameras in results.items() for name in cameras]
    order = sorted(range(turns), key=lambda k: relative_azimuth(sun_azimuths(turns)[k]))  # columns as the plot's x
    fig = plt.figure(figsize=(1.5 * turns + 1.0, 3.6 + 0.85 * (len(keys) + 1)))
    outer = fig.add_gridspec(2, 1, height_ratios=[3.6, 0.85 * (len(keys) + 1)], hspace=0.22, top=0.95, bottom=0.02)
    grid = outer[1].subgridspec(len(keys) + 1, turns, hspace=0.12, wspace=0.06)
    ax = fig.add_subplot(outer[0])
    worst = max(r["angle_deg"] for run, name in keys for r in results[run][name]["turns"])
    for run, name in keys:
        rows = sorted(results[run][name]["turns"], key=lambda r: r["relative_azimuth_deg"])
        ax.plot([r["relative_azimuth_deg"] for r in rows], [r["angle_deg"] for r in rows], "o-" if name == "photo" else "s--",
                label=f"{Path(run).name}, {name} camera (median {results[run][name]['median_deg']:.0f}°)")
    ax.axhline(TARGET_DEG, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("the sun's azimuth from the camera's (°; 0: behind the camera, ±180: behind the car)", fontsize=8)
    ax.set_ylabel("predicted vs true sun (°)", fontsize=8)
    ax.set_xlim(-180, 180)
    ax.set_ylim(0, max(90.0, worst + 10.0) * 1.35)  # the top for the legend
    ax.legend(fontsize=6, loc="upper center", ncol=2)
    labels = [("true light", None)] + [(f"{Path(run).name}\n{name}", (run, name)) for run, name in keys]
    for i, (label, key) in enumerate(labels):
        for column, k in enumerate(order):
            cell = fig.add_subplot(grid[i, column])
            predicted, true = maps[(keys[0] if key is None else key) + (k,)]
            cell.imshow(tonemap_envmap(true if key is None else predicted).clamp(0, 1).numpy())
            cell.plot(*sun_pixel(true), "o", mfc="none", mec="yellow", ms=6)
            if key is not None:
                cell.plot(*sun_pixel(predicted), "x", color="red", ms=6)
            cell.set_xticks([])
            cell.set_yticks([])
            if i == 0:
                cell.set_title(f"sun {relative_azimuth(sun_azimuths(turns)[k]):+.0f}° from camera", fontsize=7)
            if column == 0:
                cell.set_ylabel(label, fontsize=6)
    fig.suptitle("the example car under the example sky, its sun turned: where each run places it", fontsize=10, y=0.99)
    return save_figure(fig, path, dpi=100, tight=False)  # the grids place themselves


def write_outputs(out: Path, results: dict, maps: dict, turns: int, spp: int) -> None:
    text = (f"# Where runs place a known sun as it goes round\n\n`python -m pipelines.light_turns` ({turns} turns, "
            f"Cycles at {spp} spp): the angle between the predicted and the true sun.\n\n" + table(results, turns) + "\n")
    with atomic_path(out / "light_turns.md") as tmp:
        tmp.write_text(text)
    with atomic_path(out / "light_turns.json") as tmp:
        tmp.write_text(json.dumps(dict(turns=turns, spp=spp, runs=results), indent=1))
    figure(out / "light_turns.png", results, maps, turns)


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.light_turns", description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, metavar="RUN", help="run folders (or models/<name>)")
    ap.add_argument("--out", default="results/light-turns", metavar="DIR",
                    help="folder for the table, the figure and the cached renders (default: results/light-turns)")
    ap.add_argument("--turns", type=int_in(1, 72), default=8, metavar="N",
                    help="positions of the sun, 360/N degrees apart, the example's first (default: 8)")
    ap.add_argument("--spp", type=int_in(1, 4096), default=128, metavar="N",
                    help="Cycles samples per pixel of the views (default: 128)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    try:
        check_output_folder("--out", out)
        runs = [run_folder(r) for r in args.runs]
        results, maps = measure(runs, out, args.turns, args.spp)
        write_outputs(out, results, maps, args.turns, args.spp)
    except (DataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(table(results, args.turns))
    print(f"wrote {out}/light_turns.md, light_turns.json, light_turns.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
