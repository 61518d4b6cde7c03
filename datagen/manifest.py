"""The dataset's manifest (what the folder holds and how it was made) and the checks a rerun makes before it
resumes: same settings, same env map files, finished samples intact."""
from __future__ import annotations

import statistics
from dataclasses import replace
from pathlib import Path

from dibrpp.io import DataError

from .config import Config, config_dict
from .layout import DEFAULT_CAMERA, DatasetLayout
from .plan import azimuths
from .records import read_record, write_json

GENERATOR_VERSION = "1.1.0"

_NOT_OURS = "move it away or choose another --out"


def _renderer(cfg: Config) -> dict:
    renderer = dict(engine="Cycles (bpy)", spp=cfg.spp, max_bounces=cfg.max_bounces,
                    filter="Blackman-Harris 1.5 px", denoising=bool(cfg.denoise), film_transparent=True,
                    bsdf="Principled, GGX")
    if cfg.denoise:
        renderer["denoiser"] = "OpenImageDenoise, albedo + normal guides (shaded renders only)"
    return renderer


def _counts(cfg: Config, splits: dict) -> dict:
    samples = cfg.num_objects * cfg.envs_per_object
    return dict(objects=cfg.num_objects, envmaps=cfg.num_envmaps, samples=samples, views_per_sample=cfg.views,
                images=samples * cfg.views, train_objects=len(splits["objects"]["train"]),
                test_objects=len(splits["objects"]["test"]), train_envmaps=len(splits["envmaps"]["train"]),
                test_envmaps=len(splits["envmaps"]["test"]))


def build_manifest(cfg: Config, plan: dict, sources: list) -> dict:
    """The manifest of a dataset made with ``cfg`` and ``plan``; ``sources``: the env map files, if any."""
    camera = replace(DEFAULT_CAMERA, azimuths_deg=tuple(azimuths(cfg)), resolution=cfg.resolution)
    if cfg.elevations:
        camera = replace(camera, elevation_deg=float(statistics.median(cfg.elevations)),
                         elevations_deg=tuple(float(e) for e in cfg.elevations))
    manifest = dict(generator_version=GENERATOR_VERSION, dataset=cfg.dataset, config=config_dict(cfg),
                    seeds=dict(run=cfg.seed, scheme="numpy SeedSequence([seed, dataset, purpose, index...])"),
                    splits=plan["splits"], env_kind=plan["env_kind"],
                    objects=[dict(index=o["index"], split=o["split"], envmaps=o["envmaps"], material=o["material"])
                             for o in plan["objects"]],
                    counts=_counts(cfg, plan["splits"]), camera=camera.to_manifest(), renderer=_renderer(cfg),
                    normalisation="longest bounding-box side spans [-18, 18], centred")
    if sources:
        manifest["envmap_sources"] = [dict(index=i, **src) for i, src in enumerate(sources)]
    return manifest


def write_manifest(out, manifest: dict) -> None:
    write_json(DatasetLayout(out).manifest, manifest)


def check_manifest(out: Path, manifest: dict) -> None:
    """Refuse to resume into ``out`` if its manifest says it was made with other settings or env map files."""
    path = DatasetLayout(out).manifest
    if not path.exists():
        return
    old = read_record(path, _NOT_OURS)
    old_config = old.get("config", {})
    if not isinstance(old_config, dict):
        raise DataError(f"{path}: 'config' is {type(old_config).__name__}, not an object: not a datagen manifest; "
                        f"{_NOT_OURS}")
    if old_config != manifest["config"] or old.get("generator_version") != manifest["generator_version"]:
        keys = list(manifest["config"]) + [k for k in old_config if k not in manifest["config"]]
        diff = {k: (old_config.get(k), manifest["config"].get(k)) for k in keys
                if old_config.get(k) != manifest["config"].get(k)}
        raise DataError(f"{out} holds a dataset generated with different settings {diff or '(generator version)'}; "
                        "use another --out or the same settings")
    if old.get("envmap_sources") != manifest.get("envmap_sources"):
        was, now = _source_hashes(path, old), _source_hashes(path, manifest)
        changed = sorted(set(was.items()) ^ set(now.items()))
        raise DataError(f"{out} was generated from other env map files (changed: {changed[:4]}); put the "
                        "original files back in the --envmaps folder or generate into another --out")


def _source_hashes(path: Path, manifest: dict) -> dict:
    """{file name: start of its sha256} of a manifest's env map files."""
    try:
        return {s["file"]: s["sha256"][:12] for s in manifest.get("envmap_sources") or []}
    except (KeyError, TypeError) as e:
        raise DataError(f"{path}: 'envmap_sources' is not a list of {{file, sha256}} records ({e!r}); "
                        f"{_NOT_OURS}") from e


def verify_sample(d: Path, cfg: Config) -> None:
    """A finished sample folder ``d`` (:meth:`DatasetLayout.sample_dir`) still holds every file it recorded,
    at the recorded size, and as many views as ``cfg`` asks for."""
    fix = f"delete {d} and rerun to regenerate it"
    meta = read_record(d / "sample.json", fix)
    files = meta.get("files", {})
    if not isinstance(files, dict):
        raise DataError(f"{d / 'sample.json'}: 'files' is not an object of file sizes; {fix}")
    for name, size in files.items():
        p = d / name
        if not p.is_file() or p.stat().st_size != size:
            raise DataError(f"{d}: finished sample is corrupt ({name} missing or changed size); {fix}")
    if meta.get("views") != cfg.views:
        raise DataError(f"{d}: sample has {meta.get('views')} views, config says {cfg.views}; use a new --out")
