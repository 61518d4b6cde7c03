"""A shape prior learned from the generator's cars alone: ``python -m pipelines.shape_prior --out data/shape-prior``.

The normals a mirror-like car shows the sun through are the predicted shape's: its errors there are the
object's, not the view's (the mean of one object's 24 predicted shapes is as far off), and descent from a sphere
does not find them (docs/experiments.md, entries 14 and 19). This gives the shape the structure instead, as the
light prior gives the light: the encoder's template (the icosphere, per-vertex positions) fitted to the normals
and outlines of ``CARS`` procedural cars (:func:`datagen.shapes.make_shape`, meshes only, no image rendered by
Cycles; seeds from a stream apart from every dataset's), made mirror-symmetric, and their principal components.
A run with the prior starts at the mean car and predicts the components' coefficients besides its own offsets.

The fitted templates are saved as they are made (``fits.pt``, resumable) and the fit is cached as ``prior.pt``
with a key naming the generator's source digest and the fit's settings; it is refitted when either changes.
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch

from dibrpp import Cameras, Renderer
from dibrpp.cli_args import Parser, positive_int
from dibrpp.io import DataError, atomic_path
from dibrpp.mesh import Meshes, icosphere, laplacian_smoothness, uniform_laplacian

from .losses import normal_loss, soft_iou_loss
from .template import mirror_index

CARS = 100
COMPONENTS = 24
FIT_STEPS = 150
SUBDIVISIONS = 3  # the encoder's template (ModelConfig.template_subdivisions)
SEED_STREAM = 0x5A9E  # keeps these cars' seeds apart from every dataset's
FITS_FILE, PRIOR_FILE = "fits.pt", "prior.pt"
W_LAPLACIAN = 0.02  # the training's smoothness weight (TrainConfig.w_laplacian), per template_radius ** 2
TEMPLATE_RADIUS = 12.0
# the fit's views: two rings round the car (the datasets' 27 degrees and a higher one, for roofs and hoods)
ELEVATIONS, AZIMUTHS, DISTANCE, FOV_DEG, RESOLUTION = (27.0, 60.0), tuple(range(0, 360, 60)), 60.0, 39.6, 64


def generator_digest() -> str:
    """The digest of the source that makes the cars: a change there changes the prior."""
    src = Path(__file__).resolve().parents[1] / "datagen" / "shapes.py"
    return hashlib.sha256(src.read_bytes()).hexdigest()[:16]


def fit_cameras() -> Cameras:
    elev, azim = zip(*[(e, a) for e in ELEVATIONS for a in AZIMUTHS])
    return Cameras.orbit(DISTANCE, torch.tensor(elev), torch.tensor(azim, dtype=torch.float32), FOV_DEG, RESOLUTION)


def symmetric(verts: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """(..., V, 3) the mean of the vertices and their mirror images under y -> -y."""
    return 0.5 * (verts + verts[..., mirror, :] * verts.new_tensor([1.0, -1.0, 1.0]))


def fit_template(mesh: Meshes, steps: int = FIT_STEPS) -> torch.Tensor:
    """(V, 3) the template's vertices fitted to ``mesh``'s normals and outline in :func:`fit_cameras`' views (with
    the training's smoothness), mirror-symmetric, from the sphere scaled per axis to the mesh's bounding box."""
    template = icosphere(SUBDIVISIONS)
    dirs, mirror = template.verts[0], mirror_index(template.verts[0])
    cameras, renderer = fit_cameras(), Renderer("sg")
    with torch.no_grad():
        target = renderer.render_normals(mesh.expand(len(cameras)), cameras)
    laplacian = uniform_laplacian(template.faces, dirs.shape[0])
    box = mesh.verts[0]
    verts = ((box.amax(0) + box.amin(0)) / 2 + dirs * (box.amax(0) - box.amin(0)) / 2).requires_grad_(True)
    opt = torch.optim.Adam([verts], lr=0.1)
    for step in range(steps):
        if step == 2 * steps // 3:
            opt.param_groups[0]["lr"] = 0.02
        v = symmetric(verts, mirror)[None]
        out = renderer.render_normals(template.with_verts(v.expand(len(cameras), -1, -1)), cameras)
        loss = (normal_loss(out.image, target.image) + soft_iou_loss(out.silhouette, target.alpha)
                + W_LAPLACIAN * laplacian_smoothness(v, laplacian) / TEMPLATE_RADIUS ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return symmetric(verts.detach(), mirror)


def car_mesh(index: int) -> Meshes:
    from datagen.shapes import make_shape  # scikit-image and trimesh: only where cars are made
    shape = make_shape("car", np.random.default_rng([SEED_STREAM, index]))
    return Meshes(torch.from_numpy(shape["verts"]).float()[None], torch.from_numpy(shape["faces"]))


def fit_cars(folder: Path, cars: int, steps: int, progress: bool = True) -> torch.Tensor:
    """(cars, V, 3) templates fitted to the first ``cars`` cars; resumes from (and extends) ``folder``/fits.pt."""
    from tqdm import tqdm
    path, key = folder / FITS_FILE, {"digest": generator_digest(), "steps": steps, "subdivisions": SUBDIVISIONS}
    fits = []
    if path.exists():
        saved = torch.load(path, weights_only=True)
        if saved.get("key") == json.dumps(key, sort_keys=True):
            fits = list(saved["fits"][:cars])
    for i in tqdm(range(len(fits), cars), initial=len(fits), total=cars, desc="fitting the template to cars",
                  disable=not progress):
        fits.append(fit_template(car_mesh(i), steps))
        with atomic_path(path) as tmp:
            torch.save({"key": json.dumps(key, sort_keys=True), "fits": torch.stack(fits)}, tmp)
    return torch.stack(fits)


def fit(templates: torch.Tensor, components: int) -> dict:
    """PCA of fitted templates (N, V, 3): {"mean": (V, 3), "basis": (K, V, 3) orthonormal, "std": (K,),
    "explained": (K,) cumulative share of the variance}."""
    x = templates.double().flatten(1)
    mean = x.mean(0)
    _, s, vt = torch.linalg.svd(x - mean, full_matrices=False)
    if components > len(s):
        raise ValueError(f"{components} components need at least as many fitted cars; there are {len(templates)}")
    variance = s ** 2 / (len(x) - 1)
    return {"mean": mean.view(-1, 3).float(), "basis": vt[:components].view(components, -1, 3).float(),
            "std": variance[:components].sqrt().float(),
            "explained": (variance[:components].cumsum(0) / variance.sum()).float()}


def prior_key(cars: int = CARS, components: int = COMPONENTS, steps: int = FIT_STEPS) -> str:
    """What a cached prior was fitted from: the generator's digest and the fit's settings."""
    return json.dumps({"digest": generator_digest(), "cars": cars, "components": components, "steps": steps,
                       "subdivisions": SUBDIVISIONS}, sort_keys=True)


def build(folder: Path, cars: int = CARS, components: int = COMPONENTS, steps: int = FIT_STEPS,
          progress: bool = True) -> dict:
    """The prior in ``folder``: read from its cache, or fitted (the cars first, resumably) and cached."""
    folder = Path(folder)
    key = prior_key(cars, components, steps)
    cache = folder / PRIOR_FILE
    if cache.exists():
        prior = torch.load(cache, weights_only=True)
        if prior.get("key") == key:
            return prior
    folder.mkdir(parents=True, exist_ok=True)
    prior = {**fit(fit_cars(folder, cars, steps, progress), components), "key": key}
    with atomic_path(cache) as tmp:
        torch.save(prior, tmp)
    return prior


def read(folder: Path) -> dict:
    """The cached prior of ``folder`` with the default settings (what a run is built with), or a DataError that
    says how to make it: none there, or one fitted to an older car generator or other settings."""
    cache = Path(folder) / PRIOR_FILE
    if not cache.exists():
        raise DataError(f"{folder}: no shape prior; fit it with `make shape-prior`")
    prior = torch.load(cache, weights_only=True)
    if prior.get("key") != prior_key():
        raise DataError(f"{cache}: fitted to another car generator or other settings; refit it with `make shape-prior`")
    return prior


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.shape_prior",
                description="fit the shape prior (PCA of the template fitted to procedural cars)")
    ap.add_argument("--out", default="data/shape-prior", metavar="DIR", help="its folder (default: data/shape-prior)")
    ap.add_argument("--cars", type=positive_int, default=CARS, metavar="N", help=f"cars to fit (default: {CARS})")
    ap.add_argument("--components", type=positive_int, default=COMPONENTS, metavar="K",
                    help=f"principal components (default: {COMPONENTS})")
    ap.add_argument("--steps", type=positive_int, default=FIT_STEPS, metavar="N",
                    help=f"Adam steps per car (default: {FIT_STEPS})")
    args = ap.parse_args(argv)
    if args.components > args.cars:
        ap.error(f"--components {args.components}: at most --cars ({args.cars})")
    prior = build(Path(args.out), args.cars, args.components, args.steps)
    explained = ", ".join(f"{k}: {100 * float(prior['explained'][k - 1]):.0f} %"
                          for k in (1, 2, 4, 8, len(prior["std"])) if k <= len(prior["std"]))
    print(f"shape prior: {len(prior['std'])} components of {args.cars} cars' fitted templates; variance explained by "
          f"the first {explained}; cached in {Path(args.out) / PRIOR_FILE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
