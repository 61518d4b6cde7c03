import math

import numpy as np
import pytest
import torch

from dibrpp import conventions as conv
from dibrpp import io
from dibrpp.camera import Cameras
from dibrpp.mesh import cotangent_laplacian, icosphere, laplacian_smoothness, uniform_laplacian, vertex_normals


def test_orbit_camera_position_and_axes():
    cams = Cameras.orbit(60.0, 27.0, 90.0, 40.0, 64)
    el = math.radians(27)
    assert torch.allclose(cams.centers[0], torch.tensor([0.0, 60 * math.cos(el), 60 * math.sin(el)]), atol=1e-4)
    # looks at the origin down its -Z; camera +Y has a positive world-Z component (world up +Z)
    r = cams.rotation[0]
    forward_world = -r[2]
    assert torch.allclose(forward_world, -cams.centers[0] / 60, atol=1e-5)
    assert r[1, 2] > 0
    assert torch.allclose(r @ r.T, torch.eye(3), atol=1e-5)
    # the origin projects to the image centre
    ndc, depth = cams.project(torch.zeros(1, 3))
    assert torch.allclose(ndc, torch.zeros(1, 1, 2), atol=1e-6) and abs(depth.item() - 60) < 1e-4


def test_camera_straight_above_is_well_defined():
    cams = Cameras.orbit(5.0, 90.0, 0.0, 40.0, 8)
    assert torch.isfinite(cams.world_to_camera).all()
    assert torch.allclose(cams.rotation[0] @ cams.rotation[0].T, torch.eye(3), atol=1e-5)


def test_field_of_view_is_the_full_angle():
    fov = 40.0
    cams = Cameras.orbit(10.0, 0.0, 0.0, fov, 64)
    # a point on the edge of the view: 10 * tan(20 deg) to the right (world +Y, seen from +X)
    p = torch.tensor([[0.0, 10 * math.tan(math.radians(fov / 2)), 0.0]])
    ndc, _ = cams.project(p)
    assert torch.allclose(ndc[0, 0], torch.tensor([1.0, 0.0]), atol=1e-5)


def test_orbited_cameras_are_orbit_cameras_further_round():
    cams = Cameras.orbit(60.0, 27.0, torch.tensor([10.0, 200.0]), 40.0, 16)
    moved = cams.orbited(90.0)
    expected = Cameras.orbit(60.0, 27.0, torch.tensor([100.0, 290.0]), 40.0, 16)
    torch.testing.assert_close(moved.world_to_camera, expected.world_to_camera, atol=1e-4, rtol=0)
    torch.testing.assert_close(moved.fov, cams.fov)


def test_view_directions_point_back_to_the_camera():
    cams = Cameras.orbit(7.0, 20.0, 40.0, 50.0, 9)
    v = cams.view_directions_world()
    assert torch.allclose(v[0, 4, 4], cams.centers[0] / 7.0, atol=1e-5)


def test_view_directions_of_a_batch_of_cameras_are_each_cameras_own():
    cams = Cameras.orbit(7.0, 20.0, torch.tensor([40.0, 130.0, 250.0]), 50.0, 9)
    v = cams.view_directions_world()
    assert v.shape == (3, 9, 9, 3)
    for k in range(3):
        torch.testing.assert_close(v[k], cams[[k]].view_directions_world()[0])
        torch.testing.assert_close(v[k, 4, 4], cams.centers[k] / 7.0, atol=1e-5, rtol=0)


