"""The encoder's heads reach the data, its priors hold exactly, and checkpoints carry their configuration."""
import json
import math

import numpy as np
import pytest
import torch

from dibrpp import Cameras, Renderer
from dibrpp.brdf import MIN_ALPHA, alpha_from_roughness
from dibrpp.conventions import equirect_directions, linear_to_srgb
from dibrpp.mesh import icosphere
from pipelines.training import losses
from pipelines.model.light_probe import compress_radiance, pixel_samples
from pipelines.model.encoder import DIELECTRIC_SPECULAR, Encoder, ModelConfig, squash
from pipelines.model.prediction import white_balance
from pipelines.model.model_input import clip_input, decode_colour, encode_colour, encoder_input, input_radiance


def _cams(n, size=32):
    return Cameras.orbit(60.0, 27.0, torch.linspace(0, 300, n), 39.6, size)


def _saturate(model, head, sign):
    with torch.no_grad():
        head.weight.zero_()
        head.bias.fill_(sign * 50.0)


@pytest.mark.parametrize("kind", ["sg", "sh", "mc"])
def test_light_is_white_balanced(kind):
    torch.manual_seed(0)
    model = Encoder(ModelConfig(shading=kind, lobes=4, image_size=32))
    with torch.no_grad():
        model.light_head.bias.add_(torch.randn_like(model.light_head.bias))
    cams = _cams(2)
    pred = model(torch.rand(2, 4, 32, 32), cams)
    mean = pred.light(cams.world_to_camera).to_envmap(64, 128).image
    w = torch.sin((torch.arange(64) + 0.5) * math.pi / 64).view(1, -1, 1, 1)
    total = (mean * w).sum((1, 2))
    assert torch.allclose(total, total.mean(-1, keepdim=True).expand_as(total), rtol=2e-2 if kind == "sh" else 1e-3)


def test_free_light_keeps_its_colour():
    light = {"amplitude": torch.tensor([[[1.0, 0.5, 0.2]]]), "sharpness": torch.tensor([[3.0]])}
    assert not torch.allclose(light["amplitude"], white_balance(light, "sg")["amplitude"])
    model = Encoder(ModelConfig(shading="sg", lobes=2, image_size=32, light_colour="free"))
    with torch.no_grad():
        model.light_head.bias.view(2, 7)[:, 4:] = torch.tensor([1.0, 0.0, -1.0])
    amp = model(torch.rand(1, 4, 32, 32), _cams(1)).light_params["amplitude"]
    assert amp[0, 0, 0] > amp[0, 0, 2] * 2


def test_shape_is_mirror_symmetric_and_starts_at_the_template_radius():
    torch.manual_seed(0)
    model = Encoder(ModelConfig(image_size=32))
    pred = model(torch.rand(1, 4, 32, 32), _cams(1))
    assert torch.allclose(pred.verts.norm(dim=-1), torch.full_like(pred.verts[..., 0], 12.0), atol=1e-3)
    with torch.no_grad():
        model.shape_head.bias.normal_(0, 3)
    v = model(torch.rand(1, 4, 32, 32), _cams(1)).verts[0]
    mirrored = v[model.mirror] * torch.tensor([1.0, -1.0, 1.0])
    assert torch.allclose(v, mirrored, atol=1e-4)


