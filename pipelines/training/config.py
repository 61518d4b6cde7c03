"""What a training run is asked to do: :class:`TrainConfig` and its presets (the named variants: :mod:`.variants`).

Every field is settable from the command line (:func:`add_config_arguments` generates the flags from the
dataclass) and from a JSON file; both are checked by name, type and range (:meth:`TrainConfig.from_dict`).
The default path is the model of the docs (docs/training.md); ablations and diagnostics are **named
variants** (:data:`.variants.VARIANTS`): a one-line description and the fields they set, selected with ``--variant``.
The fields a variant sets stay in the config (and in each run's ``config.json``), so a run says what it was.
"""
from __future__ import annotations

import argparse
import difflib
import math
import typing
from dataclasses import MISSING, asdict, dataclass, field, fields

from .variants import EXPERIMENT_FIELDS, VARIANTS


SG_LIGHT = ("sg", "sh-sg")  # the shadings lit by SG lobes


class ConfigError(ValueError):
    """A configuration that cannot be trained: the message names the field and what to do."""


def _opt(default, help: str, choices: tuple | None = None, minimum: float | None = None,  # noqa: A002
         above: float | None = None, maximum: float | None = None):
    """A config field with its CLI help, its allowed values, its lower bound, inclusive (``minimum``) or strict
    (``above``), and its upper bound (``maximum``) (checked by validate)."""
    return field(default=default, metadata=dict(help=help, choices=choices, minimum=minimum, above=above,
                                                maximum=maximum))


