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
    timing/shard_0_of_1.json                      wall/Cycles time of a run

Every file is written atomically (temp + rename) and a folder counts as finished only once its json
marker exists, so a killed run loses at most the samples in flight and a rerun resumes.

Environment maps are procedural (outdoor skies, indoor rooms: :mod:`datagen.envmaps`) unless
``envmaps_dir`` names a folder of your own HDRIs (:mod:`datagen.envmap_files`): then those files are
maps 0..F-1 (sorted by name) and ``procedural_envmaps`` procedural maps follow; each group is split
4:1 into train/test by the seed, and the manifest's ``envmap_sources`` records each file's name,
sha256 and original resolution.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from dibrpp.io import DataError, atomic_path

from .layout import DEFAULT_CAMERA, DatasetLayout

GENERATOR_VERSION = "1.1.0"
DATASETS = ("metallic", "glossy", "diffuse")
CAMERA_DISTANCE = DEFAULT_CAMERA.distance  # 60
CAMERA_ELEVATION_DEG = DEFAULT_CAMERA.elevation_deg  # 27
FOV = DEFAULT_CAMERA.fov  # Blender's default camera (50 mm lens, 36 mm sensor): 39.6 deg
_DATASET_CODE = {"metallic": 1, "glossy": 2, "diffuse": 3}

PRESETS = {
    # Sized for learning on a CPU: the number of distinct objects and maps, not the number of iterations,
    # is what lets a model generalise (16 objects memorised, 80 did not). 40 env maps split 32/8, so that
    # every test object is lit by 2 unseen maps; about 1.2 h for all three datasets on 2 cores.
    "default": dict(num_objects=100, num_envmaps=40, envs_per_object=2, views=None, resolution=64, spp=32,
                    texture_size=256, envmap_height=64, grid=64, max_bounces=2),
    # The paper's sizes (Sec. D): 485 objects, 438 env maps, 256x256 images; for a bigger machine.
    "paper": dict(num_objects=485, num_envmaps=438, envs_per_object=3, views=None, resolution=256, spp=256,
                  texture_size=512, envmap_height=128, grid=96, max_bounces=4),
}


# The diffuse set's random-walk subsurface scattering is noisy: 28 % relative RMSE at 32 spp against a
# 4096-spp reference (python -m datagen.noise_study). 64 spp + OpenImageDenoise (albedo and normal guides)
# brings it to 10 %, as good as 256 spp, at 2.5x the time of 32 spp instead of 8x.
DATASET_DEFAULTS = {"diffuse": dict(spp=64, denoise=True)}


@dataclass
class Config:
    dataset: str
    num_objects: int
    num_envmaps: int
    envs_per_object: int
    views: int
    resolution: int
    spp: int
    seed: int = 0
    texture_size: int = 256
    envmap_height: int = 64
    grid: int = 64
    max_bounces: int = 2
    preset: str = "default"
    # Optional settings: left out of the manifest while unset, so older datasets keep matching their config.
    envmaps_dir: str | None = None  # a folder of your own HDRIs: maps 0..F-1
    procedural_envmaps: int | None = None  # with envmaps_dir: how many procedural maps follow the files
    denoise: bool | None = None  # OpenImageDenoise on the shaded renders (albedo + normal guides)

    @property
    def num_file_envmaps(self) -> int:
        return self.num_envmaps - int(self.procedural_envmaps or 0) if self.envmaps_dir else 0

    def validate(self) -> None:
        if self.dataset not in DATASETS:
            raise ValueError(f"unknown dataset {self.dataset!r}; choose one of {', '.join(DATASETS)}")
        if self.procedural_envmaps is not None:
            if not self.envmaps_dir:
                raise ValueError("--procedural-envmaps adds procedural maps to those of --envmaps DIR; without "
                                 "--envmaps every map is procedural (set their number with --num-envmaps)")
            if int(self.procedural_envmaps) < 0:
                raise ValueError(f"--procedural-envmaps must be >= 0, got {self.procedural_envmaps}")
        for name in ("num_objects", "num_envmaps", "envs_per_object", "views", "resolution", "spp",
                     "texture_size", "envmap_height", "grid"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(self, name)}")
        if self.envs_per_object > self.num_envmaps:
            if self.envmaps_dir:
                raise ValueError(f"--envs-per-object ({self.envs_per_object}) cannot exceed the number of env maps "
                                 f"({self.num_file_envmaps} in {self.envmaps_dir} + {self.procedural_envmaps or 0} "
                                 "procedural); add maps, --procedural-envmaps N or lower --envs-per-object")
            raise ValueError(f"--envs-per-object ({self.envs_per_object}) cannot exceed --num-envmaps ({self.num_envmaps})")
        if self.max_bounces < 0:
            raise ValueError("--max-bounces must be >= 0")
        if self.envmaps_dir and self.num_file_envmaps <= 0:
            raise ValueError(f"--envmaps {self.envmaps_dir}: no env map files counted")

    @property
    def shape_kind(self) -> str:
        return "head" if self.dataset == "diffuse" else "car"


