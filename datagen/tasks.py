"""The work a worker process does: make one env map, one object or one sample (an object under an env map,
all its views), each skipped when its done marker exists and written file by file, atomically, so that a
killed run resumes where it stopped."""
from __future__ import annotations

import time

import numpy as np

from dibrpp.io import atomic_path

from .config import Config
from .layout import DEFAULT_CAMERA, DatasetLayout
from .plan import ENV, OBJ, azimuths, elevations, render_seed, seed_for
from .records import write_json
from .workers import cycles_device, cycles_threads, exit_if_orphaned


def _task_envmap(out: str, i: int, make) -> dict:
    """Env map ``i`` unless finished: ``make()`` -> (env (H, 2H, 3), record); writes the EXR, its tone-mapped
    PNG and the record (the done marker)."""
    from dibrpp.io import write_exr, write_png

    layout = DatasetLayout(out)
    if layout.envmap_json(i).exists():
        return dict(kind="envmap", index=i, skipped=True)
    t0 = time.perf_counter()
    env, record = make()
    exit_if_orphaned()
    write_exr(layout.envmap(i), env)
    write_png(layout.envmap_png(i), env / (1 + env))
    write_json(layout.envmap_json(i), dict(index=i, **record, shape=list(env.shape),
                                           seconds=time.perf_counter() - t0))
    return dict(kind="envmap", index=i, skipped=False, seconds=time.perf_counter() - t0)


def task_envmap(out: str, cfg: Config, i: int, kind: str, threads: int | None = None) -> dict:
    """Procedural env map ``i`` (an outdoor sky or an indoor room), rendered with ``threads`` Cycles threads
    (default: the worker's)."""
    def make():
        from . import envmaps

        rng = np.random.default_rng(seed_for(cfg, ENV, i, 1))
        h = cfg.envmap_height
        env, params = envmaps.make_envmap(kind, rng, h, 2 * h, spp=32,
                                          threads=cycles_threads() if threads is None else threads)
        return env, dict(kind=kind, params=params, seed=seed_for(cfg, ENV, i, 1))
    return _task_envmap(out, i, make)


def task_envmap_file(out: str, cfg: Config, i: int, source: dict) -> dict:
    """Env map ``i`` from one of your files: resampled to the dataset's size (area average)."""
    def make():
        from .envmap_files import load_envmap_source

        env = load_envmap_source(cfg.envmaps_dir, source, cfg.envmap_height)
        return env, dict(kind="file", source=source, resampling="area average over solid angle (energy preserving)")
    return _task_envmap(out, i, make)


def task_object(out: str, cfg: Config, i: int, info: dict) -> dict:
    """Object ``i`` unless finished: its procedural mesh, UV unwrap and painted texture, the mesh as npz and
    OBJ, and its record (the done marker)."""
    from . import shapes, textures

    layout = DatasetLayout(out)
    if layout.object_json(i).exists():
        return dict(kind="object", index=i, skipped=True)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed_for(cfg, OBJ, i))
    obj = shapes.make_shape(cfg.shape_kind, rng, grid=cfg.grid)
    uvs, face_uvs = shapes.unwrap(obj["verts"], obj["faces"], resolution=cfg.texture_size)
    tex, style = textures.bake_texture(obj, uvs, face_uvs, cfg.texture_size, rng, tone=info["tone"])
    exit_if_orphaned()
    _write_object_files(layout, i, obj, uvs, face_uvs, tex)
    meta = dict(index=i, kind=cfg.shape_kind, split=info["split"], material=info["material"], envmaps=info["envmaps"],
                shape_params=obj["shape"].params, paint=style, normalisation=obj["normalisation"],
                num_verts=len(obj["verts"]), num_faces=len(obj["faces"]), texture_size=cfg.texture_size,
                seed=seed_for(cfg, OBJ, i), seconds=time.perf_counter() - t0)
    write_json(layout.object_json(i), meta)
    return dict(kind="object", index=i, skipped=False, seconds=time.perf_counter() - t0)


def _write_object_files(layout: DatasetLayout, i: int, obj: dict, uvs, face_uvs, tex) -> None:
    from dibrpp.io import write_png, write_textured_obj

    layout.object_dir(i).mkdir(parents=True, exist_ok=True)
    with atomic_path(layout.mesh_npz(i)) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, verts=obj["verts"].astype(np.float32), faces=obj["faces"], uvs=uvs, face_uvs=face_uvs)
    write_png(layout.texture(i), tex, srgb=False)  # values are sRGB already
    # mesh.obj + mesh.mtl, whose map_Kd names the texture relative to the OBJ
    write_textured_obj(layout.mesh_obj(i), obj["verts"], obj["faces"], uvs, face_uvs, layout.texture(i).name)


