"""The registry of named models: the paper's model as published and its Table E ablations, the single-switch
ablations of each way the default departs from the paper, the variant whose numbers the README cites, and the
diagnostics that read ground truth. Each is a one-line description and the :class:`~pipelines.training.config.TrainConfig`
fields it sets, selected with ``--variant``; ``make train-variants`` trains the runs each lists. An experiment that
lost has left the code: docs/experiments.md keeps its numbers and the commit where it last ran."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Variant:
    """A named model: what it is (one line), the fields it sets, where it is measured."""
    description: str
    fields: dict
    runs: tuple[tuple[str, int], ...] = (("glossy", 0),)  # (dataset, seed) of each run `make train-variants` trains
    kind: str = "ablation"  # published (the paper's model) | paper (Table E) | ablation (one of our choices undone) | diagnostic


# DIB-R++ as the paper describes it, where our renderer and data allow (docs/deviations.md lists what still differs)
PUBLISHED = {"light_head": "global", "texture": "global", "light_colour": "free", "input_range": "clipped",
             "cross_view_light": "view", "lr_schedule": "constant", "image_loss": "clipped", "specular": "learnt"}

VARIANTS: dict[str, Variant] = {
    # make train-published: SG and MC on each set
    "published": Variant("DIB-R++ as published: the light and texture regressed from the global code, light of any "
                         "colour, an 8-bit input, eq. 8's cross-view light, a constant rate, the image loss on clipped "
                         "images, a learnt specular level", PUBLISHED, kind="published", runs=()),
    "k4": Variant("SG light with 4 lobes (Table E)", {"lobes": 4}, kind="paper"),
    "k8": Variant("SG light with 8 lobes (Table E)", {"lobes": 8}, kind="paper"),
    "k16": Variant("SG light with 16 lobes (Table E)", {"lobes": 16}, kind="paper"),
    # one deviation from the paper undone each
    "global-light": Variant("the light regressed from the global code, the paper's head (no light probe)",
                            {"light_head": "global"}, runs=(("glossy", 0), ("metallic", 0))),
    "global-texture": Variant("texture decoded from the global code instead of looked up in the input",
                              {"texture": "global"}),
    "free-light": Variant("light of any colour instead of white-balanced", {"light_colour": "free"}),
    "clipped-input": Variant("the encoder sees the input clipped at 1, as an 8-bit picture shows it (not its EXR)",
                             {"input_range": "clipped"}, runs=(("metallic", 0), ("glossy", 0))),
    "view-light": Variant("cross-view renders under the light read from the view they are in only (eq. 8), not also "
                          "under the prediction's own", {"cross_view_light": "view"},
                          runs=(("metallic", 0), ("glossy", 0), ("glossy", 1), ("glossy", 2))),
    "constant-lr": Variant("the learning rate constant over the whole run, no cosine decay over its last third",
                           {"lr_schedule": "constant"}, runs=(("metallic", 0), ("glossy", 0))),
    # the variant whose numbers the README cites
    "pixel-normals": Variant("in evaluation, the probe's mirror cue read through normals an image-space U-Net "
                             "predicts per pixel, fitted to the GT mesh's before the model trains as the default "
                             "(3D supervision the paper does not use)",
                             {"probe_normals": "pixels"}, runs=(("metallic", 0), ("glossy", 0))),
    # diagnostics: they read ground truth, so they measure a limit, not a model
    "light-supervised-map": Variant("the light supervised by the GT env map (log L1 on the map)",
                                    {"supervision": "light-map"}, kind="diagnostic",
                                    runs=(("glossy", 0), ("metallic", 0))),
    "light-supervised-probe": Variant("the light supervised by the GT map's rough-metal probe (the light metric)",
                                      {"supervision": "light-probe"}, kind="diagnostic",
                                      runs=(("glossy", 0), ("metallic", 0))),
    "albedo-supervised": Variant("the predicted albedo supervised by the GT's in the input view: whether the light "
                                 "takes the sky's colour when the albedo cannot keep it",
                                 {"supervision": "albedo"}, kind="diagnostic", runs=(("metallic", 0),)),
    "roughness-supervised": Variant("the predicted roughness supervised by the car's GT (L1): whether the light takes "
                                    "the sky's colour when a mirror's reflection cannot be blurred",
                                    {"supervision": "roughness"}, kind="diagnostic", runs=(("metallic", 0),)),
}

# the fields some variant sets and the experiments' options no variant names: a run that changes them by hand is
# labelled with them (not the lobes, which the paper's tables set: a budget the tables compare, not a model choice)
EXPERIMENT_FIELDS = tuple(dict.fromkeys([*(k for v in VARIANTS.values() for k in v.fields if k != "lobes"),
                                         "specular"]))
