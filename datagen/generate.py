"""Dataset generation: objects x environment maps x views, rendered by Cycles in worker processes.

On-disk format (one folder per dataset; every path comes from :class:`datagen.layout.DatasetLayout`)::

    manifest.json                      generator version, config, seeds, splits, counts, file layout
    envmaps/env_0007.exr               linear HDR equirect map (H, 2H, RGB), top row first
    envmaps/env_0007.png               tone-mapped preview;  env_0007.json: kind, parameters / source (done marker)
    objects/obj_0003/mesh.npz          verts (V,3) f32, faces (F,3) i64, uvs (T,2) f32 (v up), face_uvs (F,3) i64
    objects/obj_0003/mesh.obj          the same mesh as OBJ (v/vt faces) + mesh.mtl -> texture.png
    objects/obj_0003/texture.png       albedo, sRGB 8-bit, top row first
    objects/obj_0003/object.json       material, shape parameters, paint style, split (done marker)
    samples/obj_0003_env_0007/view_05.exr         linear RGBA render (alpha = anti-aliased coverage)
    samples/obj_0003_env_0007/view_05.png         sRGB RGBA preview of the same render
    samples/obj_0003_env_0007/view_05_mask.png    alpha, 8-bit
    samples/obj_0003_env_0007/view_05_albedo.exr  linear base colour x coverage (RGB)
    samples/obj_0003_env_0007/view_05.json        camera: world_to_camera (4x4), fov (rad), resolution, azimuth, elevation, distance
    samples/obj_0003_env_0007/sample.json         object, env map, material, seeds, files + sizes, timing (done marker)
    preview.png                                   contact sheet
    timing/shard_0_of_1.json                      wall/Cycles time of the last run that rendered
    .datagen_shard_0_of_1.lock                    held while a run writes the folder (datagen.locking)

Every file is written atomically (temp + rename) and a folder counts as finished only once its json
marker exists, so a killed run loses at most the samples in flight and a rerun resumes. One run per
folder (and shard) at a time: a second one is refused. Workers die with their run.

The parts: :mod:`datagen.config` (settings, presets), :mod:`datagen.plan` (seeds, splits, materials),
:mod:`datagen.manifest` (the manifest and the checks before resuming), :mod:`datagen.tasks` (what a
worker makes), :mod:`datagen.workers` (the worker processes), :mod:`datagen.locking`; this module runs them.

Environment maps are procedural (outdoor skies, indoor rooms: :mod:`datagen.envmaps`) unless
``envmaps_dir`` names a folder of your own HDRIs (:mod:`datagen.envmap_files`): then those files are
maps 0..F-1 (sorted by name) and ``procedural_envmaps`` procedural maps follow; each group is split
4:1 into train/test by the seed, and the manifest's ``envmap_sources`` records each file's name,
sha256 and original resolution.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

from dibrpp.io import DataError

from .config import Config
from .layout import DatasetLayout
from .locking import exclusive_run, manifest_lock
from .manifest import build_manifest, check_manifest, verify_sample, write_manifest
from .plan import plan
from .records import write_json
from .tasks import task_envmap, task_envmap_file, task_object, task_sample
from .workers import completed


def generate(cfg: Config, out, workers: int = 1, shard: tuple[int, int] = (0, 1), recycle: int = 4,
             progress: bool = True, preview: bool = True, cycles_device: str = "CPU") -> dict:
    """Generate (or resume) a dataset into ``out``; returns a timing summary. ``cycles_device``: where Cycles
    renders the views ("CPU" or "GPU"); the env maps, shapes and textures are made on the CPU either way, so
    the assets are the same on any machine and only the views' noise depends on the device.

    FolderBusy (a DataError) at once if another run is writing the same shard into ``out``."""
    cfg.validate()
    out = Path(out)
    sources = _scan_envmap_files(cfg)  # read and check every file before anything renders
    _check_writable(out)
    with exclusive_run(out, shard):
        p = plan(cfg)
        manifest = build_manifest(cfg, p, sources)
        with manifest_lock(out):  # no other shard may write a different manifest between check and write
            check_manifest(out, manifest)
            write_manifest(out, manifest)
        si, sn = shard
        mine = [o for o in p["objects"] if o["index"] % sn == si]
        _verify_finished_samples(out, mine, cfg)
        threads = max(1, (os.cpu_count() or 1) // max(1, workers))
        run = dict(workers=workers, threads=threads, recycle=recycle, progress=progress, device=cycles_device)
        t_start = time.perf_counter()
        stats = dict(cycles_s=0.0, sample_s=0.0, asset_s=0.0, rendered_views=0, skipped_samples=0)
        stats["asset_s"] = _make_assets(out, cfg, p, sources, mine, run)
        stats.update(_render_samples(out, cfg, mine, run))
        stats.update(_summary(stats, time.perf_counter() - t_start, workers, threads, shard),
                     cycles_device=cycles_device)
        timing = DatasetLayout(out).timing(si, sn)
        if stats["rendered_views"] or not timing.exists():  # a rerun that finds the shard done keeps its record
            write_json(timing, stats)
        if preview and _all_samples_finished(out, p):
            from .preview import contact_sheet

            contact_sheet(out)
    return stats


def _scan_envmap_files(cfg: Config) -> list:
    """The records of ``cfg``'s env map files (none without ``--envmaps``), each file read and checked."""
    if not cfg.envmaps_dir:
        return []
    from .envmap_files import scan_envmap_folder

    sources = scan_envmap_folder(cfg.envmaps_dir)
    if len(sources) != cfg.num_file_envmaps:
        raise DataError(f"--envmaps {cfg.envmaps_dir}: holds {len(sources)} maps, the config counted "
                        f"{cfg.num_file_envmaps}; rerun the command")
    return sources


