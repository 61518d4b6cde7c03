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
SPP_START_FRACTION = 0.2  # the part of a run that spp_start covers


class ConfigError(ValueError):
    """A configuration that cannot be trained: the message names the field and what to do."""


def _opt(default, help: str, choices: tuple | None = None, minimum: float | None = None,  # noqa: A002
         above: float | None = None):
    """A config field with its CLI help, its allowed values or its lower bound, inclusive (``minimum``) or
    strict (``above``) (checked by from_dict)."""
    return field(default=default, metadata=dict(help=help, choices=choices, minimum=minimum, above=above))


@dataclass
class TrainConfig:
    dataset: str = _opt("data/glossy", "dataset folder written by `python -m datagen`")
    out: str = _opt("runs/run", "run folder (config, checkpoint, log, snapshots)")
    shading: str = _opt("sg", "shading method: the paper's MC and SG, DIB-R's SH, SH shading with SG light",
                        ("mc", "sg", "sh", "sh-sg"))
    lobes: int = _opt(32, "SG lobes of the predicted light", minimum=1)
    seed: int = _opt(0, "seed of the initial weights, the batches and the MC noise", minimum=0)
    iterations: int = _opt(1500, "training iterations", minimum=1)
    train_objects: int = _opt(0, "train on the training split's first N objects only (their every env map and view): "
                              "learning curves; 0 for all", minimum=0)
    batch_objects: int = _opt(8, "(sample, view pair) items per iteration", minimum=1)
    lr: float = _opt(3e-4, "Adam learning rate", above=0.0)
    lr_schedule: str = _opt("cosine-tail", "the learning rate over the run: constant for two thirds, then a cosine decay "
                            "to zero over the last third (the weights settle instead of jittering at the end), or "
                            "constant throughout", ("cosine-tail", "constant"))
    spp: int = _opt(8, "MC samples per pixel during training", minimum=1)
    mc_loss_samples: str = _opt("auto", "MC's image losses: their gradient from the render they score (shared), or "
                                "each pixel's sign from one render and the derivative from a second with other samples "
                                "(independent): with shared samples the expected loss holds the render's noise, which "
                                "training lowers by blurring the light. auto: independent under MC's probe sun, else "
                                "shared", ("auto", "shared", "independent"))
    spp_start: int = _opt(0, "MC samples per pixel over the run's first fifth, then --spp (0: --spp throughout)",
                          minimum=0)
    image_size: int = _opt(64, "image side the model sees (a multiple of 16; the dataset's resolution)", minimum=16)
    w_image: float = _opt(1.0, "weight of the image L1 (eq. 8)", minimum=0.0)
    w_iou: float = _opt(1.0, "weight of the soft-silhouette IoU loss", minimum=0.0)
    w_laplacian: float = _opt(0.02, "weight of the Laplacian smoothness of the shape", minimum=0.0)
    w_gradient: float = _opt(0.5, "weight of the multi-scale image-gradient L1", minimum=0.0)
    log_every: int = _opt(10, "iterations between log rows", minimum=1)
    snapshot_every: int = _opt(250, "iterations between snapshot images", minimum=1)
    checkpoint_every: int = _opt(100, "iterations between checkpoints", minimum=1)
    predict_metallic: bool = _opt(False, "predict the metallic parameter (default: where the data has metals)")
    texture: str = _opt("projected", "albedo looked up from the input view, or decoded from the global code",
                        ("projected", "global"))
    light_colour: str = _opt("white", "white-balanced light, or light of any colour", ("white", "free"))
    light_scale: str = _opt("softplus", "light sharpness and intensity linear or exponential in the head's output",
                            ("softplus", "log"))
    light_head: str = _opt("auto", "light read from the input through the predicted geometry (probe; the object as a "
                           "light probe) or regressed from the global code (global, the paper's); auto: probe for "
                           "SG light (sg, sh-sg) and mc, global for sh", ("auto", "probe", "global"))
    probe_start: str = _opt("luminance", "the probe head's first light: the mirror cue's luminance or its colour",
                            ("luminance", "colour"))
    probe_samples: str = _opt("pixels", "where the probe head reads the input: the pixels the predicted surface "
                              "covers (rasterised) or its texels' projections", ("pixels", "texels"))
    light_prior: str = _opt("", "folder of env maps whose log-luminance PCA the probe head's SG sky lives in "
                            "(pipelines.light_prior; `make light-prior`); '' for none")
    input_range: str = _opt("full", "what the encoder sees of an image: its full range (the dataset's EXR, sun "
                            "reflections included) or clipped at 1 (as an 8-bit picture shows it)", ("full", "clipped"))
    sun_lobe: str = _opt("auto", "the probe head's SG sun: its power learned (the image loss may switch it off), or "
                         "with its axis above the horizon and, on metal, at least what the mirror cue shows near its "
                         "axis above the sky's level, what the cue adds not bending the surface it was read through "
                         "(probe; with --shading mc the same SG sky and sun, no floor, on the env grid, the sun "
                         "trained in closed form; learned: MC's light is the refined cue's grid); auto: probe "
                         "wherever there is a probe head",
                         ("auto", "learned", "probe"))
    sun_min_sharpness: float = _opt(0.5, "the least sharpness of the probe head's sun lobe (0.5: as broad as a "
                                    "hemisphere; higher keeps it a sun, not a glow over half the sky)", minimum=0.5)
    sun_cue: str = _opt("auto", "the pixels the probe head's SG sun is read off: all that the predicted surface "
                        "covers, or those facing the camera (n.v >= 0.3; grazing pixels at the silhouette mirror the "
                        "direction straight behind the object); auto: facing wherever there is a probe sun",
                        ("auto", "all", "facing"))
    sun_axis: str = _opt("auto", "where the probe head's SG sun points: the mirror cue's brightest region shifted by "
                         "a learnt residual (head), the cue's alone (cue: the sun's place is the geometry's), or the "
                         "shift scaled by 1 - the predicted metallic (cue-on-metal: a metal's cue is the light's "
                         "picture, paint adds its diffuse shading); auto: cue-on-metal wherever there is a probe sun",
                         ("auto", "head", "cue", "cue-on-metal"))
    shape_detail: str = _opt("none", "each vertex of the global shape displaced along its normal by what pixel-aligned "
                             "image features show where it projects (features), or the global shape alone (none)",
                             ("none", "features"))
    probe_normals: str = _opt("surface", "the normals the probe head's mirror cue reads: the predicted surface's, or "
                              "in evaluation an image-space network's fitted to the GT mesh's in each training view "
                              "(pixels: 3D supervision the paper does not use; training reads the surface's)",
                              ("surface", "pixels"))
    cross_view_only: bool = _opt(False, "image losses on renders in the other view only, not the input view")
    shared_light: bool = _opt(False, "cross-view renders lit by another object's light under the same env map")
    cross_view_light: str = _opt("both", "the light of a prediction's render in the other view of its pair: the light "
                                 "predicted from that view (eq. 8), its own (one world light for both views), or both "
                                 "(a render under each)", ("both", "view", "own"))
    swap_light: bool = _opt(False, "cross-view renders of the same object under its other env map, with its light")
    shape_supervision: bool = _opt(False, "diagnostic: the predicted normals supervised by the GT mesh's in the "
                                   "input view (1 - cos, weight 1)")
    oracle_roughness: bool = _opt(False, "diagnostic: render with each object's GT roughness")
    light_supervision: str = _opt("", "diagnostic: light supervised by the GT map (on the map, on the probe, or the "
                                  "probe head's sun on the map's dominant direction)", ("", "map", "probe", "sun"))
    w_albedo_consistency: float = _opt(0.0, "L1 between the albedos predicted from an object's two views",
                                       minimum=0.0)
    w_albedo_darker: float = _opt(0.0, "albedo pulled down to the darker of an object's two views", minimum=0.0)
    light_lr_scale: float = _opt(1.0, "the light head's learning rate as a multiple of --lr", minimum=0.0)
    flat_albedo_iterations: int = _opt(0, "curriculum: renders use the mean albedo for this many iterations",
                                       minimum=0)
    roughness_anneal: float = _opt(0.0, "curriculum: the renders' roughness at least this at the start, lowered "
                                   "linearly to none by two thirds of the run (blurred reflections first: a smoother "
                                   "loss in the normals)", minimum=0.0)
    visibility: str = _opt("dibr", "silhouette gradient: soft silhouette, or antialiased edges (Sec. F.1)",
                           ("dibr", "edge_aa"))
    threads: int = _opt(0, "torch threads per process (0: torch's default)", minimum=0)
    device: str = _opt("cpu", "where the model, the batches and the renders live (cuda: the first GPU; one process)",
                       ("cpu", "cuda"))
    compile: bool = _opt(True, "G-buffer and shading through torch.compile (eager where it cannot)")
    variant: str = _opt("", "the named variant this run trains ('' for the default model; see --list-variants)")

    def validate(self) -> "TrainConfig":
        """Refuse wrong types, unknown choices and out-of-range values, naming the field."""
        hints = typing.get_type_hints(TrainConfig)
        for f in fields(self):
            value, kind = getattr(self, f.name), hints[f.name]
            ok = isinstance(value, kind) and not (kind in (int, float) and isinstance(value, bool))
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                ok = True
            if not ok:
                raise ConfigError(f"{f.name} must be {kind.__name__}, got {value!r}")
            if kind is float and not math.isfinite(value):
                raise ConfigError(f"{f.name} must be a finite number, got {value!r}")
            choices, minimum, above = (f.metadata.get(k) for k in ("choices", "minimum", "above"))
            if choices is not None and value not in choices:
                raise ConfigError(f"{f.name} must be one of {', '.join(map(repr, choices))}; got {value!r}")
            if minimum is not None and value < minimum:
                raise ConfigError(f"{f.name} must be >= {minimum}, got {value!r}")
            if above is not None and value <= above:
                raise ConfigError(f"{f.name} must be > {above:g}, got {value!r}")
        if self.image_size % 16:
            raise ConfigError(f"image_size must be a multiple of 16, got {self.image_size}")
        if self.shared_light and self.swap_light:
            raise ConfigError("shared_light and swap_light pair the batch differently; choose one")
        if self.cross_view_light != "view" and (self.shared_light or self.swap_light):
            raise ConfigError(f"cross_view_light {self.cross_view_light!r} lights cross-view renders with the "
                              "prediction's own light; shared_light and swap_light with another's: choose one")
        if self.shading == "sh" and self.light_head == "probe":
            raise ConfigError("light_head 'probe' predicts SG lobes or env maps, not SH; use --light-head global "
                              "(or auto) with --shading sh")
        if self.light_prior and (self.shading not in SG_LIGHT or self.resolved_light_head() != "probe"):
            raise ConfigError("light_prior shapes the probe head's SG sky; use it with --shading sg or sh-sg and the "
                              "probe light head")
        if self.sun_lobe == "probe" and (self.shading == "sh" or self.resolved_light_head() != "probe"):
            raise ConfigError("sun_lobe 'probe' reads the probe head's sun off the mirror cue; use it with --shading "
                              "sg, sh-sg or mc and the probe light head")
        # (SH with the probe head is refused above, so without a probe head there is no sun lobe; MC's has one only
        # with its probe sun)
        if self.sun_min_sharpness != TrainConfig.sun_min_sharpness and (self.resolved_light_head() != "probe" or (
                self.shading == "mc" and self.resolved_sun_lobe() != "probe")):
            raise ConfigError("sun_min_sharpness bounds the probe head's sun lobe; use it with the probe light head and "
                              "--shading sg or sh-sg, or mc with its probe sun (--sun-lobe probe or auto)")
        # the choices that read the probe sun's cue
        for name, value in (("sun_cue", "facing"), ("sun_axis", "cue"), ("sun_axis", "cue-on-metal")):
            if getattr(self, name) == value and self.resolved_sun_lobe() != "probe":
                raise ConfigError(f"{name} '{value}' reads the probe head's sun off the mirror cue; use it with the "
                                  "probe sun (--sun-lobe probe or auto, with the probe light head)")
        if self.probe_normals == "pixels" and (self.resolved_light_head() != "probe" or self.probe_samples != "pixels"):
            raise ConfigError("probe_normals 'pixels' gives the probe head's pixels their normals; use it with the probe "
                              "light head and --probe-samples pixels")
        if self.light_supervision == "sun" and (self.shading not in SG_LIGHT or self.resolved_light_head() != "probe"):
            raise ConfigError("light_supervision 'sun' teaches the probe head's SG sun lobe; use it with --shading sg "
                              "or sh-sg and the probe light head")
        if self.mc_loss_samples == "independent" and not self._has_mc_probe_sun():
            raise ConfigError("mc_loss_samples 'independent' shades MC's sky twice under its probe sun; use it with "
                              "--shading mc and the probe sun (--sun-lobe probe or auto, with the probe light head)")
        if self.spp_start and self.shading != "mc":
            raise ConfigError("spp_start sets MC's samples per pixel at the start of training; use it with --shading mc")
        if self.variant and self.variant not in VARIANTS:
            raise ConfigError(f"unknown variant {self.variant!r}; {_did_you_mean(self.variant, VARIANTS)}")
        return self

    def reads_gt_normals(self) -> bool:
        """Whether training reads the GT mesh's normals in every view (a diagnostic's loss, or the pixel normals' fit)."""
        return self.shape_supervision or self.probe_normals == "pixels"

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

    def training_spp(self, iteration: int) -> int:
        """MC's samples per pixel at ``iteration``: ``spp_start`` over the run's first fifth (where the light forms:
        a run at 32 shows its suns by iteration 250, one at 8 a glow), ``spp`` after it."""
        early = self.spp_start and iteration < self.iterations * SPP_START_FRACTION
        return self.spp_start if early else self.spp

    def resolved_light_head(self) -> str:
        """The light head the model gets. 'auto': the probe head where it was measured to light the probes and place
        the light better (SG lobes: sg, sh-sg; MC's env map since 2026-11-25), the paper's global head for the SH
        baseline. (An MC run written before then says 'auto' for the global head: runs.load_config reads it so.)"""
        if self.light_head != "auto":
            return self.light_head
        return "global" if self.shading == "sh" else "probe"

    def resolved_sun_lobe(self) -> str:
        """The probe head's sun. 'auto': read off the mirror cue (probe) wherever there is a probe head (for SG light
        the default since 2026-11-26: on metal it places the sun better, on paint it is the learned sun above the
        horizon; for MC since 2026-11-27, its sun trained in closed form: the sun better placed on both sets),
        else learned (the global head and SH have no such lobe). (An MC run written between those dates says 'auto'
        for the learned sun: runs.load_config reads it so.)"""
        if self.sun_lobe != "auto":
            return self.sun_lobe
        return "probe" if self.resolved_light_head() == "probe" else "learned"

    def resolved_sun_cue(self) -> str:
        """The pixels the probe sun is read off. 'auto': those facing the camera wherever there is a probe sun (the
        default since 2026-11-26, late: grazing pixels at the silhouette put the metallic sun behind the object on
        some seeds), else all (no probe sun reads a cue)."""
        if self.sun_cue != "auto":
            return self.sun_cue
        return "facing" if self.resolved_sun_lobe() == "probe" else "all"

    def resolved_sun_axis(self) -> str:
        """Where the probe sun points. 'auto': the learnt shift on paint only (cue-on-metal) wherever there is a probe
        sun (the default since 2026-11-26, seventh session: on metal the shift put the sun ~10 degrees too low; on
        paint, and so on every set without metals, it is the shift as before, bit for bit), else head (unused)."""
        if self.sun_axis != "auto":
            return self.sun_axis
        return "cue-on-metal" if self.resolved_sun_lobe() == "probe" else "head"

    def _has_mc_probe_sun(self) -> bool:
        return self.shading == "mc" and self.resolved_sun_lobe() == "probe"

    def resolved_mc_loss_samples(self) -> str:
        """Where MC's image losses take their gradient. 'auto': from a second render with independent samples under
        MC's probe sun (the default since 2026-11-27, thirteenth session: at 8 samples per pixel the shared samples'
        loss blurred the glossy sun into a glow), else from the render they score (nothing else has a second)."""
        if self.mc_loss_samples != "auto":
            return self.mc_loss_samples
        return "independent" if self._has_mc_probe_sun() else "shared"

    def label(self) -> str:
        """'' for the default model, else the variant's name (or, for a run configured by hand, its
        non-default experiment fields, e.g. 'light_colour=free'). Tables hold default models only."""
        if self.variant:
            return self.variant
        mine, default = self.resolved_dict(), TrainConfig(shading=self.shading).resolved_dict()  # "auto" by shading
        return ", ".join(f"{k}={mine[k]}" for k in EXPERIMENT_FIELDS if mine[k] != default[k])

    def resolved_dict(self) -> dict:
        """The fields with 'auto' choices resolved: what the run trains, whichever way it was written."""
        return {**self.to_dict(), "light_head": self.resolved_light_head(), "sun_lobe": self.resolved_sun_lobe(),
                "sun_cue": self.resolved_sun_cue(), "sun_axis": self.resolved_sun_axis(),
                "mc_loss_samples": self.resolved_mc_loss_samples()}