def test_the_pixel_normals_start_facing_the_camera_in_the_world_and_the_probe_reads_them_held_in_evaluation():
    torch.manual_seed(0)
    model = Encoder(ModelConfig(image_size=32, light_head="probe", probe_normals="pixels"))
    torch.manual_seed(0)
    default = Encoder(ModelConfig(image_size=32, light_head="probe"))
    for name, value in default.state_dict().items():  # the network draws its own weights: the rest start as before
        assert torch.equal(model.state_dict()[name], value), name
    images, cams = torch.rand(2, 4, 32, 32), _cams(2)
    net = model.pixel_normals
    with torch.no_grad():
        net.out.weight.zero_()
        net.out.bias.zero_()
        net.out.bias.copy_(torch.tensor([0.8, 0.3, 0.0]))  # turned normals, which training must not read:
        training = model(images, cams)  # in training the probe reads the surface's normals, as the default does
        assert training.pixel_normals is None
        assert torch.equal(training.light_params["amplitude"], default(images, cams).light_params["amplitude"])
        net.out.bias.zero_()
    model.eval()
    towards_camera = torch.nn.functional.normalize(cams.centers, dim=-1).view(2, 1, 1, 3)  # the cameras look at 0
    pred = model(images, cams)
    assert pred.pixel_normals.shape == (2, 32, 32, 3)
    assert torch.allclose(pred.pixel_normals, towards_camera.expand(2, 32, 32, 3), atol=1e-5)
    assert torch.equal(pred.select([1]).pixel_normals, pred.pixel_normals[1:])
    with torch.no_grad():  # other normals: another mirror cue, so another light
        net.out.bias.copy_(torch.tensor([0.8, 0.3, 0.0]))
    turned = model(images, cams)
    assert not torch.allclose(turned.light_params["amplitude"], pred.light_params["amplitude"])
    turned.light_params["amplitude"].sum().backward()  # held: the light is no loss of theirs
    assert all(p.grad is None or p.grad.abs().max() == 0 for p in net.parameters())
    assert model.light_head.log_gain.grad is not None
    with pytest.raises(ValueError, match="probe_normals 'pixels'"):
        Encoder(ModelConfig(image_size=32, probe_normals="pixels"))  # the global light head has no pixels


def test_texels_follow_the_template_surface():
    model = Encoder(ModelConfig(image_size=32))
    c = model.config
    pos = (model.template_dirs[0][model.faces[model.texel_face]] * model.texel_bary[..., None]).sum(1)
    d = equirect_directions(c.texture_height, c.texture_width).reshape(-1, 3)
    # the point hit is on the texel's ray and on the (inscribed, faceted) sphere
    assert torch.nn.functional.cosine_similarity(pos, d, dim=-1).min() > 1 - 1e-5
    assert pos.norm(dim=-1).min() > 0.97 and pos.norm(dim=-1).max() <= 1 + 1e-5


def test_projected_texture_sees_the_input_colour():
    """A red input, untrained network: the texels facing the camera see red, the others see nothing."""
    torch.manual_seed(0)
    model = Encoder(ModelConfig(image_size=32))
    cams = _cams(1)
    rgba = torch.zeros(1, 32, 32, 4)
    rgba[..., 0], rgba[..., 3] = 0.8, 1.0
    verts = model._shape(model.shape_head.bias.detach()[None])
    stem = model.stem(encoder_input(rgba))
    seen = model._projected(stem, encoder_input(rgba), model._texel_view(verts, cams))
    facing = seen[:, -1] > 0
    assert 0.2 < facing.float().mean() < 0.6
    red = linear_to_srgb(torch.tensor(0.8))
    assert torch.allclose(seen[:, 0][facing], red.expand(int(facing.sum())), atol=1e-5)
    assert (seen[:, 0][~facing] == 0).all()


def test_heads_reach_the_datasets_ground_truth(tiny_glossy):
    """Saturate every head: the reachable shapes and materials cover the ground truth of a real dataset."""
    manifest = json.loads((tiny_glossy / "manifest.json").read_text())
    half = np.array([np.abs(np.load(tiny_glossy / "objects" / f"obj_{o['index']:04d}" / "mesh.npz")["verts"]).max(0)
                     for o in manifest["objects"]])
    truth = [json.loads((tiny_glossy / "objects" / f"obj_{o['index']:04d}" / "object.json").read_text())["material"]
             for o in manifest["objects"]]
    model = Encoder(ModelConfig(image_size=32, predict_metallic=True, specular="learnt"))
    cams = _cams(1)
    reach = {}
    for sign in (-1, 1):
        _saturate(model, model.shape_head, 0)  # offsets at 0 ...
        model.shape_head.bias.data[-3:] = sign * 50.0  # ... and the per-axis scale at its bound
        _saturate(model, model.material_head, sign)
        with torch.no_grad():
            pred = model(torch.rand(1, 4, 32, 32), cams)
        reach[sign] = dict(half=pred.verts[0].abs().amax(0).numpy(), rough=float(pred.roughness),
                           spec=float(pred.specular), metal=float(pred.metallic))
    assert (reach[1]["half"] >= half.max(0)).all() and (reach[-1]["half"] <= half.min(0)).all()
    assert reach[-1]["spec"] == 0 and reach[1]["spec"] == 1 and reach[-1]["metal"] == 0 and reach[1]["metal"] == 1
    for m in truth:
        assert reach[-1]["spec"] <= m["specular_ior_level"] <= reach[1]["spec"]
        assert reach[-1]["metal"] <= m["metallic"] <= reach[1]["metal"]
        # every roughness down to the BRDF's floor is reachable; below it all roughnesses render the same
        assert reach[-1]["rough"] <= max(m["roughness"], math.sqrt(MIN_ALPHA)) <= reach[1]["rough"]


