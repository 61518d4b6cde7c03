"""datagen.cycles: the single-scene Cycles API renders in the project's conventions.

Every render here is tiny (32-64 px, a few samples, filter width 0.01 = pixel-centre sampling) so the
whole file runs in well under a minute on 2 cores.
"""
import math

import numpy as np
import pytest
import torch

pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from datagen import cycles  # noqa: E402
from dibrpp import conventions as conv  # noqa: E402
from dibrpp.io import write_png  # noqa: E402

pytestmark = pytest.mark.cycles

FOV = math.radians(30.0)
D = 30.0


def sphere(radius=5.0, center=(0.0, 0.0, 0.0), subdivisions=4):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices) + np.asarray(center), np.asarray(s.faces)


def w2c(azimuth=0.0, elevation=0.0, distance=D):
    return conv.orbit_world_to_camera(float(distance), float(elevation), float(azimuth)).numpy()


def flat_env(value=0.5, h=16, w=32):
    return np.full((h, w, 3), value, np.float32)


def test_silhouette_matches_analytic_disc_and_orientation():
    # Sphere of radius r, off-centre: up (+Z) and to the camera's right (+Y for a camera on +X).
    r, res = 3.0, 64
    center = np.array([0.0, 4.0, 3.0])
    v, f = sphere(r, center)
    out = cycles.render_scene(v, f, world_to_camera=w2c(), fov=FOV, resolution=res, envmap=flat_env(),
                              spp=4, filter_width=0.01)
    alpha = out["rgba"][..., 3]
    assert out["rgba"].shape == (res, res, 4) and out["rgba"].dtype == np.float32
    assert alpha.max() == pytest.approx(1.0, abs=1e-4) and alpha[0, 0] == 0.0
    # Expected projected ellipse via dibrpp's conventions: sample the silhouette analytically by
    # casting a ray through each pixel centre and intersecting the sphere.
    rays = conv.camera_ray_directions(res, res, FOV, dtype=torch.float64)  # camera space
    m = torch.as_tensor(w2c(), dtype=torch.float64)
    rays_w = rays @ m[:3, :3]  # camera -> world: R^T d (row-vector form)
    eye = -(m[:3, :3].T @ m[:3, 3])
    oc = eye - torch.as_tensor(center)
    b = (rays_w * oc).sum(-1)
    disc = b * b - (oc @ oc - r * r)
    expected = (disc > 0).numpy().astype(np.float32)
    # Hard coverage at pixel centres: all but the boundary pixels agree.
    assert np.abs((alpha > 0.5) - expected).sum() <= 0.04 * expected.sum() + 4
    rows, cols = np.nonzero(expected)
    rr, cc = np.nonzero(alpha > 0.5)
    assert abs(rr.mean() - rows.mean()) < 0.5 and abs(cc.mean() - cols.mean()) < 0.5
    # And the orientation itself: up is up (top row first), camera right (+Y) is to the right.
    assert rr.mean() < res / 2 - 3 and cc.mean() > res / 2 + 3


def _reflection_env(h=64, w=128):
    """Smooth env map coded by direction: R = +Y, G = +Z, B = +X."""
    d = conv.equirect_directions(h, w, dtype=torch.float64)
    env = torch.stack([d[..., 1].clamp_min(0), d[..., 2].clamp_min(0), d[..., 0].clamp_min(0)], -1) + 0.05
    return env.float().numpy()


def _env_lookup(env, d):
    h, w = env.shape[:2]
    uv = conv.direction_to_equirect_uv(d)
    col = (uv[..., 0] * w).long().clamp(0, w - 1)
    row = (uv[..., 1] * h).long().clamp(0, h - 1)
    return torch.as_tensor(env)[row, col]


def test_mirror_sphere_envmap_orientation():
    """A perfect mirror sphere reflects the env map exactly where dibrpp's conventions say it should."""
    r, res = 5.0, 48
    v, f = sphere(r, subdivisions=5)
    env = _reflection_env()
    az, el = 30.0, 20.0
    m = w2c(az, el)
    out = cycles.render_scene(v, f, world_to_camera=m, fov=FOV, resolution=res, envmap=env, base_color=(1, 1, 1),
                              roughness=0.0, metallic=1.0, spp=4, filter_width=0.01)
    rgb = torch.as_tensor(out["rgba"][..., :3], dtype=torch.float64)
    mt = torch.as_tensor(m, dtype=torch.float64)
    rays = conv.camera_ray_directions(res, res, FOV, dtype=torch.float64) @ mt[:3, :3]
    eye = -(mt[:3, :3].T @ mt[:3, 3])
    b = (rays * eye).sum(-1)
    disc = b * b - (eye @ eye - r * r)
    inside = disc > (0.5 * r) ** 2  # well inside the silhouette (no edge pixels)
    t = -b - disc.clamp_min(0).sqrt()
    n = torch.nn.functional.normalize(eye + t.unsqueeze(-1) * rays, dim=-1)
    refl = rays - 2 * (rays * n).sum(-1, keepdim=True) * n
    expected = _env_lookup(env, refl.float()).double()
    err = (rgb - expected).abs()[inside]
    assert inside.sum() > 200
    # Nearest-texel lookup vs Cycles' bilinear on a smooth map: small errors only.
    assert err.mean() < 0.02, err.mean()
    assert torch.quantile(err.max(-1).values, 0.95) < 0.06
    # A flipped convention (e.g. u mirrored) would be far off: check the test can fail.
    flipped = _env_lookup(env, refl.float() * torch.tensor([1.0, -1.0, 1.0])).double()
    assert (rgb - flipped).abs()[inside].mean() > 5 * err.mean()


