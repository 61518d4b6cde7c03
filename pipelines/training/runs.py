"""The run folder, its one owner: what ``pipelines.train`` writes and evaluate / predict / benchmarks read.

    runs/glossy/sg-seed0/
      config.json      the TrainConfig the run was trained with
      camera.json      the orbit camera of its training data (predict places the input camera with it)
      checkpoint.pt    model, model configuration, optimiser, iteration, RNG (tensors and plain data only)
      log.csv, loss.png, summary.json, snapshots/, tensorboard/
      pixel_normals.pt the pixel-normal network fitted before the model trained, read in evaluation (variant
                       pixel-normals only)

Also the objects a run is built from (model, optimiser, renderer), so that every entry point builds them the
same way without importing another entry point.
"""
from __future__ import annotations

import hashlib
import json
import math
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset
from dibrpp import RasterSettings, Renderer
from dibrpp.io import DataError, atomic_path

from ..model import pixel_normals
from .config import ConfigError, TrainConfig
from .earlier_runs import (RetiredError, earlier_model_config, earlier_state_dict, earlier_train_config,
                           is_earlier_config, without_options_left_later)
from ..model.encoder import MODEL_VERSION, Encoder, ModelConfig
from ..model.model_input import encoder_input

CONFIG, CAMERA, CHECKPOINT = "config.json", "camera.json", "checkpoint.pt"
MAX_TEMPLATE_SUBDIVISIONS = 6  # 40962 template vertices; each level more quadruples them
# the global code (shape, material) read off a map of at most 4 x 4 at any input size: one more downsampling block per
# doubling above 64², so the fully connected layer is the same at any size (docs/scale.md)
GLOBAL_GRID = 4
PIXEL_NORMALS = "pixel_normals.pt"  # variant pixel-normals: the network fitted before the model trains
LOG, SUMMARY, LOSS_PLOT, SNAPSHOTS, TENSORBOARD = "log.csv", "summary.json", "loss.png", "snapshots", "tensorboard"


def is_run(folder: Path) -> bool:
    return (Path(folder) / CHECKPOINT).is_file() and (Path(folder) / CONFIG).is_file()


def find_runs(root: Path) -> list[Path]:
    """Every run folder under ``root`` (``root`` itself if it is one)."""
    return sorted(p.parent for p in Path(root).rglob(CHECKPOINT) if (p.parent / CONFIG).exists())


def run_folder(path: Path) -> Path:
    """A run folder from a path to it or to its checkpoint; an error naming what is missing otherwise."""
    run = Path(path)
    if run.name == CHECKPOINT:
        run = run.parent
    if not is_run(run):
        raise DataError(f"{run}: not a run folder (needs {CONFIG} and {CHECKPOINT} from pipelines.train)")
    return run


# ----------------------------------------------------------------------------- config and camera

def read_json(path: Path, what: str):
    try:
        return json.loads(Path(path).read_text())
    except OSError as e:
        raise DataError(f"{path}: cannot read the {what} ({e.strerror})") from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: the {what} is not valid JSON ({e})") from e


def load_config(run: Path) -> TrainConfig:
    """The TrainConfig saved with a run, checked like any config (a run written before the retired experiments left
    the code: :mod:`.earlier_runs`)."""
    path = Path(run) / CONFIG
    try:
        saved = read_json(path, "run's configuration")  # from_dict refuses what is not a JSON object
        if isinstance(saved, dict):
            saved = without_options_left_later(saved)
        if isinstance(saved, dict) and is_earlier_config(saved):
            saved = earlier_train_config(saved, _trained_light_head(Path(run)))
        if isinstance(saved, dict):
            saved.setdefault("specular", "learnt")  # a run written before the option learnt its specular level
            saved.pop("global_grid", None)  # the map the global code is read off: the checkpoint's model says it
        config = TrainConfig.from_dict(saved)
    except (ConfigError, RetiredError) as e:
        raise DataError(f"{path}: {e}") from e
    return config


