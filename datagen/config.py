"""A dataset's settings: the presets, :class:`Config` and its checks, and how the manifest records it."""
from __future__ import annotations

from dataclasses import asdict, dataclass

DATASETS = ("metallic", "glossy", "diffuse")

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
# 4096-spp reference (python -m studies.noise_study). 64 spp + OpenImageDenoise (albedo and normal guides)
# brings it to 10 %, as good as 256 spp, at 2.5x the time of 32 spp instead of 8x.
DATASET_DEFAULTS = {"diffuse": dict(spp=64, denoise=True)}

# The model's encoder downsamples images by 16, so training takes a side that is a multiple of 16
# (pipelines.training.config.TrainConfig.image_size); a dataset at another side could not be trained on.
MAX_RESOLUTION = 1024
RESOLUTION_MULTIPLE = 16

_POSITIVE = ("num_objects", "num_envmaps", "envs_per_object", "views", "resolution", "spp", "texture_size",
             "envmap_height", "grid")
# Optional settings: left out of the manifest while unset, so older datasets keep matching their config.
_OPTIONAL = ("envmaps_dir", "procedural_envmaps", "denoise", "outdoor_share", "elevations")
OUTDOOR_SHARE = 0.6  # the share of procedural env maps that are skies (the rest are rooms), unless set


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
    envmaps_dir: str | None = None  # a folder of your own HDRIs: maps 0..F-1
    procedural_envmaps: int | None = None  # with envmaps_dir: how many procedural maps follow the files
    denoise: bool | None = None  # OpenImageDenoise on the shaded renders (albedo + normal guides)
    outdoor_share: float | None = None  # share of the procedural maps that are skies (None: OUTDOOR_SHARE)
    elevations: list[float] | None = None  # camera elevations (deg) the views take in turn (None: the default's)

    @property
    def num_file_envmaps(self) -> int:
        return self.num_envmaps - int(self.procedural_envmaps or 0) if self.envmaps_dir else 0

    @property
    def shape_kind(self) -> str:
        return "head" if self.dataset == "diffuse" else "car"

    def validate(self) -> None:
        if self.dataset not in DATASETS:
            raise ValueError(f"unknown dataset {self.dataset!r}; choose one of {', '.join(DATASETS)}")
        self._validate_envmap_sources()
        for name in _POSITIVE:
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(self, name)}")
        self._validate_resolution()
        self._validate_envs_per_object()
        if self.max_bounces < 0:
            raise ValueError("--max-bounces must be >= 0")
        if self.outdoor_share is not None and not 0.0 <= float(self.outdoor_share) <= 1.0:
            raise ValueError(f"--outdoor-share is the share of procedural maps that are skies, in [0, 1]; got "
                             f"{self.outdoor_share}")
        if self.elevations is not None and not (self.elevations and all(-90 < e < 90 for e in self.elevations)):
            raise ValueError(f"--elevations {self.elevations}: give one or more elevations strictly between -90 and "
                             "90 degrees (a camera at a pole has no up direction)")
        if self.envmaps_dir and self.num_file_envmaps <= 0:
            raise ValueError(f"--envmaps {self.envmaps_dir}: no env map files counted")

    def _validate_envmap_sources(self) -> None:
        if self.procedural_envmaps is None:
            return
        if not self.envmaps_dir:
            raise ValueError("--procedural-envmaps adds procedural maps to those of --envmaps DIR; without "
                             "--envmaps every map is procedural (set their number with --num-envmaps)")
        if int(self.procedural_envmaps) < 0:
            raise ValueError(f"--procedural-envmaps must be >= 0, got {self.procedural_envmaps}")

    def _validate_resolution(self) -> None:
        step = RESOLUTION_MULTIPLE
        if self.resolution > MAX_RESOLUTION:
            raise ValueError(f"--resolution {self.resolution}: at most {MAX_RESOLUTION} (the paper's images are 256; a "
                             "larger render takes hours a view)")
        if self.resolution % step == 0:
            return
        near = [n for n in (self.resolution // step * step, (self.resolution // step + 1) * step) if n > 0]
        raise ValueError(f"--resolution {self.resolution}: must be a multiple of {step} (the model's encoder "
                         f"downsamples images by {step}, so training refuses other sizes); e.g. "
                         + " or ".join(map(str, near)))

    def _validate_envs_per_object(self) -> None:
        if self.envs_per_object <= self.num_envmaps:
            return
        if self.envmaps_dir:
            raise ValueError(f"--envs-per-object ({self.envs_per_object}) cannot exceed the number of env maps "
                             f"({self.num_file_envmaps} in {self.envmaps_dir} + {self.procedural_envmaps or 0} "
                             "procedural); add maps, --procedural-envmaps N or lower --envs-per-object")
        raise ValueError(f"--envs-per-object ({self.envs_per_object}) cannot exceed --num-envmaps ({self.num_envmaps})")


def config_dict(cfg: Config) -> dict:
    """The config as the manifest stores it: optional settings only when set."""
    d = asdict(cfg)
    for k in _OPTIONAL:
        if d.get(k) is None or d.get(k) is False:
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


def parse_shard(s: str) -> tuple[int, int]:
    """``"i/n"`` -> (i, n): this run generates the objects whose index % n == i."""
    try:
        i, n = (int(x) for x in str(s).split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n (e.g. 0/4), got {s!r}") from None
    if n <= 0 or not 0 <= i < n:
        raise ValueError(f"--shard {s}: need 0 <= i < n")
    return i, n
