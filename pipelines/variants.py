"""The registry of named experiments: each variant of the model (an ablation, a diagnostic that reads the GT, or one
of the paper's Tables D/E) is a one-line description and the :class:`~pipelines.config.TrainConfig` fields it sets,
selected with ``--variant``; ``make train-variants`` trains the runs each lists. A variant that wins becomes the
default; one that loses stays documented in docs/experiments.md."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Variant:
    """A named experiment: what it tests (one line), the fields it sets, where it is measured."""
    description: str
    fields: dict
    runs: tuple[tuple[str, int], ...] = (("glossy", 0),)  # (dataset, seed) of each run `make train-variants` trains
    kind: str = "ablation"  # ablation (a model choice) | diagnostic (uses GT; not a model) | paper (Tables D/E)


VARIANTS: dict[str, Variant] = {
    # the paper's ablations (Tables D and E)
    "k4": Variant("SG light with 4 lobes (Table E)", {"lobes": 4}, kind="paper"),
    "k8": Variant("SG light with 8 lobes (Table E)", {"lobes": 8}, kind="paper"),
    "k16": Variant("SG light with 16 lobes (Table E)", {"lobes": 16}, kind="paper"),
    # ablations of our model's choices
    "free-light": Variant("light of any colour instead of white-balanced", {"light_colour": "free"}),
    "global-texture": Variant("texture decoded from the global code instead of looked up in the input",
                              {"texture": "global"}),
    "edge-aa": Variant("nvdiffrast-style edge antialiasing instead of DIB-R's soft silhouette (Sec. F.1)",
                       {"visibility": "edge_aa"}),
    "log-light": Variant("light scales exponential in the head's output", {"light_scale": "log"}),
    "shared-light": Variant("cross-view renders lit by another object's light under the same map (log scales)",
                            {"light_scale": "log", "shared_light": True, "cross_view_light": "view"}),
    "cross-view": Variant("image losses only on renders in the other view of each pair", {"cross_view_only": True}),
    "albedo-consistency": Variant("L1 between the albedos of an object's two views, weight 1",
                                  {"w_albedo_consistency": 1.0}),
    "albedo-consistency-0.1": Variant("L1 between the albedos of an object's two views, weight 0.1",
                                      {"w_albedo_consistency": 0.1}),
    "albedo-darker": Variant("albedo pulled down to the darker of an object's two views, weight 1",
                             {"w_albedo_darker": 1.0}),
    "albedo-darker-0.1": Variant("albedo pulled down to the darker of an object's two views, weight 0.1",
                                 {"w_albedo_darker": 0.1}),
    "log-light-lr10": Variant("exponential light scales, light head at 10x the learning rate",
                              {"light_scale": "log", "light_lr_scale": 10.0}),
    "flat-albedo": Variant("curriculum: every render uses its mean albedo for 500 iterations, then detail fades in",
                           {"flat_albedo_iterations": 500}),
    "flat-albedo-1500": Variant("the flat-albedo curriculum over the whole run", {"flat_albedo_iterations": 1500},
                                kind="diagnostic"),
    "swap-light": Variant("cross-view renders of the same object under its other env map, lit by its light",
                          {"swap_light": True, "cross_view_light": "view"},
                          runs=(("glossy", 0), ("glossy", 1), ("metallic", 0))),
    "swap-light-log-lr10": Variant("swap-light with exponential light scales at 10x the learning rate",
                                   {"swap_light": True, "light_scale": "log", "light_lr_scale": 10.0,
                                    "cross_view_light": "view"}),
    "global-light": Variant("the paper's light head: the light regressed from the global code (no light probe; MC's "
                            "default until 2026-11-25)",
                            {"light_head": "global"}, runs=(("glossy", 0), ("metallic", 0))),
    "probe-light": Variant("the light read from the input through the predicted geometry, named explicitly (what "
                           "'auto' gives SG light and, since 2026-11-25, MC)",
                           {"light_head": "probe"}, runs=()),
    "probe-light-colour": Variant("the probe head starting from the mirror cue's colour instead of its luminance",
                                  {"light_head": "probe", "probe_start": "colour"}, runs=(("glossy", 0), ("metallic", 0))),
    "probe-texels": Variant("the probe head reading the input at the predicted surface's texels, not its pixels",
                            {"light_head": "probe", "probe_samples": "texels"}, runs=(("metallic", 0),)),
    "light-prior": Variant("the probe head's SG sky in a prior learned from 2000 procedural env maps (log-PCA, 16)",
                           {"light_prior": "data/light-prior"}, runs=(("metallic", 0), ("glossy", 0))),
    "laplacian-0.005": Variant("the shape's Laplacian smoothness weight at a quarter (0.005): sharper breaks for the normals",
                               {"w_laplacian": 0.005}, runs=(("metallic", 0), ("glossy", 0))),
    "clipped-input": Variant("the encoder sees the input clipped at 1, as an 8-bit picture shows it (not its EXR)",
                             {"input_range": "clipped"}, runs=(("metallic", 0), ("glossy", 0))),
    "own-light": Variant("each prediction rendered in both views under its own light: one world light for both views",
                         {"cross_view_light": "own"}, runs=(("metallic", 0), ("glossy", 0))),
    "view-light": Variant("cross-view renders under the light read from the view they are in only (eq. 8; the default "
                          "until 2026-11-25), not also under the prediction's own",
                          {"cross_view_light": "view"},
                          runs=(("metallic", 0), ("glossy", 0), ("glossy", 1), ("glossy", 2))),
    "constant-lr": Variant("the learning rate constant over the whole run, no cosine decay over its last third (the "
                           "default until 2026-11-25)", {"lr_schedule": "constant"}, runs=(("metallic", 0), ("glossy", 0))),
    "learned-sun": Variant("the probe head's sun lobe learned like the sky's (the image loss may switch it off, no "
                           "horizon; SG's default until 2026-11-26; MC's light then a free grid, its default until "
                           "2026-11-27)", {"sun_lobe": "learned"},
                           runs=(("metallic", 0), ("metallic", 1), ("metallic", 2), ("glossy", 0), ("glossy", 1),
                                 ("glossy", 2))),
    "sharp-sun": Variant("the probe head's sun lobe at least sharpness 20 (half its peak 15 degrees off its axis): MC's "
                         "closed-form sun had become a glow over half the sky (sharpness ~1, 80 % of the power; "
                         "shared samples, as measured)",
                         {"sun_min_sharpness": 20.0, "mc_loss_samples": "shared"}, runs=()),
    "spp32": Variant("MC trained at 32 samples per pixel instead of 8, whose loss pays less for its render's noise "
                     "(entry 31; shared samples, as measured)", {"spp": 32, "mc_loss_samples": "shared"}, runs=()),
    "spp32-start": Variant("MC trained at 32 samples per pixel over the run's first fifth, 8 after it (the suns it forms "
                           "fade into a glow by iteration 750: the start is not what 8 samples change; shared samples, "
                           "as measured)", {"spp_start": 32, "mc_loss_samples": "shared"}, runs=()),
    "shared-samples": Variant("MC's image losses with each pixel's sign and derivative from the render they score, whose "
                              "expected loss holds its own noise, which training lowers by blurring the light into a "
                              "glow (MC's default until 2026-11-27, thirteenth session)",
                              {"mc_loss_samples": "shared"}, runs=()),
    "all-pixels-sun": Variant("the SG sun read off every pixel the surface covers, grazing ones at the silhouette "
                              "included (which mirror the direction behind the object; the default until 2026-11-26, "
                              "late)", {"sun_cue": "all"},
                              runs=(("metallic", 0), ("metallic", 1), ("metallic", 2), ("glossy", 0), ("glossy", 1),
                                    ("glossy", 2))),
    "cue-sun-axis": Variant("the SG sun's axis the mirror cue's soft arg-max alone, no learnt shift: the learnt shift "
                            "put the metallic sun ~10 degrees too low", {"sun_axis": "cue"},
                            runs=(("metallic", 0), ("metallic", 1), ("glossy", 0))),
    "shifted-sun-axis": Variant("the SG sun's axis shifted by the head's learnt residual on metal too (the default "
                                "until 2026-11-26, seventh session; on glossy, which predicts no metallic, the default "
                                "bit for bit)", {"sun_axis": "head"},
                                runs=(("metallic", 0), ("metallic", 1), ("metallic", 2))),
    "roughness-anneal": Variant("the renders' roughness at least 0.7 at the start, lowered to none by two thirds of "
                                "the run: blurred reflections before sharp ones, for the normals",
                                {"roughness_anneal": 0.7}, runs=(("metallic", 0), ("glossy", 0))),
    "vertex-features": Variant("each vertex displaced along its normal by pixel-aligned image features (a U-Net's up "
                               "path) read where it projects: the shape read from the input's pixels",
                               {"shape_detail": "features"}, runs=(("metallic", 0),)),
    "pixel-normals": Variant("in evaluation, the probe's mirror cue read through normals an image-space U-Net "
                             "predicts per pixel, fitted to the GT mesh's before the model trains as the default "
                             "(3D supervision the paper does not use)",
                             {"probe_normals": "pixels"}, runs=(("metallic", 0), ("glossy", 0))),
    # diagnostics: they read ground truth, so they measure a limit, not a model
    "light-supervised-map": Variant("the light supervised by the GT env map (log L1 on the map)",
                                    {"light_supervision": "map"}, kind="diagnostic",
                                    runs=(("glossy", 0), ("metallic", 0))),
    "light-supervised-probe": Variant("the light supervised by the GT map's rough-metal probe (the light metric)",
                                      {"light_supervision": "probe"}, kind="diagnostic",
                                      runs=(("glossy", 0), ("metallic", 0))),
    "sun-supervised": Variant("the probe head's sun distribution supervised by each sunny GT map's dominant direction: "
                              "what one view's cue through the predicted surface can tell a head of the sun",
                              {"light_supervision": "sun"}, kind="diagnostic", runs=(("metallic", 0),)),
    "shape-supervised": Variant("the predicted normals supervised by the GT mesh's in the input view: what one view can "
                                "predict of the normals when told them",
                                {"shape_supervision": True}, kind="diagnostic", runs=(("metallic", 0),)),
    "vertex-features-supervised": Variant("vertex-features with its normals supervised as in shape-supervised: what "
                                          "a shape read from the pixels can predict of the normals when told them",
                                          {"shape_detail": "features", "shape_supervision": True}, kind="diagnostic",
                                          runs=(("metallic", 0),)),
    "shape-supervised-40-objects": Variant("shape-supervised on half the training objects (40 of 80): how the normals "
                                           "one view predicts when told them depend on the number of objects",
                                           {"shape_supervision": True, "train_objects": 40}, kind="diagnostic",
                                           runs=(("metallic", 0), ("metallic", 1))),
    "oracle-roughness": Variant("renders use each object's GT roughness (the roughness/light-blur ambiguity)",
                                {"oracle_roughness": True}, kind="diagnostic"),
}

# the fields some variant sets: a run that changes them by hand is labelled with them (not the lobes and the samples
# per pixel, which the paper's tables and the presets set: budgets the tables compare, not model choices)
EXPERIMENT_FIELDS = tuple(dict.fromkeys(k for v in VARIANTS.values() for k in v.fields if k not in ("lobes", "spp")))
