"""The on-disk layout of a generated dataset, in one place: the writer (:mod:`datagen.generate`,
:mod:`datagen.preview`) and the reader (:mod:`datagen.reader`) both ask :class:`DatasetLayout` for
every path, and :class:`CameraSetup` reads the orbit camera back from the manifest.

This module imports neither ``bpy`` nor ``torch`` (only the standard library), so a reader never pulls
Blender in::

    layout = DatasetLayout("data/glossy")
    layout.manifest                       # data/glossy/manifest.json
    layout.view_image(3, 7, 5)            # data/glossy/samples/obj_0003_env_0007/view_05.exr
    manifest = layout.read_manifest()     # checked: ManifestError (a ValueError) names the file otherwise
    camera = CameraSetup.from_manifest(manifest)
    camera.distance, camera.elevation_deg, camera.fov    # 60.0, 27.0, 0.691 (radians)

The tree (one folder per dataset)::

    manifest.json                                 generator version, config, seeds, splits, camera, ...
    preview.png                                   contact sheet
    timing/shard_0_of_1.json                      wall / Cycles time of the last run that rendered
    .datagen_shard_0_of_1.lock, .datagen_manifest.lock   held by a running datagen (see datagen.locking)
    envmaps/env_0007.exr | .png | .json           linear HDR equirect map, its preview, its record (done marker)
    objects/obj_0003/mesh.npz | mesh.obj | mesh.mtl | texture.png | object.json
    samples/obj_0003_env_0007/sample.json         done marker of the sample
    samples/obj_0003_env_0007/view_05.exr | view_05.png | view_05_mask.png | view_05_albedo.exr | view_05.json
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["CameraSetup", "DEFAULT_CAMERA", "DatasetLayout", "ManifestError"]


@dataclass(frozen=True)
class CameraSetup:
    """The orbit cameras of a dataset: every view looks at the origin from ``distance`` at ``elevation_deg``
    and one azimuth of ``azimuths_deg``, with Blender's ``fov`` (radians, square image). A set made with
    ``--elevations`` has its elevations in ``elevations_deg``, taken in turn by the views (:meth:`view_elevation_deg`),
    and their median in ``elevation_deg``."""

    distance: float
    elevation_deg: float
    fov: float
    azimuths_deg: tuple = ()
    resolution: int | None = None
    elevations_deg: tuple = ()

    @property
    def fov_deg(self) -> float:
        return math.degrees(self.fov)

    @classmethod
    def from_manifest(cls, manifest: dict) -> "CameraSetup":
        """The set-up a manifest records under ``camera``: KeyError if it has none, ValueError (saying what is
        wrong) if it is malformed."""
        if not isinstance(manifest, dict):
            raise ValueError(f"a manifest must be a JSON object, found {type(manifest).__name__}")
        c = manifest["camera"]
        if not isinstance(c, dict):
            raise ValueError(f"the manifest's 'camera' must be an object, found {type(c).__name__}")
        try:
            res = c.get("resolution")
            return cls(distance=float(c["distance"]), elevation_deg=float(c["elevation_deg"]), fov=float(c["fov"]),
                       azimuths_deg=tuple(float(a) for a in c.get("azimuths_deg", ())),
                       resolution=None if res is None else int(res),
                       elevations_deg=tuple(float(e) for e in c.get("elevations_deg", ())))
        except (TypeError, ValueError) as e:
            raise ValueError(f"the manifest's 'camera' is malformed ({e}); expected numbers distance, "
                             "elevation_deg, fov, a list azimuths_deg (and elevations_deg) and an integer "
                             "resolution") from e

    def to_manifest(self) -> dict:
        """The manifest's ``camera`` entry (key order as the generator has always written it; ``elevations_deg``
        only for a set made with ``--elevations``)."""
        entry = dict(distance=self.distance, elevation_deg=self.elevation_deg, fov=self.fov,
                     azimuths_deg=list(self.azimuths_deg), resolution=self.resolution)
        if self.elevations_deg:
            entry["elevations_deg"] = list(self.elevations_deg)
        return entry

    def view_elevation_deg(self, obj: int, view: int) -> float:
        """The elevation of object ``obj``'s view ``view``: the elevations taken in turn, starting one later on each
        next object (the one place this rule lives; :func:`datagen.plan.elevations` renders by it)."""
        if not self.elevations_deg:
            return self.elevation_deg
        return float(self.elevations_deg[(view + obj) % len(self.elevations_deg)])


class ManifestError(ValueError):
    """A manifest.json that cannot be read as a datagen manifest."""


_REGENERATE = "regenerate the dataset with `python -m datagen` (or restore its manifest.json)"


def _manifest_problem(manifest) -> str | None:
    """What is wrong with the structure of a parsed manifest, or None."""
    if not isinstance(manifest, dict):
        return f"the file holds a JSON {type(manifest).__name__}, not an object"
    config = manifest.get("config")
    if not isinstance(config, dict):
        return "'config' is missing or not an object"
    for key in ("views", "resolution"):
        if not isinstance(config.get(key), int) or config[key] <= 0:
            return f"config '{key}' is {config.get(key)!r}, not a positive integer"
    objects = manifest.get("objects")
    if not isinstance(objects, list):
        return "'objects' is missing or not a list"
    for o in objects:
        if not (isinstance(o, dict) and isinstance(o.get("index"), int) and isinstance(o.get("split"), str)
                and isinstance(o.get("envmaps"), list) and all(isinstance(e, int) for e in o["envmaps"])
                and isinstance(o.get("material"), dict)):
            return f"an entry of 'objects' is not {{index, split, envmaps: [int], material: {{...}}}}: {str(o)[:80]}"
    try:
        CameraSetup.from_manifest(manifest)
    except (KeyError, ValueError) as e:
        return f"'camera' is missing or malformed ({e})"
    return None


# The generator's cameras: Blender's default camera (50 mm lens on a 36 mm sensor: 39.6 deg) at 60 units,
# 27 deg above the horizon (objects are normalised to [-18, 18]).
DEFAULT_CAMERA = CameraSetup(distance=60.0, elevation_deg=27.0, fov=2 * math.atan(18.0 / 50.0))

_SAMPLE_NAME = re.compile(r"^obj_(\d+)_env_(\d+)$")


class DatasetLayout:
    """Every path of a dataset folder ``root``. Indices are ints; nothing here touches the disk except
    :meth:`finished_samples` (a directory listing)."""

    VIEW_SUFFIXES = (".exr", ".png", "_mask.png", "_albedo.exr", ".json")  # the files of one view, in order

    def __init__(self, root):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"DatasetLayout({str(self.root)!r})"

    # ------------------------------------------------------------------ top level
    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def preview(self) -> Path:
        return self.root / "preview.png"

    def timing(self, shard_index: int, shard_count: int) -> Path:
        return self.root / "timing" / f"shard_{shard_index}_of_{shard_count}.json"

    def run_lock(self, shard_index: int = 0, shard_count: int = 1) -> Path:
        """Locked (flock) by the datagen run writing this shard; left in place after it ends."""
        return self.root / f".datagen_shard_{shard_index}_of_{shard_count}.lock"

    @property
    def manifest_lock(self) -> Path:
        """Locked (flock) by a datagen run while it checks and writes the manifest."""
        return self.root / ".datagen_manifest.lock"

    def read_manifest(self) -> dict:
        """The manifest, checked to have the structure the writer gives it (config, objects, camera);
        ManifestError naming the file and what is wrong otherwise."""
        path = self.manifest
        try:
            manifest = json.loads(path.read_text())
        except FileNotFoundError:
            raise ManifestError(f"{path}: no such file; is {self.root} a dataset written by `python -m datagen`?") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ManifestError(f"{path}: unreadable or corrupt JSON ({e}); {_REGENERATE}") from e
        problem = _manifest_problem(manifest)
        if problem:
            raise ManifestError(f"{path}: not a datagen manifest: {problem}; {_REGENERATE}")
        return manifest

    # ------------------------------------------------------------------ environment maps
    @property
    def envmaps_dir(self) -> Path:
        return self.root / "envmaps"

    def envmap(self, env: int) -> Path:
        """Linear HDR equirect map (H, 2H, RGB), top row first."""
        return self.envmaps_dir / f"env_{env:04d}.exr"

    def envmap_png(self, env: int) -> Path:
        return self.envmaps_dir / f"env_{env:04d}.png"

    def envmap_json(self, env: int) -> Path:
        """The map's record; its existence marks the map finished."""
        return self.envmaps_dir / f"env_{env:04d}.json"

    # ------------------------------------------------------------------ objects
    @property
    def objects_dir(self) -> Path:
        return self.root / "objects"

    def object_dir(self, obj: int) -> Path:
        return self.objects_dir / f"obj_{obj:04d}"

    def mesh_npz(self, obj: int) -> Path:
        return self.object_dir(obj) / "mesh.npz"

    def mesh_obj(self, obj: int) -> Path:
        return self.object_dir(obj) / "mesh.obj"

    def mesh_mtl(self, obj: int) -> Path:
        return self.object_dir(obj) / "mesh.mtl"

    def texture(self, obj: int) -> Path:
        return self.object_dir(obj) / "texture.png"

    def object_json(self, obj: int) -> Path:
        """The object's record; its existence marks the object finished."""
        return self.object_dir(obj) / "object.json"

    # ------------------------------------------------------------------ samples (object x env map) and views
    @property
    def samples_dir(self) -> Path:
        return self.root / "samples"

    @staticmethod
    def sample_name(obj: int, env: int) -> str:
        return f"obj_{obj:04d}_env_{env:04d}"

    @staticmethod
    def parse_sample_name(name: str) -> tuple[int, int]:
        """(object, env map) of a sample folder name ``obj_0003_env_0007``."""
        m = _SAMPLE_NAME.match(Path(name).name)
        if not m:
            raise ValueError(f"{name!r} is not a sample folder name (obj_XXXX_env_XXXX)")
        return int(m.group(1)), int(m.group(2))

    def sample_dir(self, obj: int, env: int) -> Path:
        return self.samples_dir / self.sample_name(obj, env)

    def sample_json(self, obj: int, env: int) -> Path:
        """The sample's record; its existence marks the sample finished."""
        return self.sample_dir(obj, env) / "sample.json"

    @classmethod
    def view_files(cls, view: int) -> list[str]:
        """File names of one view inside its sample folder: exr, png, mask png, albedo exr, camera json."""
        return [f"view_{view:02d}{s}" for s in cls.VIEW_SUFFIXES]

    def view_image(self, obj: int, env: int, view: int, srgb: bool = False) -> Path:
        """Linear RGBA EXR (alpha = anti-aliased coverage), or with ``srgb`` its sRGB RGBA PNG preview."""
        return self.sample_dir(obj, env) / f"view_{view:02d}{'.png' if srgb else '.exr'}"

    def view_mask(self, obj: int, env: int, view: int) -> Path:
        return self.sample_dir(obj, env) / f"view_{view:02d}_mask.png"

    def view_albedo(self, obj: int, env: int, view: int) -> Path:
        return self.sample_dir(obj, env) / f"view_{view:02d}_albedo.exr"

    def view_camera(self, obj: int, env: int, view: int) -> Path:
        return self.sample_dir(obj, env) / f"view_{view:02d}.json"

    def finished_samples(self) -> list[tuple[int, int]]:
        """(object, env map) of every sample folder holding its done marker, sorted."""
        out = []
        for marker in self.samples_dir.glob("*/sample.json"):
            try:
                out.append(self.parse_sample_name(marker.parent.name))
            except ValueError:
                continue
        return sorted(out)