_OPTIONAL = ("envmaps_dir", "procedural_envmaps", "denoise")


def config_dict(cfg: Config) -> dict:
    """The config as the manifest stores it: optional settings only when set."""
    d = asdict(cfg)
    for k in _OPTIONAL:
        if d.get(k) in (None, False):
            d.pop(k, None)
    return d


def make_config(dataset: str, preset: str = "default", envmaps=None, procedural_envmaps: int | None = None,
                **overrides) -> Config:
    """The preset's settings with ``overrides``. ``envmaps``: a folder of your own HDRIs (all of its .exr /
    .hdr files, sorted), plus ``procedural_envmaps`` procedural maps (default 0); the number of env maps is
    then counted, not set."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; choose one of {', '.join(DATASETS)}")
    values = dict(PRESETS[preset])
    if preset == "default":
        values.update(DATASET_DEFAULTS.get(dataset, {}))
    values.update({k: v for k, v in overrides.items() if v is not None})
    if values.get("views") is None:
        values["views"] = 12 if dataset == "diffuse" else 24
    if envmaps is not None:
        from .envmap_files import list_envmap_files

        if overrides.get("num_envmaps") is not None:
            raise ValueError("--num-envmaps counts procedural maps; with --envmaps DIR every file is used, "
                             "add procedural ones with --procedural-envmaps N")
        procedural_envmaps = int(procedural_envmaps or 0)
        values["num_envmaps"] = len(list_envmap_files(envmaps)) + procedural_envmaps
        values["envmaps_dir"] = str(envmaps)
    values["procedural_envmaps"] = procedural_envmaps
    cfg = Config(dataset=dataset, preset=preset, **values)
    cfg.validate()
    return cfg


def seed_for(cfg: Config, *keys: int) -> int:
    """Independent, stable seeds per (dataset, purpose, index) from the run seed."""
    return int(np.random.SeedSequence([int(cfg.seed), _DATASET_CODE[cfg.dataset], *[int(k) for k in keys]])
               .generate_state(1)[0])


_ENV, _OBJ, _RENDER, _SPLIT, _MATERIAL, _TONE = 1, 2, 3, 4, 5, 6


# ----------------------------------------------------------------------------- plan (pure, deterministic)

def azimuths(cfg: Config) -> list[float]:
    if cfg.dataset == "diffuse":  # front views only, uniformly over the front half-circle
        return [-90.0 + 180.0 * (k + 0.5) / cfg.views for k in range(cfg.views)]
    return [360.0 * k / cfg.views for k in range(cfg.views)]


def _split(n: int, rng: np.random.Generator) -> tuple[list[int], list[int]]:
    perm = rng.permutation(n)
    n_test = int(round(n / 5)) if n >= 2 else 0
    return sorted(int(i) for i in perm[n_test:]), sorted(int(i) for i in perm[:n_test])


def plan(cfg: Config) -> dict:
    """Splits (4:1 for objects and env maps), env kinds, material per object, env maps per object.

    Env maps from files (indices 0..F-1) and procedural ones (F..) are split 4:1 each, so that both
    splits hold both kinds.
    """
    rng = np.random.default_rng(seed_for(cfg, _SPLIT))
    obj_train, obj_test = _split(cfg.num_objects, rng)
    nf = cfg.num_file_envmaps
    if nf:
        f_train, f_test = _split(nf, rng)
        p_train, p_test = _split(cfg.num_envmaps - nf, rng)
        env_train = f_train + [nf + i for i in p_train]
        env_test = f_test + [nf + i for i in p_test]
    else:
        env_train, env_test = _split(cfg.num_envmaps, rng)
    env_kind = ["file" if i < nf else
                "outdoor" if np.random.default_rng(seed_for(cfg, _ENV, i)).random() < 0.6 else "indoor"
                for i in range(cfg.num_envmaps)]
    objects = []
    unseen = True  # test objects are lit only by test env maps
    for i in range(cfg.num_objects):
        split = "test" if i in obj_test else "train"
        pool = env_test if split == "test" else env_train
        if len(pool) < cfg.envs_per_object:
            # too few maps in this split (tiny runs): draw from all maps; the manifest says so
            pool = list(range(cfg.num_envmaps))
            unseen = False
        r = np.random.default_rng(seed_for(cfg, _MATERIAL, i))
        envs = sorted(int(e) for e in r.choice(pool, cfg.envs_per_object, replace=False))
        objects.append(dict(index=i, split=split, envmaps=envs, material=material_for(cfg, r),
                            tone=float((np.random.default_rng(seed_for(cfg, _TONE)).permutation(cfg.num_objects)[i]
                                        + r.uniform()) / cfg.num_objects)))
    return dict(objects=objects, splits=dict(objects=dict(train=obj_train, test=obj_test),
                                             envmaps=dict(train=env_train, test=env_test),
                                             test_objects_see_only_test_envmaps=unseen), env_kind=env_kind)


def material_for(cfg: Config, rng: np.random.Generator) -> dict:
    """Principled BSDF parameters per dataset (Sec. D)."""
    if cfg.dataset == "metallic":  # beta = 0, m = 1
        return dict(roughness=0.0, metallic=1.0, specular_ior_level=0.5, subsurface_weight=0.0)
    if cfg.dataset == "glossy":  # m = 0, s = 1 (Specular IOR Level 1.0), beta ~ U[0, 0.4]
        return dict(roughness=float(rng.uniform(0.0, 0.4)), metallic=0.0, specular_ior_level=1.0, subsurface_weight=0.0)
    # diffuse: skin, random-walk subsurface scattering, primarily diffuse
    return dict(roughness=float(rng.uniform(0.45, 0.65)), metallic=0.0, specular_ior_level=0.5,
                subsurface_weight=1.0, subsurface_radius=[1.0, 0.35, 0.2], subsurface_scale=0.25,
                subsurface_method="RANDOM_WALK")


sample_name = DatasetLayout.sample_name
view_files = DatasetLayout.view_files


def _write_json(path: Path, data) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True))


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: unreadable or corrupt JSON ({e}); delete its folder to regenerate it") from e


# ----------------------------------------------------------------------------- tasks (run in workers)

_THREADS = 0


def _init_worker(threads: int) -> None:
    global _THREADS
    _THREADS = threads
    # Blender prints a line per render ("Saved: ...") on stdout: keep the parent's progress bar clean.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
    # A parent that imported bpy has Blender's script folders (holding a pure-Python ``bpy`` package)
    # on sys.path, and spawn copies that path; drop them so the real module is found.
    sys.path[:] = [p for p in sys.path if f"{os.sep}bpy{os.sep}" not in p]
    import bpy  # noqa: F401  (pay the import once per worker)


def _task_envmap(out: str, i: int, make) -> dict:
    """Env map ``i`` unless finished: ``make()`` -> (env (H, 2H, 3), record); writes the EXR, its tone-mapped
    PNG and the record (the done marker)."""
    from dibrpp.io import write_exr, write_png

    layout = DatasetLayout(out)
    if layout.envmap_json(i).exists():
        return dict(kind="envmap", index=i, skipped=True)
    t0 = time.perf_counter()
    env, record = make()
    write_exr(layout.envmap(i), env)
    write_png(layout.envmap_png(i), env / (1 + env))
    _write_json(layout.envmap_json(i), dict(index=i, **record, shape=list(env.shape),
                                            seconds=time.perf_counter() - t0))
    return dict(kind="envmap", index=i, skipped=False, seconds=time.perf_counter() - t0)


def task_envmap(out: str, cfg: Config, i: int, kind: str) -> dict:
    """Procedural env map ``i`` (an outdoor sky or an indoor room)."""
    def make():
        from . import envmaps

        rng = np.random.default_rng(seed_for(cfg, _ENV, i, 1))
        h = cfg.envmap_height
        env, params = envmaps.make_envmap(kind, rng, h, 2 * h, spp=32, threads=_THREADS)
        return env, dict(kind=kind, params=params, seed=seed_for(cfg, _ENV, i, 1))
    return _task_envmap(out, i, make)


def task_envmap_file(out: str, cfg: Config, i: int, source: dict) -> dict:
    """Env map ``i`` from one of your files: resampled to the dataset's size (area average)."""
    def make():
        from .envmap_files import load_envmap_source

        env = load_envmap_source(cfg.envmaps_dir, source, cfg.envmap_height)
        return env, dict(kind="file", source=source, resampling="area average over solid angle (energy preserving)")
    return _task_envmap(out, i, make)