# What a run whose config.json was written before a field existed was trained with (the field's value then, not
# today's default), so that an old run reads, is labelled and is resumed as what it was.
VALUES_BEFORE_FIELD = {"light_head": "global", "probe_start": "colour", "probe_samples": "texels",
                       "input_range": "clipped", "cross_view_light": "view", "lr_schedule": "constant",
                       "sun_lobe": "learned", "sun_cue": "all", "sun_axis": "head", "mc_loss_samples": "shared"}

PRESETS = {
    "cpu": {},  # 64x64, 1500 iterations: a run of each method finishes on 2 cores in ~6-11 min
    "smoke": dict(iterations=12, batch_objects=2, log_every=2, snapshot_every=6, checkpoint_every=4, spp=2),
    "paper": dict(iterations=200_000, image_size=256, batch_objects=16, spp=64, snapshot_every=2000,
                  checkpoint_every=1000, log_every=50),
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
        default = f.default if f.default is not MISSING else None
        help_text = f"{meta['help']} (default: {default!r})"
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
        raise ConfigError(f"unknown variant kind {sorted(unknown)[0]!r}; choose from ablation, diagnostic, paper")
    return "\n".join(f"{d} {name} {s}" for name, v in VARIANTS.items() if v.kind in kinds for d, s in v.runs)
