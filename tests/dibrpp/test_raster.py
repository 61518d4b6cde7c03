import math

import pytest
import torch

from dibrpp import Material, Renderer
from dibrpp.camera import Cameras
from dibrpp.lights import SGLight
from dibrpp.mesh import Meshes, icosphere, torus
from dibrpp.raster import DIBR_SOFT_WIDTH_PX, RasterSettings, edge_response, rasterize, sample_texture


def front_camera(res=32, fov=40.0, distance=5.0):
    # camera on +X looking at the origin: world +Y is image right, +Z is image up
    return Cameras.orbit(distance, 0.0, 0.0, fov, res)


def quad(x, size=1.0):
    """Two triangles of a square in the plane X = x, facing +X (towards the camera)."""
    v = torch.tensor([[x, -size, -size], [x, size, -size], [x, size, size], [x, -size, size]])
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return v, f


def test_sphere_silhouette_matches_analytic_disc():
    r, d, fov, res = 18.0, 60.0, 40.0, 64
    frags = rasterize(icosphere(4, radius=r), Cameras.orbit(d, 27.0, 33.0, fov, res))
    disc_ndc = math.tan(math.asin(r / d)) / math.tan(math.radians(fov) / 2)
    expected = math.pi * (disc_ndc * res / 2) ** 2
    assert abs(frags.mask.sum().item() - expected) / expected < 0.02


def test_image_axes_follow_blender_camera():
    # a small square at world +Y (image right) and one at +Z (image up), seen from +X
    v1, f1 = quad(0.0, 0.3)
    v_right = v1 + torch.tensor([0.0, 1.5, 0.0])
    v_up = v1 + torch.tensor([0.0, 0.0, 1.5])
    for verts, where in ((v_right, "right"), (v_up, "up")):
        frags = rasterize(Meshes(verts, f1), front_camera())
        rows, cols = frags.mask[0].nonzero(as_tuple=True)
        if where == "right":
            assert cols.float().mean() > 20 and abs(rows.float().mean() - 15.5) < 1
        else:
            assert rows.float().mean() < 12 and abs(cols.float().mean() - 15.5) < 1


@pytest.mark.parametrize("near_first", [True, False])
def test_depth_test_picks_nearest_face_regardless_of_order(near_first):
    vn, fn = quad(1.0)  # nearer to the camera at +5
    vf, ff = quad(-1.0)
    verts = torch.cat([vn, vf] if near_first else [vf, vn])
    faces = torch.cat([fn, ff + 4])
    frags = rasterize(Meshes(verts, faces), front_camera())
    near_faces = {0, 1} if near_first else {2, 3}
    visible = set(frags.face_idx[frags.face_idx >= 0].unique().tolist())
    assert visible == near_faces
    assert torch.allclose(frags.depth[frags.mask > 0], torch.tensor(4.0), atol=1e-4)