def task_object(out: str, cfg: Config, i: int, info: dict) -> dict:
    from dibrpp.io import write_png, write_textured_obj

    from . import shapes, textures

    layout = DatasetLayout(out)
    if layout.object_json(i).exists():
        return dict(kind="object", index=i, skipped=True)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed_for(cfg, _OBJ, i))
    obj = shapes.make_shape(cfg.shape_kind, rng, grid=cfg.grid)
    uvs, face_uvs = shapes.unwrap(obj["verts"], obj["faces"], resolution=cfg.texture_size)
    tex, style = textures.bake_texture(obj, uvs, face_uvs, cfg.texture_size, rng, tone=info["tone"])
    layout.object_dir(i).mkdir(parents=True, exist_ok=True)
    with atomic_path(layout.mesh_npz(i)) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, verts=obj["verts"].astype(np.float32), faces=obj["faces"], uvs=uvs, face_uvs=face_uvs)
    write_png(layout.texture(i), tex, srgb=False)  # values are sRGB already
    # mesh.obj + mesh.mtl, whose map_Kd names the texture relative to the OBJ
    write_textured_obj(layout.mesh_obj(i), obj["verts"], obj["faces"], uvs, face_uvs, layout.texture(i).name)
    meta = dict(index=i, kind=cfg.shape_kind, split=info["split"], material=info["material"], envmaps=info["envmaps"],
                shape_params=obj["shape"].params, paint=style, normalisation=obj["normalisation"],
                num_verts=len(obj["verts"]), num_faces=len(obj["faces"]), texture_size=cfg.texture_size,
                seed=seed_for(cfg, _OBJ, i), seconds=time.perf_counter() - t0)
    _write_json(layout.object_json(i), meta)
    return dict(kind="object", index=i, skipped=False, seconds=time.perf_counter() - t0)