def test_a_fixed_specular_is_the_dielectric_convention_whatever_the_head_says():
    """specular 'fixed': every prediction's specular level is 0.5 (F0 0.04) at either end of the head, the other
    materials still follow the head; a checkpoint written before the option reads as learnt."""
    model = Encoder(ModelConfig(image_size=32, predict_metallic=True, specular="fixed"))
    reach = {}
    for sign in (-1, 1):
        _saturate(model, model.material_head, sign)
        with torch.no_grad():
            reach[sign] = model(torch.rand(1, 4, 32, 32), _cams(1))
    assert all(float(p.specular) == DIELECTRIC_SPECULAR == 0.5 for p in reach.values())
    assert float(reach[-1].metallic) == 0 and float(reach[1].metallic) == 1
    assert float(reach[-1].roughness) < float(reach[1].roughness)
    saved = ModelConfig().to_dict()
    del saved["specular"]
    assert ModelConfig.from_dict(saved).specular == "learnt"
    with pytest.raises(ValueError, match="specular"):
        Encoder(ModelConfig(specular="0.04"))


def test_roughness_has_gradient_over_its_whole_range():
    lo, hi = ModelConfig().roughness_range
    x = torch.linspace(-6, 6, 50, requires_grad=True)
    alpha_from_roughness(squash(x, lo, hi)).sum().backward()
    inside = (squash(x.detach()) > 0) & (squash(x.detach()) < 1)
    assert (x.grad[inside] > 0).all()


def test_config_is_saved_with_the_version_and_old_checkpoints_are_refused():
    c = ModelConfig(shading="mc", lobes=8, texture="global")
    assert ModelConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    with pytest.raises(ValueError, match="retrain"):
        ModelConfig.from_dict({**c.to_dict(), "version": 1})
    with pytest.raises(ValueError, match="texture"):
        Encoder(ModelConfig(texture="flow"))


def test_encoder_input_is_srgb_on_black_with_alpha():
    rgba = torch.rand(2, 16, 16, 4)
    x = encoder_input(rgba)
    assert x.shape == (2, 4, 16, 16)
    assert torch.allclose(x[:, :3], (linear_to_srgb(rgba[..., :3]) * rgba[..., 3:]).permute(0, 3, 1, 2))
    assert torch.equal(x[:, 3], rgba[..., 3])


def test_full_range_input_keeps_the_sun_and_clipping_gives_the_8_bit_picture():
    x = torch.cat([torch.linspace(0, 1, 257), torch.logspace(0, 5, 100)])
    colour = encode_colour(x)
    assert (colour[1:] >= colour[:-1]).all() and float(colour.max()) < 6  # monotone, a sun ~1e4 reads < 6
    assert torch.allclose(decode_colour(colour), x, rtol=1e-5, atol=1e-6)
    torch.manual_seed(0)
    rgba = torch.rand(3, 16, 16, 4)
    rgba[..., :3] = rgba[..., :3] * torch.logspace(-1, 4, 16).view(1, 16, 1, 1)  # radiance up to 1e4
    rgba[0, ..., 3] = 1.0
    images = encoder_input(rgba)
    # clipped: bit for bit what the encoder saw before it could see the full range
    old = torch.cat([linear_to_srgb(rgba[..., :3]) * rgba[..., 3:], rgba[..., 3:]], -1).permute(0, 3, 1, 2)
    assert torch.equal(clip_input(images), old)
    radiance, alpha = input_radiance(images)
    assert torch.allclose(radiance[0], rgba[0, ..., :3], rtol=1e-4)  # the full range comes back where alpha is 1
    assert float(input_radiance(clip_input(images))[0].max()) <= 1.0
    # a colour over a tiny alpha (resampled edges) decodes to a bounded radiance, not to inf
    edge = torch.cat([torch.full((1, 3, 4, 4), 0.9), torch.full((1, 1, 4, 4), 1e-4)], 1)
    assert torch.isfinite(input_radiance(edge)[0]).all()
    # a clipped model sees the same input either way; a full-range one sees the sun
    cams = _cams(3, 16)
    for input_range in ("clipped", "full"):
        torch.manual_seed(1)
        model = Encoder(ModelConfig(image_size=16, light_head="probe", input_range=input_range))
        a, b = model(images, cams), model(clip_input(images), cams)
        same = all(torch.equal(a.light_params[k], b.light_params[k]) for k in a.light_params)
        assert same == (input_range == "clipped")