def test_perspective_correct_interpolation_on_a_tilted_plane():
    # plane through the origin tilted about Z; interpolated world positions must lie on the pixel rays
    v = torch.tensor([[-2.0, -2.0, -1.0], [2.0, 2.0, -1.0], [2.0, 2.0, 1.0], [-2.0, -2.0, 1.0]])
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    cams = front_camera(res=48, fov=60.0, distance=4.0)
    frags = rasterize(Meshes(v, f), cams)
    pos = frags.interpolate(v.unsqueeze(0), f)
    # plane: x == y; ray from camera centre through the pixel must hit the plane at pos
    assert torch.allclose(pos[:, 0], pos[:, 1], atol=1e-4)
    ndc, _ = cams.project(pos.unsqueeze(0))
    rem = frags.pix % (48 * 48)
    centre = torch.stack([(2 * (rem % 48) + 1) / 48 - 1, 1 - (2 * (rem // 48) + 1) / 48], -1).float()
    assert torch.allclose(ndc[0], centre, atol=1e-4)


def test_degenerate_and_behind_camera_faces_and_empty_images_give_no_nan():
    v = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [0.0, 0, 0],  # zero area
                      [10.0, -1, -1], [10.0, 1, -1], [10.0, 0, 1],  # behind the camera at +5
                      [6.0, -1, -1], [4.0, 1, -1], [0.0, 0, 1]], requires_grad=True)  # crosses the camera plane
    f = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    frags = rasterize(Meshes(v, f), front_camera())
    assert frags.mask.sum() == 0
    (frags.soft_mask.sum() + frags.depth.sum()).backward()
    assert torch.isfinite(v.grad).all()
    empty = rasterize(Meshes(torch.tensor([[100.0, 100, 100], [100, 101, 100], [100, 100, 101]]), torch.tensor([[0, 1, 2]])), front_camera())
    assert empty.mask.sum() == 0 and torch.isfinite(empty.soft_mask).all() and empty.soft_mask.max() == 0


def test_soft_silhouette_is_one_inside_and_decays_outside():
    frags = rasterize(icosphere(2), front_camera(res=64, distance=4.0))
    soft, hard = frags.soft_mask[0], frags.mask[0]
    assert torch.all(soft[hard > 0] == 1)
    # DIB-R's sigma (1/7000 NDC^2) is ~0.4 px at 64 px: the band hugs the outline and vanishes 2 px out
    near = torch.nn.functional.max_pool2d(hard[None, None], 5, 1, 2)[0, 0] > 0
    band = soft[(hard == 0) & near]
    assert band.max() > 0.5 and torch.all(band <= 1)
    assert soft[~near].max() < 1e-3


def test_vertex_gradients_match_finite_differences():
    torch.manual_seed(0)
    v0 = quad(0.0, 0.8)[0].double()
    v0[:, 1:] += 0.05 * torch.randn(4, 2, dtype=torch.float64)
    f = quad(0.0)[1]
    colours = torch.rand(4, 3, dtype=torch.float64)
    cams = front_camera(res=24)
    cams = Cameras(cams.world_to_camera.double(), cams.fov.double(), 24)
    weights = torch.rand(24, 24, 5, dtype=torch.float64)
    settings = RasterSettings(soft_width_px=12 / math.sqrt(500))  # 1/500 NDC^2: wide enough for finite differences

    def loss(v):
        frags = rasterize(Meshes(v, f), cams, settings)
        rgb = frags.to_image(frags.interpolate(colours, f))[0]
        img = torch.cat([rgb, frags.soft_mask[0].unsqueeze(-1), frags.coverage[0].unsqueeze(-1)], -1)
        return (img * weights).sum()

    v = v0.clone().requires_grad_(True)
    loss(v).backward()
    eps = 1e-5
    for i in range(4):
        for k in (1, 2):  # image-plane coordinates; moving them moves the silhouette and the interpolation
            dv = torch.zeros_like(v0)
            dv[i, k] = eps
            fd = (loss(v0 + dv) - loss(v0 - dv)) / (2 * eps)
            # the hard mask is piecewise constant; FD is exact only while no pixel changes coverage
            assert abs(fd - v.grad[i, k]) <= 1e-3 * max(1.0, abs(fd)), (i, k, fd.item(), v.grad[i, k].item())


def test_optimising_vertices_towards_a_target_silhouette_reduces_the_loss():
    cams = Cameras.orbit(4.0, torch.tensor([0.0, 30.0, -20.0]), torch.tensor([0.0, 90.0, 200.0]), 45.0, 48)
    target_mesh = icosphere(2)
    target_mesh = target_mesh.with_verts(target_mesh.verts * torch.tensor([1.3, 0.8, 0.9]))
    target = rasterize(target_mesh, cams).mask
    sphere = icosphere(2)
    offset = torch.zeros_like(sphere.verts, requires_grad=True)
    opt = torch.optim.Adam([offset], lr=0.01)
    losses = []
    for _ in range(60):
        soft = rasterize(sphere.with_verts(sphere.verts + offset), cams).soft_mask
        loss = 1 - (soft * target).sum() / (soft + target - soft * target).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_texture_sampling_is_bilinear_and_differentiable():
    tex = torch.rand(1, 5, 7, 2, dtype=torch.float64, requires_grad=True)
    uv = torch.rand(30, 2, dtype=torch.float64, requires_grad=True)
    batch = torch.zeros(30, dtype=torch.long)
    assert torch.autograd.gradcheck(lambda t, u: sample_texture(t, u, batch), (tex, uv))
    # texel centres return the texel (OBJ convention: v up, row 0 at the top)
    centre = torch.tensor([[(3 + 0.5) / 7, 1 - (1 + 0.5) / 5]], dtype=torch.float64)
    assert torch.allclose(sample_texture(tex, centre, batch[:1]), tex[0, 1, 3])
    # wrap in u: sampling just past u = 1 blends the last and first columns
    edge = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    wrapped = sample_texture(tex, edge, batch[:1], wrap_u=True)
    assert torch.allclose(wrapped, 0.5 * (tex[0, 2, -1] + tex[0, 2, 0]))


# ----------------------------------------------------------------------------- silhouettes: soft mask, coverage

def blackman_harris_cdf_2d(s: torch.Tensor, angle: float, n: int = 1500) -> torch.Tensor:
    """Numerical edge response of Cycles' separable Blackman-Harris filter (width 1.5 px, spanning 3 px)."""
    x = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    wx = 0.35875 - 0.48829 * torch.cos(2 * math.pi * x) + 0.14128 * torch.cos(4 * math.pi * x) - 0.01168 * torch.cos(6 * math.pi * x)
    u = 3 * x - 1.5
    w2 = (wx[:, None] * wx[None, :]) / wx.sum() ** 2
    proj = u[:, None] * math.cos(angle) + u[None, :] * math.sin(angle)
    return torch.stack([(w2 * (proj < si)).sum() for si in s])


def filtered_supersampled_mask(mesh: Meshes, cam_at, res: int, factor: int = 16) -> torch.Tensor:
    """Reference coverage: the hard mask at ``factor`` x the resolution, filtered by the separable BH filter."""
    hi = rasterize(mesh, cam_at(res * factor), RasterSettings(soft=False, filter_width=0)).mask[0].double()
    taps = int(1.5 * factor)
    x = (torch.arange(-taps, taps, dtype=torch.float64) + 0.5) / factor  # sub-pixel centres around a pixel centre
    t = x / 3 + 0.5
    k = 0.35875 - 0.48829 * torch.cos(2 * math.pi * t) + 0.14128 * torch.cos(4 * math.pi * t) - 0.01168 * torch.cos(6 * math.pi * t)
    k = k / k.sum()
    pad = taps - factor // 2
    img = torch.nn.functional.pad(hi[None, None], (pad, pad, pad, pad))
    img = torch.nn.functional.conv2d(img, k.view(1, 1, 1, -1), stride=(1, factor))
    return torch.nn.functional.conv2d(img, k.view(1, 1, -1, 1), stride=(factor, 1))[0, 0]


def test_edge_response_is_the_blackman_harris_edge_integral():
    s = torch.linspace(-2.0, 2.0, 41, dtype=torch.float64)
    e = edge_response(s)
    assert torch.all(e[1:] >= e[:-1]) and e[s <= -1.5].abs().max() < 1e-12 and (e[s >= 1.5] - 1).abs().max() < 1e-12
    assert abs(e[20] - 0.5) < 1e-12
    assert (e - blackman_harris_cdf_2d(s, 0.0)).abs().max() < 1.5e-3  # axis-aligned edge: the filter's CDF
    assert (e - blackman_harris_cdf_2d(s, math.pi / 4)).abs().max() < 6e-3  # diagonal edge: close


def test_coverage_of_a_straight_edge_is_the_edge_response_of_its_distance():
    cams = front_camera(res=32)
    v, f = quad(0.0, 1.0)
    v = v + torch.tensor([0.0, 1.3, 0.0])  # right half of the image: the left edge is vertical, mid-image
    frags = rasterize(Meshes(v, f), cams)
    ndc, _ = cams.project(v)
    edge_col = (ndc[0, 0, 0] + 1) * 16 - 0.5  # pixel-centre coordinates
    row = frags.coverage[0, 16]
    expected = edge_response(torch.arange(32.0) - edge_col)
    assert (row - expected).abs().max() < 1e-5
    assert frags.mask[0, 16].sum() == (torch.arange(32.0) >= edge_col).sum()


@pytest.mark.parametrize("shape,res", [("sphere", 48), ("torus", 48), ("torus", 96)])
def test_coverage_matches_a_filtered_supersampled_mask(shape, res):
    mesh, elevation = (icosphere(4), 20.0) if shape == "sphere" else (torus(), 40.0)
    cam_at = lambda r: Cameras.orbit(3.2, elevation, 30.0, 40.0, r)  # noqa: E731
    ref = filtered_supersampled_mask(mesh, cam_at, res)
    frags = rasterize(mesh, cam_at(res))
    cov = frags.coverage[0].double()
    band = (torch.maximum(cov, ref) > 0.002) & (torch.minimum(cov, ref) < 0.998)
    err = (cov - ref).abs()[band]
    # measured: mean 0.002-0.003, worst pixel 0.05-0.15 (outline corners and T-junctions at the torus hole)
    assert err.mean() < 0.006 and err.max() < 0.25, (err.mean().item(), err.max().item())
    # the hard mask is ~0.14 off on the same band; DIB-R's soft mask further
    assert (frags.mask[0].double() - ref).abs()[band].mean() > 0.1


def test_coverage_sum_is_the_projected_area_and_its_gradient_the_area_gradient():
    cams = Cameras.orbit(5.0, 10.0, 20.0, 40.0, 64)
    cams = Cameras(cams.world_to_camera.double(), cams.fov.double(), 64)
    v = torch.tensor([[0.0, -0.9, -0.7], [0.2, 0.8, -0.5], [-0.1, -0.2, 0.85]], dtype=torch.float64, requires_grad=True)
    f = torch.tensor([[0, 1, 2]])
    cov = rasterize(Meshes(v, f), cams).coverage
    ndc, _ = cams.project(v)
    px = ndc[0] * 32
    area = 0.5 * ((px[1, 0] - px[0, 0]) * (px[2, 1] - px[0, 1]) - (px[1, 1] - px[0, 1]) * (px[2, 0] - px[0, 0])).abs()
    assert abs(cov.sum() - area) / area < 0.01
    g_cov, = torch.autograd.grad(cov.sum(), v)
    g_area, = torch.autograd.grad(area, v)
    assert (g_cov - g_area).norm() / g_area.norm() < 0.05


def soft_mask_reference_ndc(v, f, cams, sigma=1 / 7000, radius=0.02):
    """DIB-R's soft silhouette with d in NDC, written out directly for one triangle."""
    res = cams.resolution
    ndc, _ = cams.project(v)
    tri = ndc[0, f[0]]
    centres = torch.stack(torch.meshgrid((2 * torch.arange(res) + 1) / res - 1, 1 - (2 * torch.arange(res) + 1) / res, indexing="xy"), -1)
    p = centres.reshape(-1, 2).to(tri)

    def seg(a, b):
        t = ((p - a) @ (b - a) / ((b - a) @ (b - a))).clamp(0, 1)
        return ((p - a - t[:, None] * (b - a)) ** 2).sum(-1)

    d2 = torch.stack([seg(tri[i], tri[(i + 1) % 3]) for i in range(3)]).min(0).values
    soft = torch.where(d2 <= radius ** 2, torch.exp(-d2 / sigma), torch.zeros_like(d2))
    return soft.view(res, res)


def test_soft_width_in_pixels_reproduces_dibr_sigma_at_64_and_keeps_its_width_in_pixels():
    v = torch.tensor([[0.0, -0.9, -0.7], [0.2, 0.8, -0.5], [-0.1, -0.2, 0.85]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2]])
    cams = Cameras.orbit(5.0, 10.0, 20.0, 40.0, 64)
    cams = Cameras(cams.world_to_camera.double(), cams.fov.double(), 64)
    assert abs(DIBR_SOFT_WIDTH_PX - math.sqrt(1 / 7000) * 32) < 1e-12
    frags = rasterize(Meshes(v, f), cams)
    outside = frags.mask[0] == 0
    ref = soft_mask_reference_ndc(v, f, cams)
    assert (frags.soft_mask[0][outside] - ref[outside]).abs().max() < 1e-5  # exp(.) is clamped below 1 - 1e-6
    # the band of 0 < soft < 1 around the outline grows with the outline's length (x4 from 64 to 256 px);
    # a width fixed in NDC would also widen it in pixels (x16)
    band = {}
    for res in (64, 256):
        soft = rasterize(icosphere(3), Cameras.orbit(4.0, 10.0, 20.0, 40.0, res)).soft_mask[0]
        band[res] = ((soft > 0.01) & (soft < 1)).sum().item()
    assert 3.0 < band[256] / band[64] < 8.0, band  # measured 5.4 (the NDC width: 19.6)


def test_renders_expose_coverage_alpha_soft_mask_and_silhouette():
    mesh, cams = icosphere(3), front_camera(res=48, distance=4.0)
    mat = Material(albedo=torch.tensor([[0.6, 0.4, 0.2]]))
    for visibility in ("dibr", "edge_aa"):
        out = Renderer("sg", raster_settings=RasterSettings(visibility=visibility)).render_albedo(mesh, cams, mat)
        frags = out.fragments
        assert torch.equal(out.alpha, frags.coverage) and torch.equal(out.soft_mask, frags.soft_mask)
        assert torch.equal(out.silhouette, frags.coverage if visibility == "edge_aa" else frags.soft_mask)
        rgb = out.rgb[0]
        colour = torch.tensor([0.6, 0.4, 0.2])
        if visibility == "dibr":  # hard RGB, soft mask beside it
            assert torch.allclose(rgb[frags.mask[0] > 0], colour) and rgb[frags.mask[0] == 0].abs().max() == 0
            assert (frags.soft_mask[0] > frags.mask[0]).any()
        else:  # premultiplied by the coverage, uncovered fringe pixels take their neighbour's colour
            assert torch.allclose(rgb, frags.coverage[0, ..., None] * colour, atol=1e-6)
            assert ((frags.mask[0] == 0) & (frags.coverage[0] > 0.05)).any()
            assert torch.equal(frags.soft_mask, frags.mask)  # no soft mask is computed
    with pytest.raises(ValueError):
        RasterSettings(visibility="nvdiffrast")


@pytest.mark.parametrize("visibility", ["dibr", "edge_aa"])
def test_silhouette_gradient_matches_finite_differences(visibility):
    cams = front_camera(res=32)
    cams = Cameras(cams.world_to_camera.double(), cams.fov.double(), 32)
    v0 = torch.tensor([[0.0, -0.9, -0.7], [0.2, 0.8, -0.5], [-0.1, -0.2, 0.85]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2]])
    weights = torch.rand(32, 32, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    # a wide soft mask so that finite differences see a smooth function; the coverage is smooth as it is
    settings = RasterSettings(visibility=visibility, soft_width_px=1.0, soft_radius_px=4.0)

    def loss(v):
        return (rasterize(Meshes(v, f), cams, settings).silhouette[0] * weights).sum()

    v = v0.clone().requires_grad_(True)
    loss(v).backward()
    assert v.grad.abs().min() > 1e-3  # every coordinate moves the silhouette (x: depth, under perspective)
    eps = 1e-6
    for i in range(3):
        for k in range(3):
            dv = torch.zeros_like(v0)
            dv[i, k] = eps
            fd = (loss(v0 + dv) - loss(v0 - dv)) / (2 * eps)
            assert abs(fd - v.grad[i, k]) <= 1e-5 * max(1.0, abs(fd)), (i, k, fd.item(), v.grad[i, k].item())


@pytest.mark.parametrize("visibility", ["dibr", "edge_aa"])
def test_fitting_a_quad_to_a_target_silhouette_converges(visibility):
    cams = front_camera(res=48)
    square = quad(0.0)[0]
    faces = quad(0.0)[1]
    target_verts = square * torch.tensor([1.0, 0.9, 0.6]) + torch.tensor([0.0, 0.25, -0.1])
    target_verts[2] += torch.tensor([0.0, 0.2, 0.15])
    target = rasterize(Meshes(target_verts, faces), cams).coverage
    settings = RasterSettings(visibility=visibility)
    image_plane = (0.7 * square[:, 1:]).requires_grad_(True)
    opt = torch.optim.Adam([image_plane], lr=0.02)
    losses = []
    for _ in range(100):
        verts = torch.cat([torch.zeros(4, 1), image_plane], 1)
        sil = rasterize(Meshes(verts, faces), cams, settings).silhouette
        loss = 1 - (sil * target).sum() / (sil + target - sil * target).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    # measured: the corners land within 0.05 (dibr) / 0.01 (edge_aa) of the target's (~0.4 / 0.1 px)
    assert losses[-1] < 0.3 * losses[0]
    assert (image_plane.detach() - target_verts[:, 1:]).abs().max() < 0.1


def test_edge_aa_image_gradient_moves_the_outline():
    """With edge_aa, an image loss alone (no silhouette term) reaches the outline's vertices."""
    cams = front_camera(res=32)
    v0, f = quad(0.0, 0.8)
    colour = Material(albedo=torch.tensor([[1.0, 1.0, 1.0]]))
    grads = {}
    for visibility in ("dibr", "edge_aa"):
        v = v0.clone().requires_grad_(True)
        out = Renderer("sg", raster_settings=RasterSettings(visibility=visibility)).render_albedo(Meshes(v, f), cams, colour)
        out.rgb.sum().backward()
        grads[visibility] = v.grad
    # a constant colour has no barycentric gradient: only the antialiased outline gives one
    assert grads["dibr"].abs().max() == 0
    g = grads["edge_aa"]
    assert g[0, 1] < 0 and g[1, 1] > 0 and g[0, 2] < 0 and g[2, 2] > 0  # growing the square brightens the image


@pytest.mark.parametrize("visibility,filter_width", [("dibr", 0.0), ("dibr", 1.5), ("edge_aa", 1.5)])
def test_selected_images_render_as_the_same_renders_made_apart(visibility, filter_width):
    """A render shaded under several lights is rasterized once and its images repeated
    (Renderer.gbuffer_of_images): images, silhouettes and gradients as if each repeat had been rendered alone."""
    torch.manual_seed(0)
    sphere = icosphere(2, radius=1.0)
    base = sphere.verts.expand(3, -1, -1) * torch.tensor([[1.0], [0.8], [1.2]]).unsqueeze(-1)
    verts = base.clone().requires_grad_(True)
    cams = Cameras.orbit(torch.tensor([5.0, 6.0, 4.5]), torch.tensor([10.0, 30.0, -20.0]),
                         torch.tensor([0.0, 50.0, 120.0]), 40.0, 24)
    material = Material(albedo=torch.tensor([[0.6, 0.4, 0.3]]), roughness=0.4)
    renderer = Renderer("sg", raster_settings=RasterSettings(visibility=visibility, filter_width=filter_width))
    images = torch.tensor([2, 0, 2, 1, 0])
    light = SGLight(torch.nn.functional.normalize(torch.randn(5, 4, 3), dim=-1), torch.rand(5, 4) * 20 + 1,
                    torch.rand(5, 4, 3))
    frags, g = renderer.gbuffer_of_images(sphere.with_verts(verts), cams, material, images)
    once = renderer.shade(frags, g, light)
    (once.rgb.sum() + once.silhouette.sum()).backward()
    grad_once, verts.grad = verts.grad, None
    apart = renderer(sphere.with_verts(verts[images]), cams[images.tolist()], material, light)
    (apart.rgb.sum() + apart.silhouette.sum()).backward()
    torch.testing.assert_close(once.image, apart.image)
    torch.testing.assert_close(once.silhouette, apart.silhouette)
    torch.testing.assert_close(grad_once, verts.grad)
