"""A set of procedural environment maps alone, no object rendered: what the light space learns from
(``python -m datagen.envmap_set --out data/envmaps``; ``make light-space``).

The maps are the datasets' kinds (outdoor skies and indoor rooms, :mod:`datagen.envmaps`, in the same share and HDR
range) drawn from a seed stream of their own: no map of any dataset's split (whose seeds are
``plan.seed_for(cfg, ENV, i, 1)``) is among them, and no file map (Blender's bundled HDRIs stay the held-out real light).

Layout: ``maps/NNNNN.exr`` (equirect, linear radiance, the project's convention), ``maps/NNNNN.json`` (its kind and
generator parameters), and ``manifest.json`` once every map is there. Resumable: a rerun renders the missing maps only.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from dibrpp.cli_args import Parser, check_output_folder, float_in, int_in, non_negative_int
from dibrpp.io import DataError, atomic_path, read_exr, write_exr

from .config import OUTDOOR_SHARE

FORMAT = "dibrpp-envmap-set-1"
STREAM = 7  # this set's seed purpose, beside the datasets' (plan.ENV ... plan.TONE are 1-6)


def map_seed(seed: int, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(seed), STREAM, int(index)])


def map_kind(seed: int, index: int, outdoor_share: float = OUTDOOR_SHARE) -> str:
    draw = np.random.default_rng(map_seed(seed, index).spawn(1)[0]).random()
    return "outdoor" if draw < outdoor_share else "indoor"


def map_path(out: Path, index: int) -> Path:
    return out / "maps" / f"{index:05d}.exr"


def render_set(out: Path, count: int, seed: int = 0, height: int = 64, outdoor_share: float = OUTDOOR_SHARE,
               progress: bool = True) -> int:
    """Render the maps of the set that are missing; write the manifest when all ``count`` are there. Returns how many
    were rendered."""
    from tqdm import tqdm

    from . import envmaps

    out.mkdir(parents=True, exist_ok=True)
    manifest = out / "manifest.json"
    if manifest.exists():
        saved = json.loads(manifest.read_text())
        if (saved.get("seed"), saved.get("height"), saved.get("outdoor_share")) != (seed, height, outdoor_share):
            raise SystemExit(f"error: --out {out} holds a set made with other settings ({saved}); choose another --out")
    todo = [i for i in range(count) if not map_path(out, i).exists()]
    for i in tqdm(todo, desc="env maps", unit="map", disable=not progress):
        t0 = time.perf_counter()
        kind = map_kind(seed, i, outdoor_share)
        env, params = envmaps.make_envmap(kind, np.random.default_rng(map_seed(seed, i)), height, 2 * height, spp=32)
        record = dict(index=i, kind=kind, params=params, seconds=round(time.perf_counter() - t0, 3))
        with atomic_path(map_path(out, i).with_suffix(".json")) as tmp:
            tmp.write_text(json.dumps(record))
        write_exr(map_path(out, i), env)  # last: its presence marks the map done
    kinds = [json.loads(map_path(out, i).with_suffix(".json").read_text())["kind"] for i in range(count)]
    with atomic_path(manifest) as tmp:
        tmp.write_text(json.dumps(dict(format=FORMAT, count=count, seed=seed, height=height,
                                       outdoor_share=outdoor_share, kinds=kinds), indent=1))
    return len(todo)


def read_set(folder: Path) -> tuple[np.ndarray, list[str]]:
    """(N, H, 2H, 3) float32 radiance and each map's kind, from a finished set."""
    manifest = Path(folder) / "manifest.json"
    if not manifest.exists():
        raise FileNotFoundError(f"{folder} holds no finished env-map set (no manifest.json); run "
                                f"`python -m datagen.envmap_set --out {folder}` (or `make light-space`) first")
    saved = json.loads(manifest.read_text())
    if saved.get("format") != FORMAT:
        raise ValueError(f"{manifest} is not an env-map set of this version (format {saved.get('format')!r})")
    maps = np.stack([read_exr(map_path(Path(folder), i)) for i in range(saved["count"])])
    return maps.astype(np.float32), list(saved["kinds"])


def main(argv=None) -> int:
    p = Parser(prog="python -m datagen.envmap_set", description=__doc__)
    p.add_argument("--out", type=Path, required=True, help="output folder (reruns resume into it)")
    p.add_argument("--count", type=int_in(1, 100_000), default=600, help="number of maps")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the set")
    p.add_argument("--envmap-height", type=int_in(1, 1024), default=64, help="map height; width is twice that")
    p.add_argument("--outdoor-share", type=float_in(0.0, 1.0), default=OUTDOOR_SHARE,
                   help="share of outdoor skies, the rest rooms (the datasets')")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    a = p.parse_args(argv)
    try:
        check_output_folder("--out", a.out)
    except DataError as e:
        p.exit(2, f"error: {e}\n")
    done = render_set(a.out, a.count, a.seed, a.envmap_height, a.outdoor_share, progress=not a.quiet)
    print(f"{a.out}: {a.count} env maps ({done} rendered now)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
