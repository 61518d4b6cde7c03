"""Env maps alone, for the light prior: ``python -m datagen.prior_maps --out data/light-prior [--count N]``.

The same procedural generator as the datasets (:mod:`datagen.envmaps`: Cycles skies with a sun, clouds and
ground; path-traced rooms; 60 % outdoor), but no car is rendered, so a few thousand maps take minutes. Their
seeds are drawn from their own stream, so no map here is a dataset's map (and none is a test map).

Layout of ``--out`` (owned here)::

    maps_0000.npy ...   (CHUNK, H, 2H, 3) float32 linear radiance, CHUNK maps each, written atomically
    manifest.json       count, height, seed and the generator's digest (the sources the maps depend on)

Resumable: finished chunks are kept, and a folder made by another version of the generator is refused.
"""
from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dibrpp.cli_args import Parser, check_output_folder, non_negative_int, positive_int
from dibrpp.io import DataError, atomic_path

from .config import OUTDOOR_SHARE  # as in the datasets

CHUNK = 100
SEED_STREAM = 0x5E1F  # keeps these seeds apart from every dataset's
MANIFEST = "manifest.json"
SOURCES = ("envmaps.py", "textures.py")  # what the maps depend on, besides Blender


def generator_digest() -> str:
    import bpy

    h = hashlib.sha256(bpy.app.version_string.encode())
    for name in SOURCES:
        h.update((Path(__file__).parent / name).read_bytes())
    return h.hexdigest()[:16]


def chunk_path(out: Path, k: int) -> Path:
    return out / f"maps_{k:04d}.npy"


def make_chunk(out: Path, k: int, height: int, seed: int, spp: int, chunk: int = CHUNK) -> int:
    """Render chunk ``k`` (maps k * chunk ... (k + 1) * chunk - 1, in a worker) and write it."""
    from .envmaps import make_envmap
    from .workers import exit_if_orphaned

    maps = []
    for i in range(k * chunk, (k + 1) * chunk):
        rng = np.random.default_rng(np.random.SeedSequence([seed, SEED_STREAM, i]))
        kind = "outdoor" if rng.random() < OUTDOOR_SHARE else "indoor"
        env, _ = make_envmap(kind, rng, height, 2 * height, spp=spp, threads=1)
        maps.append(env)
    exit_if_orphaned()
    with atomic_path(chunk_path(out, k)) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.stack(maps).astype(np.float32))
    return k


def generate(out: Path, count: int, height: int = 32, seed: int = 0, spp: int = 16, workers: int = 2,
             progress: bool = True, chunk: int = CHUNK) -> None:
    out.mkdir(parents=True, exist_ok=True)
    chunks = -(-count // chunk)
    manifest = {"count": chunks * chunk, "height": height, "seed": seed, "spp": spp, "chunk": chunk,
                "generator": generator_digest()}
    path = out / MANIFEST
    if path.exists():
        old = json.loads(path.read_text())
        changed = {k: (old.get(k), v) for k, v in manifest.items() if k != "count" and old.get(k) != v}
        if changed:
            raise DataError(f"{out} holds maps made with other settings or another generator ({changed}); "
                            "choose another --out or delete it to rebuild")
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(manifest, indent=2) + "\n")
    todo = [k for k in range(chunks) if not chunk_path(out, k).exists()]
    from .workers import init_worker

    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=init_worker,
                             initargs=(1, os.getpid())) as pool:
        jobs = [pool.submit(make_chunk, out, k, height, seed, spp, chunk) for k in todo]
        for job in tqdm(as_completed(jobs), total=len(jobs), desc=f"env maps for the light prior ({chunk} per chunk)",
                        disable=not progress):
            job.result()


def main(argv=None) -> int:
    ap = Parser(prog="python -m datagen.prior_maps", description=(
        "render procedural env maps (no objects) for the light prior; resumable"))
    ap.add_argument("--out", default="data/light-prior", metavar="DIR", help="output folder (default: data/light-prior)")
    ap.add_argument("--count", type=positive_int, default=2000, metavar="N",
                    help=f"number of maps, rounded up to a multiple of {CHUNK} (default: 2000)")
    ap.add_argument("--height", type=positive_int, default=32, metavar="N", help="map height; width is twice (default: 32)")
    ap.add_argument("--workers", type=positive_int, default=2, metavar="N", help="render processes (default: 2)")
    ap.add_argument("--seed", type=non_negative_int, default=0, help="seed of the maps (default: 0)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    out = Path(args.out)
    try:
        check_output_folder("--out", out)
        generate(out, args.count, args.height, args.seed, workers=args.workers, progress=not args.no_progress)
    except DataError as e:
        ap.error(str(e))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