def test_equirect_mapping_matches_blender():
    d = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0]])
    uv = conv.direction_to_equirect_uv(d)
    assert torch.allclose(uv[0], torch.tensor([0.5, 0.5]))
    assert torch.allclose(uv[1], torch.tensor([0.25, 0.5]))
    assert torch.allclose(uv[2], torch.tensor([0.75, 0.5]))
    assert abs(uv[3, 1]) < 1e-6
    # many float32-normalised directions, some a hair from the poles (where acos(z) was off by 3e-4)
    dirs = torch.randn(100_000, 3, generator=torch.Generator().manual_seed(1))
    dirs[:100, :2] *= 1e-4
    dirs = torch.nn.functional.normalize(dirs, dim=-1)
    torch.testing.assert_close(conv.equirect_uv_to_direction(conv.direction_to_equirect_uv(dirs)), dirs,
                               atol=2e-6, rtol=0)
    assert abs(conv.equirect_solid_angles(16, 32).sum() * 32 - 4 * math.pi) < 1e-4


def test_srgb_round_trip():
    x = torch.linspace(0, 1, 101)
    assert torch.allclose(conv.linear_to_srgb(conv.srgb_to_linear(x)), x, atol=1e-5)
    assert abs(conv.srgb_to_linear(torch.tensor(0.5)) - 0.2140) < 1e-3


def test_icosphere_template():
    m = icosphere()
    assert m.verts.shape == (1, 642, 3) and m.faces.shape == (1280, 3)
    assert icosphere(4).verts.shape[1] == 2562
    # outward counter-clockwise winding, unit normals pointing out
    n = vertex_normals(m.verts, m.faces)[0]
    assert torch.allclose(n, m.verts[0], atol=0.02)
    assert (m.face_normals()[0] * m.verts[0][m.faces].mean(1)).sum(-1).min() > 0
    # uvs: no face spans more than a small range (the seam is split)
    corner_u = m.uvs[m.face_uvs][..., 0]
    assert (corner_u.max(1).values - corner_u.min(1).values).max() < 0.3


def test_laplacians():
    m = icosphere(2)
    lu = uniform_laplacian(m.faces, m.verts.shape[1])
    lc = cotangent_laplacian(m.verts[0], m.faces)
    ones = torch.ones(m.verts.shape[1], 1)
    assert torch.allclose(torch.sparse.mm(lu, ones), torch.zeros_like(ones), atol=1e-5)
    assert torch.allclose(torch.sparse.mm(lc, ones), torch.zeros_like(ones), atol=1e-4)
    # a smooth sphere is smoother than a noisy one
    noisy = m.verts + 0.05 * torch.randn_like(m.verts)
    assert laplacian_smoothness(noisy, lu) > 2 * laplacian_smoothness(m.verts, lu)


def test_exr_round_trip_and_clear_errors(tmp_path):
    img = np.random.rand(5, 7, 4).astype(np.float32) * 10
    io.write_exr(tmp_path / "a.exr", img)
    assert np.array_equal(io.read_exr(tmp_path / "a.exr", "RGBA"), img)
    (tmp_path / "broken.exr").write_bytes(b"not an exr")
    with pytest.raises(io.DataError, match="not a readable OpenEXR"):
        io.read_exr(tmp_path / "broken.exr")
    with pytest.raises(io.DataError, match="no such file"):
        io.read_exr(tmp_path / "missing.exr")
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    io.write_exr(tmp_path / "nan.exr", bad)
    with pytest.raises(io.DataError, match="non-finite"):
        io.read_exr(tmp_path / "nan.exr", "RGBA")
    with pytest.raises(io.DataError, match="missing"):
        io.read_exr(tmp_path / "a.exr", "RGBZ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "broken.exr", "nan.exr"]  # no temp files left


def test_png_and_mesh_io(tmp_path):
    img = np.random.rand(4, 6, 3).astype(np.float32)
    io.write_png(tmp_path / "a.png", img)
    back = io.read_png(tmp_path / "a.png", linear=True)
    assert np.abs(back - img).max() < 0.02
    m = icosphere(1)
    io.save_mesh(tmp_path / "s.obj", m.verts[0], m.faces)
    loaded = io.load_mesh(tmp_path / "s.obj")
    assert loaded.verts.shape == m.verts.shape and torch.equal(loaded.faces, m.faces)
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(io.DataError, match="NaN"):
        io.load_mesh(tmp_path / "nan.obj")