@dataclass
class TrainConfig:
    # data and run
    dataset: str = _opt("data/glossy", "dataset folder written by `python -m datagen`; the model sees its resolution")
    out: str = _opt("runs/run", "run folder (config, checkpoint, log, snapshots)")
    seed: int = _opt(0, "seed of the initial weights, the batches and the MC noise", minimum=0)
    variant: str = _opt("", "the named variant this run trains ('' for the default model; see --list-variants)")
    train_objects: int = _opt(0, "train on the training split's first N objects only (their every env map and view): "
                              "learning curves; 0 for all", minimum=0)
    # schedule
    iterations: int = _opt(6000, "training iterations", minimum=1)
    batch_objects: int = _opt(8, "(sample, view pair) items per iteration", minimum=1, maximum=256)
    lr: float = _opt(3e-4, "Adam learning rate", above=0.0)
    lr_schedule: str = _opt("cosine-tail", "the learning rate over the run: constant for two thirds, then a cosine decay "
                            "to zero over the last third (the weights settle instead of jittering at the end), or "
                            "constant throughout", ("cosine-tail", "constant"))
    log_every: int = _opt(10, "iterations between log rows", minimum=1)
    checkpoint_every: int = _opt(100, "iterations between checkpoints and snapshot images", minimum=1)
    # loss
    w_image: float = _opt(1.0, "weight of the image L1 (eq. 8)", minimum=0.0)
    w_iou: float = _opt(1.0, "weight of the soft-silhouette IoU loss", minimum=0.0)
    w_laplacian: float = _opt(0.02, "weight of the Laplacian smoothness of the shape", minimum=0.0)
    w_gradient: float = _opt(0.5, "weight of the multi-scale image-gradient L1 (the stand-in for VGG)", minimum=0.0)
    image_loss: str = _opt("hdr-srgb", "the space the image losses compare in: the sRGB curve continued above 1 "
                           "(highlights keep their gradient), or sRGB clipped at 1 (an 8-bit picture's, the paper's)",
                           ("hdr-srgb", "clipped"))
    # model
    shading: str = _opt("sg", "shading method: the paper's MC and SG, DIB-R's SH, SH shading with SG light",
                        ("mc", "sg", "sh", "sh-sg"))
    lobes: int = _opt(32, "SG lobes of the predicted light", minimum=2)
    spp: int = _opt(8, "MC samples per pixel during training", minimum=1)
    predict_metallic: bool | None = _opt(None, "predict the metallic parameter (unset: where the dataset has metals)")
    specular: str = _opt("fixed", "a dielectric's specular level: fixed at Specular IOR Level 0.5 (F0 0.04, IOR 1.5: "
                         "the metallic-roughness convention; not the data's value), or learnt from the image",
                         ("fixed", "learnt"))
    texture: str = _opt("projected", "albedo looked up from the input view, or decoded from the global code",
                        ("projected", "global"))
    light_colour: str = _opt("sky-ground", "white-balanced light whose sky (the probe head's) is tinted by a colour above "
                             "the horizon and one below, white-balanced light alone, or light of any colour",
                             ("sky-ground", "white", "free"))
    light_head: str = _opt("probe", "light read from the input through the predicted geometry (probe: the object as a "
                           "light probe) or regressed from the global code (global, the paper's); SH light is always "
                           "regressed", ("probe", "global"))
    input_range: str = _opt("full", "what the encoder sees of an image: its full range (the dataset's EXR, sun "
                            "reflections included) or clipped at 1 (as an 8-bit picture shows it)", ("full", "clipped"))
    cross_view_light: str = _opt("both", "the light of a prediction's render in the other view of its pair: the light "
                                 "predicted from that view (eq. 8), or both that and its own (a render under each: one "
                                 "world light has to explain both views)", ("both", "view"))
    probe_normals: str = _opt("surface", "the normals the probe head's mirror cue reads: the predicted surface's, or "
                              "in evaluation an image-space network's fitted to the GT mesh's in each training view "
                              "(pixels: 3D supervision the paper does not use; training reads the surface's)",
                              ("surface", "pixels"))
    supervision: str = _opt("none", "diagnostic: ground truth the run is told: the GT env map (light-map), its rough-metal "
                            "probe (light-probe), the GT albedo in the input view (albedo), or the object's GT "
                            "roughness (roughness)", ("none", "light-map", "light-probe", "albedo", "roughness"))
    # device
    device: str = _opt("cpu", "where the model, the batches and the renders live (cuda: the first GPU; one process)",
                       ("cpu", "cuda"))
    compile: bool = _opt(True, "G-buffer and shading through torch.compile (eager where it cannot)")

    def validate(self) -> "TrainConfig":
        """Refuse wrong types, unknown choices and out-of-range values, naming the field."""
        hints = typing.get_type_hints(TrainConfig)
        for f in fields(self):
            value, kind = getattr(self, f.name), hints[f.name]
            if value is None and f.default is None:
                continue  # unset: decided by the data (predict_metallic)
            kind = typing.get_args(kind)[0] if typing.get_args(kind) else kind
            ok = isinstance(value, kind) and not (kind in (int, float) and isinstance(value, bool))
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                ok = True
            if not ok:
                raise ConfigError(f"{f.name} must be {kind.__name__}, got {value!r}")
            if kind is float and not math.isfinite(value):
                raise ConfigError(f"{f.name} must be a finite number, got {value!r}")
            choices, minimum, above, maximum = (f.metadata.get(k) for k in ("choices", "minimum", "above", "maximum"))
            if choices is not None and value not in choices:
                raise ConfigError(f"{f.name} must be one of {', '.join(map(repr, choices))}; got {value!r}")
            if minimum is not None and value < minimum:
                raise ConfigError(f"{f.name} must be >= {minimum}, got {value!r}")
            if above is not None and value <= above:
                raise ConfigError(f"{f.name} must be > {above:g}, got {value!r}")
            if maximum is not None and value > maximum:
                raise ConfigError(f"{f.name} must be <= {maximum:g} (more does not fit in memory), got {value!r}")
        if not any((self.w_image, self.w_iou, self.w_gradient)) and self.supervision in ("none", "albedo", "roughness"):
            raise ConfigError("every image and silhouette loss weight is 0 (w_image, w_iou, w_gradient): nothing would "
                              "train the model; give at least one a positive weight")
        if self.probe_normals == "pixels" and not self.has_probe_head():
            raise ConfigError("probe_normals 'pixels' gives the probe head's pixels their normals; use it with the probe "
                              "light head (--light-head probe) and --shading sg, sh-sg or mc")
        if self.variant and self.variant not in VARIANTS:
            raise ConfigError(f"unknown variant {self.variant!r}; {_did_you_mean(self.variant, VARIANTS)}")
        return self

    def has_probe_head(self) -> bool:
        """Whether the light is read through the predicted geometry (SH light is always regressed)."""
        return self.light_head == "probe" and self.shading != "sh"

    def model_light_head(self) -> str:
        return "probe" if self.has_probe_head() else "global"

    def independent_mc_samples(self) -> bool:
        """Whether MC's image losses take each pixel's sign and derivative from renders with independent samples:
        under the probe head's sun, whose sky MC shades (with one render the loss pays for the render's own noise,
        which training lowers by blurring the light)."""
        return self.shading == "mc" and self.has_probe_head()

    @classmethod
    def from_dict(cls, values: dict, preset: str = "cpu") -> "TrainConfig":
        """The preset's config with ``values`` applied (a config file's JSON, CLI flags), checked by name, type
        and range. A ``variant`` in ``values`` applies the variant's fields first, then the explicit ones."""
        if not isinstance(values, dict):
            raise ConfigError(f"a config must be a JSON object of TrainConfig fields, got {type(values).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ConfigError(f"unknown config field {unknown[0]!r}; {_did_you_mean(unknown[0], names)}")
        if preset not in PRESETS:
            raise ConfigError(f"unknown preset {preset!r}; choose from {', '.join(sorted(PRESETS))}")
        variant = values.get("variant", "")
        if variant and variant not in VARIANTS:
            raise ConfigError(f"unknown variant {variant!r}; {_did_you_mean(variant, VARIANTS)}")
        chosen = {**PRESETS[preset], **(VARIANTS[variant].fields if variant else {}), **values}
        return cls(**chosen).validate()

    @classmethod
    def preset(cls, name: str, **overrides) -> "TrainConfig":
        return cls.from_dict(overrides, preset=name)

    def to_dict(self) -> dict:
        return asdict(self)

    def label(self) -> str:
        """'' for the default model, else the variant's name (or, for a run configured by hand, its
        non-default experiment fields, e.g. 'light_colour=free'). Tables hold default models only."""
        if self.variant:
            return self.variant
        mine, default = self.to_dict(), TrainConfig().to_dict()
        if self.shading == "sh":  # SH light is always regressed and SH shading is Lambertian: no choice in either
            mine["light_head"], mine["specular"] = default["light_head"], default["specular"]
        return ", ".join(f"{k}={mine[k]}" for k in EXPERIMENT_FIELDS if mine[k] != default[k])


PRESETS = {
    "cpu": {},  # 64x64, 6000 iterations: an SG run trains on 2 cores in ~22-45 min
    "smoke": dict(iterations=12, batch_objects=2, log_every=2, checkpoint_every=4, spp=2),
    # the paper's batch, samples and length; its 256 x 256 images are the dataset's (datagen --preset paper)
    "paper": dict(iterations=200_000, batch_objects=16, spp=64, checkpoint_every=1000, log_every=50),
}


def _did_you_mean(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=1)
    return f"did you mean {close[0]!r}?" if close else f"known: {', '.join(sorted(known))}"


def _cli_type(kind):
    """An argparse type that names the expected kind in its error."""
    def parse(text: str):
        try:
            return kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
    parse.__name__ = kind.__name__
    return parse


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """One flag per TrainConfig field (``--batch-objects``), with its type, choices and default in the help.
    Unset flags stay None, so that a preset, a variant and a config file apply underneath them."""
    hints = typing.get_type_hints(TrainConfig)
    group = parser.add_argument_group("training configuration (every TrainConfig field)")
    for f in fields(TrainConfig):
        kind, meta = hints[f.name], f.metadata
        kind = typing.get_args(kind)[0] if typing.get_args(kind) else kind
        default = f.default if f.default is not MISSING else None
        help_text = meta["help"] if default is None else f"{meta['help']} (default: {default!r})"
        flag = "--" + f.name.replace("_", "-")
        if f.name == "variant":
            group.add_argument(flag, default=None, metavar="NAME", help=help_text)
        elif kind is bool:
            group.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        else:
            group.add_argument(flag, type=_cli_type(kind), choices=meta.get("choices"), default=None,
                               metavar=None if meta.get("choices") else kind.__name__.upper(), help=help_text)


def config_overrides(args: argparse.Namespace) -> dict:
    """The TrainConfig fields set on the command line."""
    return {f.name: getattr(args, f.name) for f in fields(TrainConfig) if getattr(args, f.name, None) is not None}


def describe_variants() -> str:
    width = max(map(len, VARIANTS))
    return "\n".join(f"{name:<{width}}  {v.kind:<10}  {v.description}" for name, v in VARIANTS.items())


def variant_runs(kinds: list[str]) -> str:
    """'dataset variant seed' lines of every run of the variants of ``kinds`` (for make's loops)."""
    unknown = set(kinds) - {v.kind for v in VARIANTS.values()}
    if unknown:
        raise ConfigError(f"unknown variant kind {sorted(unknown)[0]!r}; choose from ablation, diagnostic, paper, "
                          "published")
    return "\n".join(f"{d} {name} {s}" for name, v in VARIANTS.items() if v.kind in kinds for d, s in v.runs)