def _trained_light_head(run: Path) -> str | None:
    """The light head of a run's checkpointed model, where its config may say 'auto' (None: no checkpoint)."""
    if not (run / CHECKPOINT).exists():
        return None
    return read_checkpoint(run / CHECKPOINT).get("model_config", {}).get("light_head")


def save_config(run: Path, config: TrainConfig) -> None:
    with atomic_path(Path(run) / CONFIG) as tmp:
        tmp.write_text(json.dumps(config.to_dict(), indent=2))


def save_camera(run: Path, camera_setup, framing: dict) -> None:
    """The orbit camera of the training data (a datagen CameraSetup) and how its views frame their object
    (:func:`pipelines.model.framing.training_framing`), for predict."""
    setup = dict(distance=camera_setup.distance, elevation_deg=camera_setup.elevation_deg,
                 fov_deg=camera_setup.fov_deg, **framing)
    with atomic_path(Path(run) / CAMERA) as tmp:
        tmp.write_text(json.dumps(setup, indent=2))


def load_camera(run: Path) -> dict:
    """The camera set-up of the data a run was trained on: distance, elevation_deg, fov_deg, and where the run
    recorded them, object_size and object_centre."""
    path = Path(run) / CAMERA
    if not path.is_file():
        raise DataError(f"{path} missing: the run predates saved camera set-ups; retrain it")
    setup = read_json(path, "camera set-up")
    if not isinstance(setup, dict) or not all(_finite(setup.get(k)) for k in ("distance", "elevation_deg", "fov_deg")):
        raise DataError(f"{path}: expected finite numbers distance, elevation_deg and fov_deg; retrain the run")
    size, centre = setup.get("object_size"), setup.get("object_centre")
    if (size, centre) != (None, None) and not (
            _finite(size) and 0 < size <= 1 and isinstance(centre, list) and len(centre) == 2
            and all(_finite(c) and 0 <= c <= 1 for c in centre)):
        raise DataError(f"{path}: object_size {size!r} / object_centre {centre!r} are no share of the image side and "
                        "point in it; retrain the run")
    return setup


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


# ----------------------------------------------------------------------------- checkpoints

def save_checkpoint(path: Path, model: Encoder, opt, iteration: int, config: TrainConfig) -> None:
    state = {"model": model.state_dict(), "model_config": model.config.to_dict(), "optimizer": opt.state_dict(),
             "iteration": iteration, "config": config.to_dict(), "torch_rng": torch.get_rng_state()}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def read_checkpoint(path: Path) -> dict:
    """A checkpoint's state, read as tensors and plain data only (a pickled object from someone else's run
    cannot run code here)."""
    try:
        state = torch.load(path, weights_only=True, map_location="cpu")  # a run trained on a GPU reads anywhere
    except FileNotFoundError:
        raise DataError(f"{path}: no checkpoint") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError, ValueError, KeyError, IndexError,
            TypeError, AttributeError) as e:  # a text file or another format: torch.load's errors vary
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if isinstance(e, (KeyError, IndexError, TypeError, AttributeError)):
            first = "not a file torch.save wrote"
        raise DataError(f"{path}: unreadable checkpoint ({first}); it may be truncated or not a dibrpp "
                        "checkpoint: retrain the run, or resume it from an intact copy") from None
    if not isinstance(state, dict) or not {"model", "iteration"} <= set(state):
        raise DataError(f"{path}: not a dibrpp checkpoint (no model state and iteration)")
    return state


