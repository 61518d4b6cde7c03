"""Runs written before the experiments that lost left the code (model version 8): read as what they were trained
with where that is a model this code has, refused with one line otherwise.

A version-8 run names every option of its day. Where each retired option holds the value the default path had
(or the value an 'auto' resolved to), the run is a model this code trains, and it loads, evaluates and resumes as
before. A run of a retired experiment, or of a version before 8, is refused: the message names the option and the
commit whose code still has it (docs/experiments.md keeps each experiment's numbers).
"""
from __future__ import annotations

from .variants import VARIANTS

LAST_COMMIT = "35af5d2"  # the last commit with every retired experiment's code
EARLIER_VERSION = 8


class RetiredError(ValueError):
    """A run this code cannot read as it was trained: the message says which commit can."""


def _refuse(what: str, commit: str = LAST_COMMIT) -> RetiredError:
    return RetiredError(f"{what}; that experiment has left the code: evaluate or resume it at commit {commit} "
                        f"(git checkout {commit}), or retrain it")


def _probe_sun_fields(light_head: str) -> dict:
    """The sun options a version-8 model had on the default path: the probe sun wherever there is a probe head."""
    if light_head == "probe":
        return {"sun_lobe": ("probe",), "sun_cue": ("facing",), "sun_axis": ("cue-on-metal",)}
    return {}  # the global head has no sun lobe: those options did nothing


# the version-8 model options that are gone, and the value(s) the default path had
RETIRED_MODEL = {"light_scale": ("softplus",), "probe_start": ("luminance",), "probe_samples": ("pixels",),
                 "light_prior": (0,), "shape_detail": ("none",), "sun_min_sharpness": (0.5,)}


def earlier_model_config(d: dict, version: int) -> dict:
    """A checkpoint's model configuration as this code's ``version`` reads it (refused if it cannot be)."""
    if d.get("version") == version:
        return d
    if d.get("version") != EARLIER_VERSION:
        raise ValueError(f"the checkpoint was written by model version {d.get('version')}; this code reads versions "
                         f"{EARLIER_VERSION} and {version}: retrain it (e.g. `make train-glossy`), or check out the "
                         "commit that wrote it")
    retired = {**RETIRED_MODEL, **_probe_sun_fields(d.get("light_head"))}
    for name, kept in retired.items():
        if name in d and d[name] not in kept:
            raise _refuse(f"the checkpoint's model was trained with {name}={d[name]!r}")
    gone = set(RETIRED_MODEL) | {"sun_lobe", "sun_cue", "sun_axis"}
    return {**{k: v for k, v in d.items() if k not in gone}, "version": version}


def earlier_state_dict(state: dict) -> dict:
    """A version-8 model's weights without the buffer only its retired texel probe read."""
    return {k: v for k, v in state.items() if k != "texel_solid_angle"}


# the version-8 training options that are gone, and the value(s) under which the run is this code's model
RETIRED_TRAINING = {"cross_view_only": (False,), "shared_light": (False,), "swap_light": (False,),
                    "w_albedo_consistency": (0, 0.0), "w_albedo_darker": (0, 0.0), "light_lr_scale": (1, 1.0),
                    "flat_albedo_iterations": (0,), "roughness_anneal": (0, 0.0), "spp_start": (0,),
                    "oracle_roughness": (False,), "visibility": ("dibr",), "light_scale": ("softplus",),
                    "probe_start": ("luminance",), "probe_samples": ("pixels",), "light_prior": ("",),
                    "shape_detail": ("none",), "sun_min_sharpness": (0.5, 0)}
DROPPED = ("image_size", "snapshot_every")  # the data's size; how often snapshots were written
SUN_AUTO = {"sun_lobe": "probe", "sun_cue": "facing", "sun_axis": "cue-on-metal"}  # under the probe head