def task_sample(out: str, cfg: Config, i: int, env: int, info: dict) -> dict:
    import torch

    from dibrpp.conventions import orbit_world_to_camera
    from dibrpp.io import write_exr, write_png

    from . import cycles as C

    layout = DatasetLayout(out)
    d = layout.sample_dir(i, env)
    if layout.sample_json(i, env).exists():
        return dict(kind="sample", obj=i, env=env, skipped=True, views=cfg.views)
    t0 = time.perf_counter()
    with np.load(layout.mesh_npz(i)) as m:
        verts, faces, uvs, face_uvs = m["verts"], m["faces"], m["uvs"], m["face_uvs"]
    material = C.PrincipledMaterial.from_dict(info["material"], texture=layout.texture(i))
    settings = C.RenderSettings(resolution=cfg.resolution, spp=cfg.spp, max_bounces=cfg.max_bounces,
                                denoise=bool(cfg.denoise), albedo_aov=True, threads=_THREADS)
    cs = C.build_scene(verts, faces, envmap=layout.envmap(env), settings=settings, material=material, uvs=uvs,
                       face_uvs=face_uvs)
    build_s = time.perf_counter() - t0
    d.mkdir(parents=True, exist_ok=True)
    rendered = 0
    for v, az in enumerate(azimuths(cfg)):
        names = layout.view_files(v)
        if all((d / n).exists() for n in names):
            continue  # finished before a crash
        w2c = orbit_world_to_camera(torch.tensor(CAMERA_DISTANCE, dtype=torch.float64), CAMERA_ELEVATION_DEG, az)
        C.set_camera(cs, w2c.numpy(), FOV)
        C.set_seed(cs, seed_for(cfg, _RENDER, i, env, v) % (1 << 31))
        res = C.render(cs)
        rgba, albedo = res["rgba"], res["albedo"]
        write_exr(d / names[0], rgba)
        write_png(d / names[1], rgba)
        write_png(d / names[2], rgba[..., 3])
        write_exr(d / names[3], albedo)
        _write_json(d / names[4], dict(world_to_camera=w2c.tolist(), fov=FOV, resolution=cfg.resolution,
                                       azimuth_deg=az, elevation_deg=CAMERA_ELEVATION_DEG, distance=CAMERA_DISTANCE,
                                       convention="dibrpp.conventions: world +Z up, camera looks down -Z, +Y up"))
        rendered += 1
    files = {n: (d / n).stat().st_size for v in range(cfg.views) for n in layout.view_files(v)}
    total = time.perf_counter() - t0
    _write_json(layout.sample_json(i, env), dict(object=i, envmap=env, split=info["split"], material=info["material"],
                                        views=cfg.views, azimuths_deg=azimuths(cfg), files=files,
                                        render_seeds=[seed_for(cfg, _RENDER, i, env, v) % (1 << 31)
                                                      for v in range(cfg.views)],
                                        timing=dict(total_s=total, cycles_s=cs.render_seconds, build_s=build_s,
                                                    views_rendered=rendered, renders=cs.renders)))
    return dict(kind="sample", obj=i, env=env, skipped=False, views=cfg.views, rendered=rendered,
                total_s=total, cycles_s=cs.render_seconds)


