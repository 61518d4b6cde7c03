"""What a dataset holds, decided before anything renders (pure and deterministic): seeds, splits, env map
kinds, each object's material and env maps, and the views' azimuths and elevations."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .config import OUTDOOR_SHARE, Config
from .layout import DEFAULT_CAMERA

_DATASET_CODE = {"metallic": 1, "glossy": 2, "diffuse": 3}
# The purposes a seed is drawn for (the second key of seed_for): changing one changes the data.
ENV, OBJ, RENDER, SPLIT, MATERIAL, TONE = 1, 2, 3, 4, 5, 6


def seed_for(cfg: Config, *keys: int) -> int:
    """Independent, stable seeds per (dataset, purpose, index) from the run seed."""
    return int(np.random.SeedSequence([int(cfg.seed), _DATASET_CODE[cfg.dataset], *[int(k) for k in keys]])
               .generate_state(1)[0])


def render_seed(cfg: Config, obj: int, env: int, view: int) -> int:
    """Cycles' seed for one view (Cycles takes a 31-bit seed)."""
    return seed_for(cfg, RENDER, obj, env, view) % (1 << 31)


def azimuths(cfg: Config) -> list[float]:
    """The views' azimuths in degrees: all around, or for the diffuse heads the front half-circle."""
    if cfg.dataset == "diffuse":  # front views only, uniformly over the front half-circle
        return [-90.0 + 180.0 * (k + 0.5) / cfg.views for k in range(cfg.views)]
    return [360.0 * k / cfg.views for k in range(cfg.views)]


def elevations(cfg: Config, obj: int) -> list[float]:
    """The camera elevations in degrees of object ``obj``'s views: the configured ones taken in turn, starting one
    later on each next object (object 0's views 0, 1, 2, ... at the first, second, third, ...; object 1's at the
    second, third, ...), so that across the objects every azimuth is seen from every elevation; or the default
    camera's for every view."""
    camera = replace(DEFAULT_CAMERA, elevations_deg=tuple(cfg.elevations or ()))
    return [camera.view_elevation_deg(obj, v) for v in range(cfg.views)]


def _split(n: int, rng: np.random.Generator) -> tuple[list[int], list[int]]:
    perm = rng.permutation(n)
    n_test = int(round(n / 5)) if n >= 2 else 0
    return sorted(int(i) for i in perm[n_test:]), sorted(int(i) for i in perm[:n_test])


def _split_envmaps(cfg: Config, rng: np.random.Generator) -> tuple[list[int], list[int]]:
    """Env maps from files (indices 0..F-1) and procedural ones (F..) are split 4:1 each, so that both
    splits hold both kinds."""
    nf = cfg.num_file_envmaps
    if not nf:
        return _split(cfg.num_envmaps, rng)
    f_train, f_test = _split(nf, rng)
    p_train, p_test = _split(cfg.num_envmaps - nf, rng)
    return f_train + [nf + i for i in p_train], f_test + [nf + i for i in p_test]


def _env_kind(cfg: Config, i: int) -> str:
    if i < cfg.num_file_envmaps:
        return "file"
    share = OUTDOOR_SHARE if cfg.outdoor_share is None else float(cfg.outdoor_share)
    return "outdoor" if np.random.default_rng(seed_for(cfg, ENV, i)).random() < share else "indoor"


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


def plan(cfg: Config) -> dict:
    """Splits (4:1 for objects and env maps), env kinds, material per object, env maps per object."""
    rng = np.random.default_rng(seed_for(cfg, SPLIT))
    obj_train, obj_test = _split(cfg.num_objects, rng)
    env_train, env_test = _split_envmaps(cfg, rng)
    objects = []
    unseen = True  # test objects are lit only by test env maps
    for i in range(cfg.num_objects):
        split = "test" if i in obj_test else "train"
        pool = env_test if split == "test" else env_train
        if len(pool) < cfg.envs_per_object:
            # too few maps in this split (tiny runs): draw from all maps; the manifest says so
            pool = list(range(cfg.num_envmaps))
            unseen = False
        r = np.random.default_rng(seed_for(cfg, MATERIAL, i))
        envs = sorted(int(e) for e in r.choice(pool, cfg.envs_per_object, replace=False))
        objects.append(dict(index=i, split=split, envmaps=envs, material=material_for(cfg, r),
                            tone=float((np.random.default_rng(seed_for(cfg, TONE)).permutation(cfg.num_objects)[i]
                                        + r.uniform()) / cfg.num_objects)))
    return dict(objects=objects, splits=dict(objects=dict(train=obj_train, test=obj_test),
                                             envmaps=dict(train=env_train, test=env_test),
                                             test_objects_see_only_test_envmaps=unseen),
                env_kind=[_env_kind(cfg, i) for i in range(cfg.num_envmaps)])