# training options of experiments that left the code later, the model unchanged, by the last commit with their code:
# the value(s) under which the run is the default model
LEFT_LATER = {"84e9556": {"w_albedo_variation": (0, 0.0)}, "de11f3d": {"own_light_material": ("learnt",)},
              "fc03e2f": {"own_light_roughness": ("learnt",)}, "3a0c414": {"w_roughness_prior": (0, 0.0)}}
# choices of a kept option whose experiments left the code later: option -> {choice: the last commit with its code}
CHOICES_LEFT_LATER = {"light_colour": {"sky-prior": "97ea15f", "two-colour": "140a12d"},
                      "texture": {"projected-unlit": "2527105"}, "supervision": {"sun": "f62f542", "shape": "f62f542"},
                      "light_head": {"space": "08b4aeb"}}
# settings of how a run ran, not of what it trains, that left the config for a flag of train: dropped, any value
RUN_SETTINGS_LEFT = ("threads",)
# variants that became the default: their runs are the default model (their fields are the default's values now)
BECAME_DEFAULT = ("sky-ground",)


def _drop_retired(values: dict, retired: dict, commit: str = LAST_COMMIT) -> None:
    """Pop ``retired``'s options from ``values`` where they hold a kept value; refuse the run otherwise."""
    for name, kept in retired.items():
        if name in values and (value := values.pop(name)) not in kept:
            raise _refuse(f"the run was trained with {name}={value!r}", commit)


def without_options_left_later(saved: dict) -> dict:
    """A run's config without the options of experiments that left the code after version 8: dropped where they held
    the default's value (the run is this code's model), refused naming the commit that has them otherwise, as are runs
    of a retired choice (CHOICES_LEFT_LATER)."""
    values = dict(saved)
    for commit, retired in LEFT_LATER.items():
        _drop_retired(values, retired, commit)
    for name, gone in CHOICES_LEFT_LATER.items():
        if (value := values.get(name)) in gone:
            raise _refuse(f"the run was trained with {name}={value!r}", gone[value])
    for name in RUN_SETTINGS_LEFT:
        values.pop(name, None)
    if values.get("variant") in BECAME_DEFAULT:
        values["variant"] = ""
    return values


def is_earlier_config(saved: dict) -> bool:
    return any(k in saved for k in (*RETIRED_TRAINING, *DROPPED, "sun_lobe", "light_supervision"))


def earlier_train_config(saved: dict, trained_light_head: str | None) -> dict:
    """A version-8 run's config.json as this code's TrainConfig fields. ``trained_light_head``: the light head its
    checkpoint's model has (what an 'auto' gave the run), None where no checkpoint can be read."""
    values = dict(saved)
    _drop_retired(values, RETIRED_TRAINING)
    for name in DROPPED:
        values.pop(name, None)
    shading = values.get("shading", "sg")
    head = values.get("light_head", "auto")
    if head == "auto":
        head = trained_light_head or ("global" if shading == "sh" else "probe")
    values["light_head"] = "probe" if shading == "sh" else head  # SH's light is always regressed
    on_probe_sun = head == "probe" and shading != "sh"
    for name, default in SUN_AUTO.items():
        value = values.pop(name, "auto")
        if on_probe_sun and value not in ("auto", default):
            raise _refuse(f"the run was trained with {name}={value!r}")
    if values.get("cross_view_light") == "own":
        raise _refuse("the run was trained with cross_view_light='own'")
    samples = values.pop("mc_loss_samples", "auto")
    if samples != "auto" and (samples == "independent") != (shading == "mc" and on_probe_sun):
        raise _refuse(f"the run was trained with mc_loss_samples={samples!r}")
    light, shape = values.pop("light_supervision", ""), values.pop("shape_supervision", False)
    if light and shape:
        raise _refuse("the run was told both the GT light and the GT normals")
    values["supervision"] = {"map": "light-map", "probe": "light-probe", "sun": "sun"}.get(light, "shape" if shape else "none")
    variant = values.get("variant", "")
    if variant == "probe-light":  # the default model, named
        values["variant"] = ""
    elif variant and variant not in VARIANTS:
        raise _refuse(f"the run is variant {variant!r}")
    return values