def _completed(tasks, workers: int, threads: int, recycle: int):
    """Results of ``tasks`` [(fn, args)] as they finish; a failed task stops the run with its error.

    Workers are recycled (bpy leaks memory) by running the tasks in batches, each in a fresh pool. The
    pool's own ``max_tasks_per_child`` deadlocks on Python 3.11 when a worker retires, so it is not used.
    """
    ctx = mp.get_context("spawn")
    batch = max(1, workers) * max(1, recycle)
    for start in range(0, len(tasks), batch):
        with ProcessPoolExecutor(max(1, workers), mp_context=ctx, initializer=_init_worker,
                                 initargs=(threads,)) as pool:
            futures = [pool.submit(fn, *a) for fn, a in tasks[start:start + batch]]
            try:
                for fut in as_completed(futures):
                    try:
                        yield fut.result()
                    except BrokenProcessPool as e:
                        raise RuntimeError("a datagen worker process died (crash or out of memory); rerun the "
                                           "same command to resume, finished samples are kept") from e
            finally:
                for f in futures:
                    f.cancel()


# ----------------------------------------------------------------------------- verification

def verify_sample(d: Path, cfg: Config) -> None:
    meta = _read_json(d / "sample.json")  # d: a sample folder (DatasetLayout.sample_dir)
    for name, size in meta.get("files", {}).items():
        p = d / name
        if not p.is_file() or p.stat().st_size != size:
            raise DataError(f"{d}: finished sample is corrupt ({name} missing or changed size); "
                            f"delete {d} and rerun to regenerate it")
    if meta.get("views") != cfg.views:
        raise DataError(f"{d}: sample has {meta.get('views')} views, config says {cfg.views}; use a new --out")