def test_the_probe_head_reads_radiance_linear_to_1_and_logarithmic_above():
    grid = torch.rand(2, 8, 4, 8)
    assert torch.equal(compress_radiance(grid), grid)
    grid[:, [0, 5]] = 1e4
    squeezed = compress_radiance(grid)
    assert torch.allclose(squeezed[:, [0, 5]], torch.tensor(1 + math.log(1e4)))
    assert torch.equal(squeezed[:, [3, 7]], grid[:, [3, 7]])  # coverage untouched


# ----------------------------------------------------------------------------- losses

def test_hdr_srgb_is_srgb_below_one_and_keeps_gradients_above():
    x = torch.linspace(0, 1, 101)
    assert torch.allclose(losses.hdr_srgb(x), linear_to_srgb(x), atol=1e-6)
    hi = torch.tensor([2.0, 50.0, 5000.0], requires_grad=True)
    losses.hdr_srgb(hi).sum().backward()
    assert (hi.grad > 0).all()
    assert (torch.diff(losses.hdr_srgb(torch.logspace(-4, 4, 200))) > 0).all()


def test_image_and_silhouette_losses_on_hand_made_cases():
    mask = torch.zeros(1, 4, 4)
    mask[:, :2] = 1
    a, b = torch.zeros(1, 4, 4, 3), torch.zeros(1, 4, 4, 3)
    b[:, :2] = 0.5
    assert losses.foreground_l1(a, b, mask).item() == pytest.approx(0.5)
    b[:, 2:] = 9.0  # background does not count
    assert losses.foreground_l1(a, b, mask).item() == pytest.approx(0.5)
    assert losses.soft_iou_loss(mask, mask).item() == pytest.approx(0)
    half = mask.clone()
    half[:, 1] = 0
    assert losses.soft_iou_loss(half, mask).item() == pytest.approx(0.5)
    x, y = torch.rand(1, 16, 16, 3), torch.zeros(1, 16, 16, 3)  # three scales need 16 px and more
    assert losses.gradient_loss(x, x).item() == 0 and losses.gradient_loss(x, y).item() > 0


def test_probe_light_starts_at_the_mirror_cue_and_places_it_in_the_world():
    """An untrained probe head (MC) returns the projected map itself: a mirror sphere seen from the front whose
    upper half is bright shows, through its mirror directions, a bright sky above and a dark ground below, in the
    world frame whatever the camera's azimuth."""
    torch.manual_seed(0)
    model = Encoder(ModelConfig(image_size=32, shading="mc", light_head="probe"))
    for azimuth in (0.0, 120.0):
        cams = Cameras.orbit(40.0, 0.0, azimuth, 40.0, 32)
        rgba = torch.zeros(1, 32, 32, 4)
        rgba[..., 3] = 1.0
        rgba[:, :16, :, :3] = 0.9  # the upper half of the image (rows from the top)
        rgba[:, 16:, :, :3] = 0.05
        pred = model(encoder_input(rgba), cams)
        env = pred.light(cams.world_to_camera).to_envmap(16, 32).image[0]
        assert env[:5].mean() > 5 * env[-5:].mean(), azimuth  # the top rows of the world map (+Z) are the bright ones