def load_checkpoint(path: Path) -> tuple[dict, Encoder]:
    """(state, model) of a checkpoint, the model built from the configuration saved with it."""
    state = read_checkpoint(path)
    if "model_config" not in state:
        raise DataError(f"{path} was written by an older version of the model (no model configuration saved with "
                        "it); retrain it, e.g. `make train-glossy`")
    saved, weights = state["model_config"], state["model"]
    if not isinstance(saved, dict) or not isinstance(weights, dict):
        wrong, value = ("model configuration", saved) if not isinstance(saved, dict) else ("weights", weights)
        raise DataError(f"{path}: the {wrong} is a {type(value).__name__}, not a mapping; not a dibrpp checkpoint: "
                        "retrain the run or restore a copy")
    subdivisions = saved.get("template_subdivisions", 3)
    if not isinstance(subdivisions, int) or not 0 <= subdivisions <= MAX_TEMPLATE_SUBDIVISIONS:
        raise DataError(f"{path}: template_subdivisions {subdivisions!r}, expected an integer in "
                        f"0..{MAX_TEMPLATE_SUBDIVISIONS} (each level quadruples the template's faces)")
    try:
        if isinstance(saved, dict) and saved.get("version") != MODEL_VERSION:
            saved, weights = earlier_model_config(saved, MODEL_VERSION), earlier_state_dict(weights)
        model = Encoder(ModelConfig.from_dict(saved))
        model.load_state_dict(weights)
    except (ValueError, RuntimeError, TypeError, AttributeError, KeyError) as e:
        raise DataError(f"{path}: {str(e).splitlines()[0]}") from e
    _check_template(path, model)
    return state, model


def _check_template(path: Path, model: Encoder) -> None:
    """The template mesh the checkpoint holds indexes its own vertices and UVs (a corrupt index would fail deep in
    rendering)."""
    for name, index, count in (("faces", model.faces, model.template_dirs.shape[-2]),
                               ("face_uvs", model.face_uvs, model.uvs.shape[-2])):
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= count):
            raise DataError(f"{path}: the template's {name} index {int(index.min())}..{int(index.max())}, outside "
                            f"its {count} entries; the checkpoint is corrupt: retrain the run or restore a copy")


def checkpoint_digest(run: Path) -> str:
    """A short hash of what a run's evaluation depends on: its checkpoint's bytes and its config."""
    h = hashlib.sha256()
    for name in (CHECKPOINT, CONFIG):
        with open(Path(run) / name, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:16]


@dataclass
class Run:
    """A trained (or interrupted) run, loaded for inference."""
    folder: Path
    config: TrainConfig
    model: Encoder
    iteration: int


def load_run(folder: Path) -> Run:
    folder = run_folder(folder)
    config = load_config(folder)
    state, model = load_checkpoint(folder / CHECKPOINT)
    check_config_matches_model(folder, config, model.config)
    model.eval()
    return Run(folder, config, model, int(state["iteration"]))


def check_config_matches_model(folder: Path, config: TrainConfig, model_config: ModelConfig) -> None:
    """A run's config.json and its checkpoint's model agree on what a run is read as (a config copied from
    another run would otherwise be evaluated, tabled or predicted with the wrong shading or lobe count)."""
    for name in ("shading", "lobes", "predict_metallic", "specular"):
        saved, built = getattr(config, name), getattr(model_config, name)
        if name == "predict_metallic" and saved is None:
            continue
        if saved != built:
            raise DataError(f"{folder}: {CONFIG} says {name} = {saved!r} but {CHECKPOINT} holds a model with "
                            f"{name} = {built!r}; the files belong to different runs: restore the run's own {CONFIG}")
    today = ModelConfig(image_size=model_config.image_size, global_grid=GLOBAL_GRID)
    if model_config.grid_side() != today.grid_side():
        raise DataError(f"{folder}: {CHECKPOINT} holds a model whose global code is read off a "
                        f"{model_config.grid_side()}-cell side at {model_config.image_size}² (global_grid "
                        f"{model_config.global_grid}), today's off {today.grid_side()}; that option has left the code: "
                        "evaluate or resume the run at commit 3a0c414 (git checkout 3a0c414), or retrain it")


# ----------------------------------------------------------------------------- what a run is built from

def make_model(config: TrainConfig, image_size: int) -> Encoder:
    """The encoder a run trains on images of ``image_size`` (the dataset's)."""
    return Encoder(ModelConfig(shading=config.shading, lobes=config.lobes, image_size=image_size,
                               predict_metallic=bool(config.predict_metallic), texture=config.texture,
                               light_colour=config.light_colour, light_head=config.model_light_head(),
                               input_range=config.input_range, probe_normals=config.probe_normals,
                               global_grid=GLOBAL_GRID, specular=config.specular))