def _check_manifest(out: Path, manifest: dict) -> None:
    path = DatasetLayout(out).manifest
    if not path.exists():
        return
    old = _read_json(path)
    if old.get("config") != manifest["config"] or old.get("generator_version") != manifest["generator_version"]:
        keys = list(manifest["config"]) + [k for k in old.get("config", {}) if k not in manifest["config"]]
        diff = {k: (old.get("config", {}).get(k), manifest["config"].get(k)) for k in keys
                if old.get("config", {}).get(k) != manifest["config"].get(k)}
        raise DataError(f"{out} holds a dataset generated with different settings {diff or '(generator version)'}; "
                        "use another --out or the same settings")
    if old.get("envmap_sources") != manifest.get("envmap_sources"):
        was = {s["file"]: s["sha256"][:12] for s in old.get("envmap_sources") or []}
        now = {s["file"]: s["sha256"][:12] for s in manifest.get("envmap_sources") or []}
        changed = sorted(set(was.items()) ^ set(now.items()))
        raise DataError(f"{out} was generated from other env map files (changed: {changed[:4]}); put the "
                        "original files back in the --envmaps folder or generate into another --out")


def _check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write_probe_{os.getpid()}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as e:
        raise DataError(f"cannot write to output folder {out}: {e}") from e


def parse_shard(s: str) -> tuple[int, int]:
    try:
        i, n = (int(x) for x in str(s).split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n (e.g. 0/4), got {s!r}") from None
    if n <= 0 or not 0 <= i < n:
        raise ValueError(f"--shard {s}: need 0 <= i < n")
    return i, n


# ----------------------------------------------------------------------------- driver

def generate(cfg: Config, out, workers: int = 1, shard: tuple[int, int] = (0, 1), recycle: int = 4,
             progress: bool = True, preview: bool = True) -> dict:
    """Generate (or resume) a dataset into ``out``; returns a timing summary."""
    from tqdm import tqdm

    cfg.validate()
    out = Path(out)
    layout = DatasetLayout(out)
    sources = []
    if cfg.envmaps_dir:  # read and check every file before anything renders
        from .envmap_files import scan_envmap_folder

        sources = scan_envmap_folder(cfg.envmaps_dir)
        if len(sources) != cfg.num_file_envmaps:
            raise DataError(f"--envmaps {cfg.envmaps_dir}: holds {len(sources)} maps, the config counted "
                            f"{cfg.num_file_envmaps}; rerun the command")
    _check_writable(out)
    p = plan(cfg)
    camera = replace(DEFAULT_CAMERA, azimuths_deg=tuple(azimuths(cfg)), resolution=cfg.resolution)
    renderer = dict(engine="Cycles (bpy)", spp=cfg.spp, max_bounces=cfg.max_bounces,
                    filter="Blackman-Harris 1.5 px", denoising=bool(cfg.denoise), film_transparent=True,
                    bsdf="Principled, GGX")
    if cfg.denoise:
        renderer["denoiser"] = "OpenImageDenoise, albedo + normal guides (shaded renders only)"
    manifest = dict(generator_version=GENERATOR_VERSION, dataset=cfg.dataset, config=config_dict(cfg),
                    seeds=dict(run=cfg.seed, scheme="numpy SeedSequence([seed, dataset, purpose, index...])"),
                    splits=p["splits"], env_kind=p["env_kind"],
                    objects=[dict(index=o["index"], split=o["split"], envmaps=o["envmaps"], material=o["material"])
                             for o in p["objects"]],
                    counts=dict(objects=cfg.num_objects, envmaps=cfg.num_envmaps, samples=cfg.num_objects * cfg.envs_per_object,
                                views_per_sample=cfg.views, images=cfg.num_objects * cfg.envs_per_object * cfg.views,
                                train_objects=len(p["splits"]["objects"]["train"]),
                                test_objects=len(p["splits"]["objects"]["test"]),
                                train_envmaps=len(p["splits"]["envmaps"]["train"]),
                                test_envmaps=len(p["splits"]["envmaps"]["test"])),
                    camera=camera.to_manifest(), renderer=renderer,
                    normalisation="longest bounding-box side spans [-18, 18], centred")
    if sources:
        manifest["envmap_sources"] = [dict(index=i, **src) for i, src in enumerate(sources)]
    _check_manifest(out, manifest)
    _write_json(layout.manifest, manifest)

    si, sn = shard
    my_objects = [o for o in p["objects"] if o["index"] % sn == si]
    my_envs = sorted({e for o in my_objects for e in o["envmaps"]})
    # Verify what is already there before spending time.
    for o in my_objects:
        for e in o["envmaps"]:
            if layout.sample_json(o["index"], e).exists():
                verify_sample(layout.sample_dir(o["index"], e), cfg)
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    t_start = time.perf_counter()
    stats = dict(cycles_s=0.0, sample_s=0.0, asset_s=0.0, rendered_views=0, skipped_samples=0)
    assets = [(task_envmap_file, (str(out), cfg, e, sources[e])) if e < cfg.num_file_envmaps else
              (task_envmap, (str(out), cfg, e, p["env_kind"][e])) for e in my_envs]
    assets += [(task_object, (str(out), cfg, o["index"], o)) for o in my_objects]
    bar = tqdm(total=len(assets), desc=f"{cfg.dataset}: assets", unit="asset", disable=not progress)
    for r in _completed(assets, workers, threads, recycle):
        stats["asset_s"] += r.get("seconds", 0.0)
        bar.update(1)
    bar.close()
    samples = [(task_sample, (str(out), cfg, o["index"], e, o)) for o in my_objects for e in o["envmaps"]]
    bar = tqdm(total=len(samples) * cfg.views, desc=f"{cfg.dataset}: views", unit="view", disable=not progress)
    for r in _completed(samples, workers, threads, recycle):
        if r["skipped"]:
            stats["skipped_samples"] += 1
        else:
            stats["cycles_s"] += r["cycles_s"]
            stats["sample_s"] += r["total_s"]
            stats["rendered_views"] += r["rendered"]
        bar.update(r["views"])
    bar.close()
    wall = time.perf_counter() - t_start
    stats.update(wall_s=wall, workers=workers, threads_per_worker=threads, shard=f"{si}/{sn}",
                 render_overhead=(stats["sample_s"] - stats["cycles_s"]) / stats["cycles_s"] if stats["cycles_s"] else None,
                 seconds_per_view=stats["sample_s"] / stats["rendered_views"] if stats["rendered_views"] else None)
    _write_json(layout.timing(si, sn), stats)
    if preview and all(layout.sample_json(o["index"], e).exists() for o in p["objects"] for e in o["envmaps"]):
        from .preview import contact_sheet

        contact_sheet(out)
    return stats