def test_pixel_samples_are_the_renderers_normals_at_the_covered_pixels():
    """The probe reads, at each pixel the predicted surface covers, the normal the renderer shades it with, the
    direction to the camera and what the input shows there; pixels it does not cover weigh nothing."""
    sphere = icosphere(2, radius=10.0)
    cams = Cameras.orbit(40.0, 25.0, torch.tensor([30.0, 200.0]), 40.0, 24)
    radiance, alpha = torch.rand(2, 24, 24, 3), torch.ones(2, 24, 24)
    alpha[1, :, :12] = 0.0  # the input's own silhouette counts too
    normals, to_camera, seen, weight = pixel_samples(sphere, cams, radiance, alpha)
    shown = Renderer("sg", compile=False).render_normals(sphere, cams)
    covered = shown.fragments.mask.reshape(2, -1) > 0
    assert torch.equal(weight[0] > 0, covered[0])
    assert torch.equal(weight[1] > 0, covered[1] & (alpha[1].reshape(-1) > 0))
    torch.testing.assert_close(normals[covered], shown.rgb[..., :3].reshape(2, -1, 3)[covered], atol=1e-5, rtol=0)
    torch.testing.assert_close(seen, radiance.reshape(2, -1, 3))
    assert torch.allclose(to_camera.norm(dim=-1), torch.ones(()))
    centre = 12 * 24 + 12  # the pixel below the image centre faces the camera almost squarely
    assert ((normals[:, centre] * to_camera[:, centre]).sum(-1) > 0.95).all()
    with pytest.raises(ValueError, match="pixels"):
        pixel_samples(sphere, cams, radiance[:, :16, :16], alpha[:, :16, :16])


def test_a_global_grid_of_4_keeps_the_fully_connected_layer_at_larger_inputs_and_changes_nothing_at_64():
    torch.manual_seed(0)
    default = Encoder(ModelConfig(image_size=64))
    torch.manual_seed(0)
    grid4 = Encoder(ModelConfig(image_size=64, global_grid=4))
    assert all(torch.equal(a, b) for a, b in zip(default.state_dict().values(), grid4.state_dict().values()))
    at128 = Encoder(ModelConfig(image_size=128, global_grid=4))
    assert at128.fc[1].weight.shape == default.fc[1].weight.shape and len(at128.backbone) == len(default.backbone) + 1
    assert Encoder(ModelConfig(image_size=128)).fc[1].weight.shape[1] == 4 * default.fc[1].weight.shape[1]
    pred = at128(encoder_input(torch.rand(1, 128, 128, 4)), _cams(1, 128))
    assert torch.isfinite(pred.meshes().verts).all()
    sides = {s: ModelConfig(image_size=s, global_grid=4).grid_side() for s in (32, 64, 96, 128, 256)}
    assert sides == {32: 2, 64: 4, 96: 3, 128: 4, 256: 4}


def test_the_sky_and_ground_colours_are_read_off_the_cue():
    """A cue (probe frame = world frame) of blue cells above the horizon and brown ones below: the sky's log colour
    over the ground's is the blue cells' over the brown ones' (the soft horizon mixes the cells next to it, within
    15 %). Untrained, the code's shift is zero."""
    from pipelines.model.light_probe import ProbeLightHead

    head = ProbeLightHead("sg", 8, 16, 32, 1000.0, 10.0, sky_ground=True)
    z = head.cell_dirs[0, 2]
    blue, brown = torch.tensor([0.1, 0.2, 0.6]), torch.tensor([0.4, 0.25, 0.1])
    grid = torch.zeros(1, 8, 16, 32)
    grid[0, :3] = torch.where(z > 0, blue.view(3, 1, 1), brown.view(3, 1, 1))
    grid[0, 3] = 1.0
    colour = head.hemisphere_colour(grid, torch.zeros(1, 512), torch.eye(3)[None])[0]
    sky_minus_ground = colour[:, 0, 0] - colour[:, -1, 0]  # the top row against the bottom row
    chroma = lambda c: c.log() - c.log().mean()  # noqa: E731
    expected = chroma(blue) - chroma(brown)
    assert torch.allclose(sky_minus_ground, expected, atol=0.15 * expected.abs().max())
