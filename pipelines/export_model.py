"""Ship a trained run as a model a user can try without training: ``make models`` runs it for the models in models/.

    python -m pipelines.export_model --run runs/glossy/sg-seed0 --out models/glossy-sg

Writes into --out a run folder that ``pipelines.predict`` and ``pipelines.evaluate`` read like any other:
``checkpoint.pt`` (the model's weights in half precision, no optimizer state: a fifth of the run's checkpoint),
``config.json`` and ``camera.json`` as trained, ``metrics.json`` (the shipped weights evaluated on the test split of
the run's dataset as ``make eval`` evaluates, ~1 min) and ``MODEL_CARD.md``: the data, the recipe, the code's
commit, those metrics and the command that retrains it. The model is built in a temporary folder beside --out and
its files move into --out once all are written: a failed export (the run's dataset missing, say) leaves a model
already in --out as it was. --out may be neither the run folder nor inside it. The export is a model, not a
prediction: ``pipelines.predict`` with it writes the mesh, textures and ``model.glb``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import torch

from dibrpp.cli_args import Parser, check_output_folder
from dibrpp.formatting import format_number, markdown_table
from dibrpp.io import DataError, atomic_path, staged

from .evaluation.summary import CONSTANT_REFERENCES
from .scoring import EVAL_SPP, EVAL_VIEW_STRIDE, evaluate_run
from .training.runs import (CAMERA, CHECKPOINT, CONFIG, SUMMARY, load_camera, load_run, read_checkpoint, read_json,
                            run_folder)

REPO = Path(__file__).resolve().parents[1]
CARD, METRICS = "MODEL_CARD.md", "metrics.json"
# the card's metrics: (key, what it is); a light metric's constant-map score is shown beside it
CARD_METRICS = [("image_whole", "image L1, whole image"), ("iou", "2D IoU loss"), ("texture", "texture 1-NCC"),
                ("normal_deg", "normal error (°, median)"), ("light_ldr", "light eq. 9 (LDR maps)"),
                ("probe_metal", "rough-metal probe si-RMSE"), ("probe_mirror", "mirror probe si-RMSE"),
                ("direction_deg", "dominant light direction (°, median)")]


def half_precision(state: dict, parameters: set[str]) -> dict:
    """The model's learnt parameters in float16 (predict and evaluate load them into float32); buffers (the
    template mesh, its UVs, fixed bases) stay as they are."""
    return {k: v.half() if k in parameters and v.is_floating_point() else v for k, v in state.items()}


def git_commit() -> str:
    """The checkout's commit, marked '-dirty' where tracked files differ from it ('unknown' outside git)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "dibrpp", "datagen", "pipelines"],
                               cwd=REPO).returncode != 0
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def metrics_table(metrics: dict) -> str:
    rows = []
    for key, what in CARD_METRICS:
        value = metrics.get(key)
        constant = metrics.get(f"{key}_constant") if f"{key}_constant" in CONSTANT_REFERENCES else None
        rows.append([what, format_number(value, ".3g") if value is not None else "—",
                     format_number(constant, ".3g") if constant is not None else ""])
    return markdown_table(["test split", "this model", "a constant map"], rows)


def model_card(name: str, config: dict, camera: dict, metrics: dict, iteration: int, seconds: float | None,
               commit: str, retrain: str) -> str:
    dataset = Path(config["dataset"]).name
    took = f", {seconds / 60:.0f} min on the machine that trained it" if seconds else ""
    learnt_specular = config.get("specular", "learnt") == "learnt"  # runs written before the option learnt it
    return "\n".join([
        f"# {name}", "",
        f"DIB-R++'s single-image model as this repository trains it by default: **{config['shading'].upper()} shading, "
        f"{config['lobes']} lobes**, trained on the `{dataset}` set (Blender Cycles, `make data-{dataset}`) for "
        f"{iteration} iterations, seed {config['seed']}{took}.", "",
        f"- **Input:** one {camera.get('image_size', '')}{'²' if camera.get('image_size') else ''} view of a car of "
        f"that set's kind, its mask as alpha; the training camera: distance {camera['distance']:g}, elevation "
        f"{camera['elevation_deg']:g}°, field of view {camera['fov_deg']:.1f}°; `predict` frames a photo's object as "
        "these views frame theirs (`--framing`).",
        "- **Output:** a mesh (the template deformed), an albedo texture, roughness"
        f"{' / metallic' if config.get('predict_metallic') else ''}"
        f"{' / specular' if learnt_specular else ' (a dielectric specular level of 0.5)'}, "
        f"the light as {config['lobes']} SG lobes "
        "(world frame, written as an env map).",
        f"- **Code:** commit `{commit}`; weights in half precision (evaluated as shipped).",
        f"- **Retrain:** `{retrain}`; another machine's rounding moves a retrain's metrics as another seed does: "
        "within the seed spread of docs/results.md (the default with a sky and a ground).", "",
        f"## Test split of `{dataset}` ({metrics.get('test_views', '?')} views; `make eval`'s metrics)", "",
        metrics_table(metrics), "",
        "Lower is better everywhere. What the numbers mean and how they compare with the paper: docs/evaluation.md "
        "and docs/results.md.", "",
        "## What to expect", "",
        "Objects like the training set's, cut out, seen from about the training elevation. A photo of something "
        "else gives a car-like shape; an 8-bit photo clips the highlights the light is read from, so an EXR of the "
        "view places the light better (docs/evaluation.md, prediction on your own image).", ""])