def _quadrant_texture(n=32):
    tex = np.zeros((n, n, 3), np.float32)
    h = n // 2
    tex[:h, :h] = (0.9, 0.1, 0.1)  # top-left: red
    tex[:h, h:] = (0.1, 0.9, 0.1)  # top-right: green
    tex[h:, :h] = (0.1, 0.1, 0.9)  # bottom-left: blue
    tex[h:, h:] = (0.9, 0.9, 0.2)  # bottom-right: yellow
    return tex


def _plane(s=8.0):
    # In the plane x = 0, facing +X (a camera at azimuth 0): camera right = +Y, up = +Z.
    v = np.array([[0, -s, -s], [0, s, -s], [0, s, s], [0, -s, s]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)  # OBJ convention: v up
    return v, f, uv


@pytest.mark.parametrize("as_png", [False, True])
def test_texture_uv_orientation_and_albedo_for_metal(tmp_path, as_png):
    v, f, uv = _plane()
    tex = _quadrant_texture()
    texture = tex
    if as_png:
        texture = tmp_path / "tex.png"
        write_png(texture, conv.srgb_to_linear(torch.as_tensor(tex)))  # round-trips to the same sRGB bytes
    res = 32
    # Per-corner UVs for the first case, per-vertex for the second: both paths are exercised.
    kw = dict(uvs=uv, face_uvs=f) if not as_png else dict(uvs=uv)
    out = cycles.render_scene(v, f, world_to_camera=w2c(), fov=FOV, resolution=res, envmap=flat_env(0.3),
                              texture=texture, roughness=0.3, metallic=1.0, spp=4, filter_width=0.01,
                              albedo_aov=True, **kw)
    albedo = out["albedo"]
    assert albedo.shape == (res, res, 3)
    lin = conv.srgb_to_linear(torch.as_tensor(tex)).numpy()
    q = res // 2
    # The plane fills the view (half-size 8 at distance 30 with fov 30 deg spans ~0.99 of it).
    for (r, c), (tr, tc) in {(q // 2, q // 2): (0, 0), (q // 2, q + q // 2): (0, 31),
                             (q + q // 2, q // 2): (31, 0), (q + q // 2, q + q // 2): (31, 31)}.items():
        np.testing.assert_allclose(albedo[r, c], lin[tr, tc], atol=0.02 if as_png else 2e-3)
    # The metal's shaded colour is tinted by its base colour (not zero as the Diffuse Color pass would be).
    assert out["rgba"][q // 2, q // 2, 0] > 2 * out["rgba"][q // 2, q // 2, 1]


def test_albedo_is_base_colour_for_metal_and_zero_on_background():
    v, f = sphere(5.0, subdivisions=3)
    colour = (0.7, 0.3, 0.1)
    out = cycles.render_scene(v, f, world_to_camera=w2c(), fov=FOV, resolution=32, envmap=flat_env(),
                              base_color=colour, metallic=1.0, roughness=0.0, spp=4, albedo_aov=True)
    np.testing.assert_allclose(out["albedo"][16, 16], colour, atol=1e-4)
    assert np.all(out["albedo"][0, 0] == 0)
    # Coverage-weighted like the alpha (same samples and filter).
    np.testing.assert_allclose(out["albedo"][..., 0] / colour[0], out["rgba"][..., 3], atol=1e-3)


def test_scene_reuse_across_cameras_and_determinism():
    v, f = sphere(5.0, subdivisions=3)
    kw = dict(envmap=_reflection_env(16, 32), resolution=24, roughness=0.4, spp=4, seed=3)
    cams = [w2c(0), w2c(90)]
    cs = cycles.build_scene(v, f, envmap=kw["envmap"], material=cycles.PrincipledMaterial(roughness=0.4),
                            settings=cycles.RenderSettings(resolution=24, spp=4, seed=3))
    views = []
    for m in cams:
        cycles.set_camera(cs, m, FOV)
        views.append(cycles.render(cs)["rgba"])
    assert cs.renders == 2 and cs.render_seconds > 0
    assert not np.allclose(views[0], views[1])  # the camera moved (the env map is not symmetric)
    # A fresh scene with the same seed gives the same pixels as the reused one.
    again = cycles.render_scene(v, f, world_to_camera=cams[1], fov=FOV, **kw)["rgba"]
    np.testing.assert_array_equal(again, views[1])
    other_seed = cycles.render_scene(v, f, world_to_camera=cams[1], fov=FOV, **{**kw, "seed": 4})["rgba"]
    assert not np.array_equal(other_seed, views[1])
    # Records and keywords are the same call (keywords override the records' fields).
    records = cycles.render_scene(v, f, world_to_camera=cams[1], fov=FOV, envmap=kw["envmap"],
                                  material=cycles.PrincipledMaterial(roughness=0.9),
                                  settings=cycles.RenderSettings(resolution=24, spp=4, seed=4), roughness=0.4)["rgba"]
    np.testing.assert_array_equal(records, other_seed)


def test_set_envmap_swaps_lighting():
    v, f = sphere(5.0, subdivisions=3)
    cs = cycles.build_scene(v, f, envmap=flat_env(0.2), material=cycles.PrincipledMaterial(roughness=0.5),
                            settings=cycles.RenderSettings(resolution=16, spp=2))
    cycles.set_camera(cs, w2c(), FOV)
    a = cycles.render(cs)["rgba"]
    cycles.set_envmap(cs, flat_env(0.8))
    b = cycles.render(cs)["rgba"]
    np.testing.assert_allclose(b[8, 8, :3], 4 * a[8, 8, :3], rtol=0.1)


def test_bad_inputs_raise_clear_errors():
    v, f = sphere(5.0, subdivisions=1)
    base = dict(world_to_camera=w2c(), fov=FOV, resolution=16, envmap=flat_env())
    with pytest.raises(ValueError, match="resolution"):
        cycles.render_scene(v, f, **{**base, "resolution": 0})
    with pytest.raises(ValueError, match="faces index"):
        cycles.render_scene(v, f + len(v), **base)
    with pytest.raises(ValueError, match="needs uvs"):
        cycles.render_scene(v, f, texture=np.zeros((4, 4, 3)), **base)
    with pytest.raises(ValueError, match="rigid"):
        cycles.render_scene(v, f, **{**base, "world_to_camera": np.diag([2.0, 1, 1, 1])})
    with pytest.raises(ValueError, match="envmap"):
        cycles.render_scene(v, f, **{**base, "envmap": np.zeros((4, 4))})
    from dibrpp.io import DataError

    with pytest.raises(DataError, match="no such"):
        cycles.render_scene(v, f, **{**base, "envmap": "/nonexistent/env.exr"})


def test_records_validate_and_loose_arguments_are_refused():
    """No render: the records' checks, and the API refuses arguments it would otherwise drop."""
    with pytest.raises(ValueError, match="roughness"):
        cycles.PrincipledMaterial(roughness=1.5).validate()
    with pytest.raises(ValueError, match="subsurface_method"):
        cycles.PrincipledMaterial(subsurface_method="CHRISTENSEN").validate()
    with pytest.raises(ValueError, match="unknown material parameter"):
        cycles.PrincipledMaterial.from_dict(dict(roughness=0.2, sheen=1.0))
    m = cycles.PrincipledMaterial.from_dict(dict(roughness=0.2, metallic=1.0, subsurface_radius=[1, 0.3, 0.2]),
                                            texture="t.png")
    assert (m.roughness, m.metallic, m.texture, m.specular_ior_level) == (0.2, 1.0, "t.png", 0.5)
    for bad, match in ((dict(spp=0), "spp"), (dict(filter_width=0.0), "filter_width"), (dict(device="TPU"), "device"),
                       (dict(resolution=8, width=0), "resolution"), (dict(adaptive_threshold=-1), "adaptive")):
        with pytest.raises(ValueError, match=match):
            cycles.RenderSettings(**bad).validate()
    v, f = sphere(5.0, subdivisions=1)
    with pytest.raises(TypeError):
        cycles.build_scene(v, f, envmap=flat_env(), resolution=16)  # loose settings: use RenderSettings
    with pytest.raises(TypeError, match="unknown argument"):
        cycles.render_scene(v, f, world_to_camera=w2c(), fov=FOV, envmap=flat_env(), roughnes=0.2)


def test_denoiser_removes_noise_but_leaves_the_albedo_alone():
    """RenderSettings(denoise=True): OpenImageDenoise (albedo + normal guides) on the shaded render only."""
    v, f = sphere(5.0, subdivisions=3)
    env = _reflection_env(16, 32)
    kw = dict(world_to_camera=w2c(20, 10), fov=FOV, envmap=env, roughness=0.6, albedo_aov=True, resolution=24,
              subsurface_weight=1.0, subsurface_radius=(1.0, 0.35, 0.2), subsurface_scale=0.5)
    ref = cycles.render_scene(v, f, spp=256, seed=9, **kw)
    raw = cycles.render_scene(v, f, spp=4, seed=1, **kw)
    den = cycles.render_scene(v, f, spp=4, seed=1, denoise=True, **kw)
    inside = ref["rgba"][..., 3] > 0.99
    err = lambda out: np.sqrt(((out["rgba"][..., :3] - ref["rgba"][..., :3])[inside] ** 2).mean())  # noqa: E731
    assert err(den) < 0.7 * err(raw), (err(den), err(raw))
    np.testing.assert_array_equal(den["albedo"], raw["albedo"])
    np.testing.assert_allclose(den["rgba"][..., 3], raw["rgba"][..., 3], atol=0.02)