def make_optimizer(model: Encoder, config: TrainConfig) -> torch.optim.Adam:
    # fused: one kernel over all parameters (a quarter of the per-tensor loop's time on a CPU), the same update
    return torch.optim.Adam(model.parameters(), lr=config.lr, fused=True)


def fitted_pixel_normals(out: Path, model: Encoder, data, seed: int, progress: bool = False) -> None:
    """Variant pixel-normals: ``model``'s pixel-normal network fitted to the training views' GT normals
    (:func:`pipelines.model.pixel_normals.fit`) before the model trains, kept in the run folder (a resumed run reads it
    back), and held (no gradient) from then on. ``data``: TrainingViews with its normals."""
    net, path = model.pixel_normals, out / PIXEL_NORMALS
    if path.exists():
        net.load_state_dict(torch.load(path, map_location=next(net.parameters()).device, weights_only=True))
    else:
        flat = lambda t: t.flatten(0, 1)  # noqa: E731 (samples, views, ...) -> views
        images = model.visible_input(encoder_input(flat(data.images))).contiguous()
        if not progress:  # the fit takes minutes on a CPU: say so where no bar shows it
            print(f"{out}: fitting the pixel-normal network to the training views' normals "
                  f"({pixel_normals.FIT_STEPS} steps) before training", flush=True)
        pixel_normals.fit(net, images, flat(data.world_to_camera), flat(data.normals), seed, progress=progress)
        with atomic_path(path) as tmp:
            torch.save(net.state_dict(), tmp)
    net.requires_grad_(False)


def make_renderer(config: TrainConfig, seed: int, training: bool = False, spp: int | None = None,
                  device: str | None = None, eager: bool = False) -> Renderer:
    """The renderer of a run (``spp`` overrides the training spp, e.g. for evaluation) on ``device`` (the run's
    own by default). ``training``: the losses read the soft mask, so the anti-aliased coverage (only the image's
    alpha) is not computed. ``eager``: no torch.compile (a few renders, which a compile would only delay)."""
    filter_width = 0.0 if training else RasterSettings.filter_width
    settings = RasterSettings(cull_backfaces=True, visibility="dibr", filter_width=filter_width)
    return Renderer(config.shading, spp=spp or config.spp, seed=seed, raster_settings=settings,
                    compile=not eager and compiles(config, device or config.device, training))


def compiles(config: TrainConfig, device: str, training: bool) -> bool:
    """Whether the renderer goes through torch.compile (``config.compile``) where it pays: on the CPU always; on
    CUDA only to train SG or SH, whose compile takes seconds there. Compiling MC on CUDA had not finished one step
    after 110 s, and evaluation renders batches of several shapes, each a compile: eager CUDA starts at once."""
    return config.compile and (str(device).startswith("cpu") or (training and config.shading != "mc"))


SECOND_SAMPLES_SEED = 1_000_003  # offsets the seeds of the second samples' renders from every run's first ones


def step_renderers(config: TrainConfig, iteration: int) -> tuple[Renderer, Renderer | None]:
    """The renderers of training step ``iteration`` (what train and the step benchmark shade with): MC's samples
    differ per iteration, reproducibly, at the config's samples for that iteration; the second, with independent
    samples, where MC's image losses take their gradient from one (``independent_mc_samples``), else None."""
    seed, spp = config.seed * 7919 + iteration, config.spp
    first = make_renderer(config, seed=seed, training=True, spp=spp)
    if not config.independent_mc_samples():
        return first, None
    return first, make_renderer(config, seed=SECOND_SAMPLES_SEED + seed, training=True, spp=spp)


def check_image_size(run: Path, image_size: int, ds: MultiViewDataset) -> None:
    """A DataError unless the dataset's images are the size the run's model reads (as training refuses them)."""
    if ds.resolution != image_size:
        raise DataError(f"{run} was trained on {image_size}x{image_size} images but {ds.root} holds "
                        f"{ds.resolution}x{ds.resolution}; evaluate it on a dataset rendered at {image_size} "
                        f"(python -m datagen --resolution {image_size}) or a run trained on {ds.root}")
