"""The sun-consensus loss on hand-made scenes: a sphere seen from two views with a sun's reflection drawn where
the sphere mirrors it."""
import torch

from dibrpp import Cameras
from dibrpp.mesh import Meshes, icosphere
from pipelines.light_probe import mirror_directions, pixel_samples
from pipelines.losses import sun_consensus_loss, sun_pixels


def _two_views_of_a_sun_on_a_sphere(sun: torch.Tensor, res: int = 32):
    sphere = icosphere(3, radius=10.0)
    a, b = Cameras.orbit(40.0, 25.0, 30.0, 40.0, res), Cameras.orbit(40.0, 35.0, 100.0, 40.0, res)
    cams = Cameras(torch.cat([a.world_to_camera, b.world_to_camera]), torch.cat([a.fov, b.fov]), res)
    images = torch.ones(2, res, res, 4)
    normals, to_camera, _, weight = pixel_samples(sphere.expand(2), cams, images[..., :3], images[..., 3])
    cos = (mirror_directions(normals, to_camera) * sun).sum(-1)
    bright = (cos > torch.cos(torch.deg2rad(torch.tensor(6.0)))) & (weight > 0.5)
    images[..., :3] = torch.where(bright.view(2, res, res, 1), 100.0, 1.0)
    return sphere, cams, images, bright


def test_sun_pixels_are_the_reflection_in_views_that_show_one_and_none_under_a_bright_sky():
    sun = torch.nn.functional.normalize(torch.tensor([0.3, 0.2, 1.0]), dim=0)
    sphere, cams, images, bright = _two_views_of_a_sun_on_a_sphere(sun)
    _, _, radiance, weight = pixel_samples(sphere.expand(2), cams, images[..., :3], images[..., 3])
    w = sun_pixels(radiance, weight)
    assert bright.sum(1).min() > 0 and torch.equal(w > 0, bright)
    assert float(sun_pixels(torch.ones_like(radiance), weight).sum()) == 0  # a uniform sky has no sun


def test_sun_consensus_is_zero_on_the_true_surface_and_pulls_a_wrong_one():
    sun = torch.nn.functional.normalize(torch.tensor([0.3, 0.2, 1.0]), dim=0)
    sphere, cams, images, _ = _two_views_of_a_sun_on_a_sphere(sun)
    true = float(sun_consensus_loss(sphere.expand(2), cams, images))
    verts = (sphere.verts * torch.tensor([1.0, 1.0, 0.6])).expand(2, -1, -1).clone().requires_grad_(True)
    squashed = Meshes(verts, sphere.faces, sphere.uvs, sphere.face_uvs)
    wrong = sun_consensus_loss(squashed, cams, images)
    wrong.backward()
    assert true < 0.01 < 0.1 < float(wrong) and float(verts.grad.abs().sum()) > 0, (true, float(wrong))