# ----------------------------------------------------------------------------- samples

def task_sample(out: str, cfg: Config, i: int, env: int, info: dict) -> dict:
    """Sample (object ``i``, env map ``env``) unless finished: every view not yet on disk, then the sample's
    record (the done marker) with the size of every file, so a later run can check them."""
    layout = DatasetLayout(out)
    if layout.sample_json(i, env).exists():
        return dict(kind="sample", obj=i, env=env, skipped=True, views=cfg.views)
    t0 = time.perf_counter()
    scene = _sample_scene(layout, cfg, i, env, info)
    build_s = time.perf_counter() - t0
    layout.sample_dir(i, env).mkdir(parents=True, exist_ok=True)
    rendered = 0
    for v, (az, el) in enumerate(zip(azimuths(cfg), elevations(cfg, i))):
        if all(p.exists() for p in _view_paths(layout, i, env, v)):
            continue  # finished before a crash
        _render_view(scene, layout, cfg, i, env, v, az, el)
        rendered += 1
    total = time.perf_counter() - t0
    timing = dict(total_s=total, cycles_s=scene.render_seconds, build_s=build_s, views_rendered=rendered,
                  renders=scene.renders)
    exit_if_orphaned()
    write_json(layout.sample_json(i, env), _sample_record(layout, cfg, i, env, info, timing))
    return dict(kind="sample", obj=i, env=env, skipped=False, views=cfg.views, rendered=rendered,
                total_s=total, cycles_s=scene.render_seconds)


def _view_paths(layout: DatasetLayout, i: int, env: int, v: int) -> list:
    return [layout.sample_dir(i, env) / name for name in layout.view_files(v)]


def _sample_scene(layout: DatasetLayout, cfg: Config, i: int, env: int, info: dict):
    """The Cycles scene of one sample: the object's mesh, material and texture under env map ``env``."""
    from . import cycles

    with np.load(layout.mesh_npz(i)) as m:
        verts, faces, uvs, face_uvs = m["verts"], m["faces"], m["uvs"], m["face_uvs"]
    material = cycles.PrincipledMaterial.from_dict(info["material"], texture=layout.texture(i))
    settings = cycles.RenderSettings(resolution=cfg.resolution, spp=cfg.spp, max_bounces=cfg.max_bounces,
                                     denoise=bool(cfg.denoise), albedo_aov=True, threads=cycles_threads(),
                                     device=cycles_device())
    return cycles.build_scene(verts, faces, envmap=layout.envmap(env), settings=settings, material=material,
                              uvs=uvs, face_uvs=face_uvs)


def _render_view(scene, layout: DatasetLayout, cfg: Config, i: int, env: int, v: int, az: float, el: float) -> None:
    """Render view ``v`` (azimuth ``az``, elevation ``el``) and write its five files: RGBA EXR and PNG, mask, albedo,
    camera."""
    import torch

    from dibrpp.conventions import orbit_world_to_camera
    from dibrpp.io import write_exr, write_png

    from . import cycles

    cam = DEFAULT_CAMERA
    w2c = orbit_world_to_camera(torch.tensor(cam.distance, dtype=torch.float64), el, az)
    cycles.set_camera(scene, w2c.numpy(), cam.fov)
    cycles.set_seed(scene, render_seed(cfg, i, env, v))
    res = cycles.render(scene)
    rgba, albedo = res["rgba"], res["albedo"]
    exr, png, mask, albedo_exr, camera_json = _view_paths(layout, i, env, v)
    exit_if_orphaned()
    write_exr(exr, rgba)
    write_png(png, rgba)
    write_png(mask, rgba[..., 3])
    write_exr(albedo_exr, albedo)
    write_json(camera_json, dict(world_to_camera=w2c.tolist(), fov=cam.fov, resolution=cfg.resolution,
                                 azimuth_deg=az, elevation_deg=el, distance=cam.distance,
                                 convention="dibrpp.conventions: world +Z up, camera looks down -Z, +Y up"))


def _sample_record(layout: DatasetLayout, cfg: Config, i: int, env: int, info: dict, timing: dict) -> dict:
    """sample.json: what the sample is, every file with its size, the render seeds and the timing."""
    files = {p.name: p.stat().st_size for v in range(cfg.views) for p in _view_paths(layout, i, env, v)}
    return dict(object=i, envmap=env, split=info["split"], material=info["material"], views=cfg.views,
                azimuths_deg=azimuths(cfg), **(dict(elevations_deg=elevations(cfg, i)) if cfg.elevations else {}),
                files=files,
                render_seeds=[render_seed(cfg, i, env, v) for v in range(cfg.views)], timing=timing)