def _check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write_probe_{os.getpid()}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as e:
        raise DataError(f"cannot write to output folder {out}: {e}") from e


def _verify_finished_samples(out: Path, objects: list, cfg: Config) -> None:
    """Check what is already there before spending time."""
    layout = DatasetLayout(out)
    for o in objects:
        for e in o["envmaps"]:
            if layout.sample_json(o["index"], e).exists():
                verify_sample(layout.sample_dir(o["index"], e), cfg)


def _progress_bar(progress: bool, **kw):
    from tqdm import tqdm

    return tqdm(disable=not progress, **kw)


def _make_assets(out: Path, cfg: Config, p: dict, sources: list, objects: list, run: dict) -> float:
    """The env maps and objects of ``objects``; returns the seconds spent making them."""
    envs = sorted({e for o in objects for e in o["envmaps"]})
    tasks = [(task_envmap_file, (str(out), cfg, e, sources[e])) if e < cfg.num_file_envmaps else
             (task_envmap, (str(out), cfg, e, p["env_kind"][e])) for e in envs]
    tasks += [(task_object, (str(out), cfg, o["index"], o)) for o in objects]
    seconds = 0.0
    with _progress_bar(run["progress"], total=len(tasks), desc=f"{cfg.dataset}: assets", unit="asset") as bar:
        for r in completed(tasks, run["workers"], run["threads"], run["recycle"]):
            seconds += r.get("seconds", 0.0)
            bar.update(1)
    return seconds


def _render_samples(out: Path, cfg: Config, objects: list, run: dict) -> dict:
    """Every sample of ``objects``; returns the render statistics."""
    tasks = [(task_sample, (str(out), cfg, o["index"], e, o)) for o in objects for e in o["envmaps"]]
    stats = dict(cycles_s=0.0, sample_s=0.0, rendered_views=0, skipped_samples=0)
    with _progress_bar(run["progress"], total=len(tasks) * cfg.views, desc=f"{cfg.dataset}: views",
                       unit="view") as bar:
        for r in completed(tasks, run["workers"], run["threads"], run["recycle"], run["device"]):
            if r["skipped"]:
                stats["skipped_samples"] += 1
            else:
                stats["cycles_s"] += r["cycles_s"]
                stats["sample_s"] += r["total_s"]
                stats["rendered_views"] += r["rendered"]
            bar.update(r["views"])
    return stats


def _summary(stats: dict, wall: float, workers: int, threads: int, shard: tuple[int, int]) -> dict:
    cycles_s, sample_s, views = stats["cycles_s"], stats["sample_s"], stats["rendered_views"]
    return dict(wall_s=wall, workers=workers, threads_per_worker=threads, shard=f"{shard[0]}/{shard[1]}",
                render_overhead=(sample_s - cycles_s) / cycles_s if cycles_s else None,
                seconds_per_view=sample_s / views if views else None)


def _all_samples_finished(out: Path, p: dict) -> bool:
    layout = DatasetLayout(out)
    return all(layout.sample_json(o["index"], e).exists() for o in p["objects"] for e in o["envmaps"])