def check_out_beside_run(run: Path, out: Path) -> None:
    """A :class:`DataError` where ``out`` is the run folder or inside it (the export would overwrite the run's own
    checkpoint with its half-precision copy)."""
    run_at, out_at = Path(run).resolve(), Path(out).resolve()
    if out_at == run_at or run_at in out_at.parents:
        where = "is the run folder" if out_at == run_at else f"is inside the run folder {run}"
        raise DataError(f"--out {out}: {where}, whose checkpoint the export would overwrite; give the model a folder of "
                        "its own beside the run (e.g. models/<name>)")


def export(run: Path, out: Path, retrain: str, commit: str | None = None) -> Path:
    check_out_beside_run(run, out)
    loaded = load_run(run)  # refuses a broken run before anything is written
    state = read_checkpoint(run / CHECKPOINT)
    parameters = {name for name, _ in loaded.model.named_parameters()}
    shipped = {"model": half_precision(state["model"], parameters), "model_config": state["model_config"],
               "iteration": state["iteration"], "config": state.get("config")}
    with staged(out) as folder:  # every file in place at once, or none
        with atomic_path(folder / CHECKPOINT) as tmp:
            torch.save(shipped, tmp)
        for name in (CONFIG, CAMERA):
            shutil.copyfile(run / name, folder / name)
        print(f"evaluating the shipped weights for {out} on the test split of {loaded.config.dataset}", flush=True)
        metrics, _ = evaluate_run(folder, eval_spp=EVAL_SPP, view_stride=EVAL_VIEW_STRIDE)
        metrics["run"] = str(out)  # the model's own folder, not the one it is staged in
        with atomic_path(folder / METRICS) as tmp:
            tmp.write_text(json.dumps(metrics, indent=1))
        summary = read_json(run / SUMMARY, "training summary") if (run / SUMMARY).exists() else {}
        camera = {**load_camera(run), "image_size": loaded.model.config.image_size}
        card = model_card(Path(out).resolve().name, loaded.config.to_dict(), camera, metrics, loaded.iteration,
                          summary.get("seconds"), commit or git_commit(), retrain)
        with atomic_path(folder / CARD) as tmp:
            tmp.write_text(card)
    return out


def folder(text: str) -> Path:
    """An argument type: a folder's path (an empty string would mean the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a folder, got an empty string")
    return Path(text)


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.export_model", description=__doc__)
    ap.add_argument("--run", required=True, type=folder, metavar="DIR", help="a trained run folder")
    ap.add_argument("--out", required=True, type=folder, metavar="DIR",
                    help="the model's folder (made if missing; not the run folder nor inside it)")
    ap.add_argument("--retrain", default="", metavar="COMMAND", help="the command that retrains it, for the card")
    ap.add_argument("--commit", metavar="SHA", help="the code's commit, for the card (default: this checkout's)")
    args = ap.parse_args(argv)
    try:
        check_output_folder("--out", args.out)
        run_folder(args.run)  # a missing or broken run: said before anything is written
        check_out_beside_run(args.run, args.out)
        out = export(args.run, args.out, args.retrain or f"python -m pipelines.train --out {args.run}", args.commit)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the disk filled up, or a folder went away while exporting: --out is as it was
        print(f"error: --out {args.out}: cannot write the model ({e}); free space or choose another folder",
              file=sys.stderr)
        return 2
    size = (out / CHECKPOINT).stat().st_size / 2 ** 20
    print(f"wrote {out}/: {CHECKPOINT} ({size:.1f} MiB), {CONFIG}, {CAMERA}, {METRICS}, {CARD}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
