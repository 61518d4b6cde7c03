"""The object as a light probe: the light head reads the input through the predicted geometry.

A glossy or metallic surface shows, at each pixel, the light arriving from the mirror direction of the view
about its normal, r = 2(n.v)n - v (Rematas et al., DeepReflectanceMaps, CVPR 2016; Georgoulis et al., TPAMI
2018); a diffuse one shows the light integrated about n. :func:`pixel_samples` rasterises the predicted surface
in the input view (its normal and view direction at each covered pixel, with what the input shows there) and
:func:`probe_grid` scatters those into an equirect grid at r (the mirror cue) and at n (the diffuse cue), with a
coverage channel each. The pixel -> light-direction mapping is geometry, so the network does not have to
learn it from a few dozen env maps; :class:`ProbeLightHead` is a small CNN on that grid (wrap-around in azimuth)
joined with the global code, whose output starts as the projected map itself (its last layer is zero).

The grid is in the **probe frame**: the input camera's frame turned so that the camera's up is the grid's pole
(+Z) and its viewing direction the grid's centre (+X). The datasets' cameras look at the object from a fixed
elevation, so sky and ground are rows of this grid, and a conv's translation along azimuth is a turn about up.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from dibrpp import conventions as conventions
from dibrpp.brdf import Material
from dibrpp.camera import Cameras
from dibrpp.mesh import Meshes
from dibrpp.raster import RasterSettings, rasterize
from dibrpp.renderer import build_gbuffer
from dibrpp.sg import sg_integral

# camera (x right, y up, z back) -> probe frame (X forward = -z, Y left = -x, Z up = y); a rotation (det +1)
CAMERA_TO_PROBE = ((0.0, 0.0, -1.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
LOG_EPS = 1e-3  # radiance floor of the grid's log (an 8-bit input's darkest step is ~3e-4 linear)
BLUR_CELLS = 1.0  # std. dev. of the Gaussian that spreads each sample over the grid, in cells
# the sun is read off the pixels that face the camera at least this much (n.v); grazing ones, at the silhouette,
# mirror the direction straight behind the object through the least sure normals
FACING_MIN = 0.3
# the cue's radiance within this angle of the sun's axis is the sun's (metrics.dominant_direction's cone), and the
# horizon's softness (in sin elevation) below which the sun's prior falls off
SUN_CONE_DEG = 20.0
SUN_BROADEST = 0.5  # the sun lobe's least sharpness: as broad as a hemisphere
HORIZON_SOFTNESS = 0.05
# MC's probe sun: its light's grid is this many times finer than the probe grid (64 x 128, 2.8 degree cells), so that
# a sun trained as a sharp SG lobe is not spread over 11 degree cells
SUN_GRID_SCALE = 4
# light_colour sky-ground: the horizon's softness (in sin elevation) between the sky's colour and the ground's
SKY_GROUND_SOFTNESS = 0.1


def camera_to_probe(device=None, dtype=torch.float32) -> torch.Tensor:
    return torch.tensor(CAMERA_TO_PROBE, device=device, dtype=dtype)


def world_to_probe(world_to_camera: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) rotations from the world to each view's probe frame (world_to_camera (B, 4, 4) or (B, 3, 3))."""
    return camera_to_probe(world_to_camera.device, world_to_camera.dtype) @ world_to_camera[:, :3, :3]


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W) grids: wrap-around in azimuth, clamped at the poles."""
    r = max(1, math.ceil(2 * sigma))
    t = torch.arange(-r, r + 1, device=x.device, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="circular"), k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def scatter_to_grid(dirs: torch.Tensor, values: torch.Tensor, weight: torch.Tensor, height: int,
                    width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted mean of ``values`` (B, N, C) at directions ``dirs`` (B, N, 3) per equirect cell, blurred by
    BLUR_CELLS: ((B, C, H, W) mean, (B, 1, H, W) the weight that reached each cell, relative to the mean)."""
    b, n, c = values.shape
    uv = conventions.direction_to_equirect_uv(dirs)
    col = (uv[..., 0] * width).long().clamp(0, width - 1)
    row = (uv[..., 1] * height).long().clamp(0, height - 1)
    cell = (row * width + col) + torch.arange(b, device=dirs.device).unsqueeze(1) * (height * width)
    sums = values.new_zeros(b * height * width, c + 1)
    sums.index_add_(0, cell.reshape(-1), torch.cat([values * weight.unsqueeze(-1), weight.unsqueeze(-1)], -1).reshape(-1, c + 1))
    sums = _blur(sums.view(b, height, width, c + 1).permute(0, 3, 1, 2), BLUR_CELLS)
    total = sums[:, c:]
    mean_weight = total.mean((2, 3), keepdim=True).clamp_min(1e-8)
    return sums[:, :c] / total.clamp_min(1e-6 * mean_weight), total / mean_weight


# hard coverage only (the probe reads covered pixels), and the template is closed and wound outwards
_PROBE_RASTER = RasterSettings(soft=False, filter_width=0.0, cull_backfaces=True)


def pixel_samples(meshes: Meshes, cameras: Cameras, radiance: torch.Tensor,
                  alpha: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The predicted surface as the input view shows it, per pixel (dense, (B, H*W, ...), H = W the cameras'
    resolution): world-frame unit normals (the renderer's G-buffer's shading normals) and directions to the
    camera, the input's linear ``radiance`` (B, H, W, 3) there, and a weight (the input's ``alpha`` (B, H, W)
    on the pixels the surface covers, else 0)."""
    res = cameras.resolution
    if radiance.shape[1:3] != (res, res) or alpha.shape[1:] != (res, res):
        raise ValueError(f"the input view is {tuple(radiance.shape[1:3])} pixels, its cameras {res} x {res}")
    meshes = meshes.expand(len(cameras))
    frags = rasterize(meshes, cameras, _PROBE_RASTER)
    point = build_gbuffer(meshes, cameras, Material(albedo=radiance.new_ones(1, 3)), frags).point
    b = len(cameras)
    up = point.normal.new_tensor([0.0, 0.0, 1.0])  # any unit vector where nothing is covered (weight 0)
    dense = lambda packed: up.expand(b * res * res, 3).index_copy(0, frags.pix, packed).view(b, res * res, 3)  # noqa: E731
    weight = frags.mask.reshape(b, -1) * alpha.reshape(b, -1).clamp(0, 1)
    return dense(point.normal), dense(point.view), radiance.reshape(b, -1, 3), weight


def mirror_directions(normals: torch.Tensor, to_camera: torch.Tensor) -> torch.Tensor:
    """Unit directions r = 2(n.v)n - v from which a mirror at normals n shows light to the camera (v: to it)."""
    return F.normalize(2 * (normals * to_camera).sum(-1, keepdim=True) * normals - to_camera, dim=-1, eps=1e-12)


def probe_grid(normals: torch.Tensor, to_camera: torch.Tensor, seen: torch.Tensor, weight: torch.Tensor,
               world_to_camera: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B, 8, H, W) probe-frame grid: mirror-cue radiance (3) and coverage (1), diffuse-cue radiance (3) and
    coverage (1). normals, to_camera (B, N, 3) world-frame unit vectors of N surface points; seen (B, N, 3) the
    linear radiance the input shows there; weight (B, N) how much each point counts (0: not seen)."""
    rot = world_to_probe(world_to_camera.to(normals.dtype))
    mirror = mirror_directions(normals, to_camera)
    to_probe = lambda d: d @ rot.mT  # noqa: E731 (row vectors)
    mirror_mean, mirror_cover = scatter_to_grid(to_probe(mirror), seen, weight, height, width)
    normal_mean, normal_cover = scatter_to_grid(to_probe(normals), seen, weight, height, width)
    return torch.cat([mirror_mean, mirror_cover, normal_mean, normal_cover], 1)


def facing_mirror_cue(normals: torch.Tensor, to_camera: torch.Tensor, seen: torch.Tensor, weight: torch.Tensor,
                      world_to_camera: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B, 4, H, W) the mirror cue (radiance, coverage) of :func:`probe_grid` from the points that face the camera
    at least FACING_MIN (n.v) only."""
    facing = (normals * to_camera).sum(-1) >= FACING_MIN
    mirror = mirror_directions(normals, to_camera) @ world_to_probe(world_to_camera.to(normals.dtype)).mT
    return torch.cat(scatter_to_grid(mirror, seen, weight * facing, height, width), 1)


def compress_radiance(grid: torch.Tensor) -> torch.Tensor:
    """The grid as the head's CNN reads it: radiance linear up to 1 (all a clipped input holds), logarithmic above
    (1 + ln x), so a full-range input's sun reflection (~1e4) enters as ~10; coverage channels as they are."""
    radiance = grid[:, [0, 1, 2, 4, 5, 6]]
    radiance = torch.where(radiance > 1, 1 + torch.log(radiance.clamp_min(1.0)), radiance)
    return torch.cat([radiance[:, :3], grid[:, 3:4], radiance[:, 3:], grid[:, 7:8]], 1)


def cue_sun_power(grid: torch.Tensor, axis: torch.Tensor, cell_dirs: torch.Tensor,
                  solid_angle: torch.Tensor) -> torch.Tensor:
    """(B, 3) the power the mirror cue of ``grid`` (B, C >= 4, H, W: its radiance and coverage first, as in
    :func:`probe_grid`) shows within SUN_CONE_DEG of ``axis`` (B, 3)
    above the sky's level (the median of its covered cells): the least light a reflector (which returns at most
    what reaches it) needs there. cell_dirs (H*W, 3) and solid_angle (H*W,) of the grid's cells, same frame."""
    rgb, covered = grid[:, :3].flatten(2), grid[:, 3].flatten(1) > 0.05
    sky = torch.nanmedian(rgb.masked_fill(~covered.unsqueeze(1), float("nan")), -1).values.nan_to_num(0.0)
    near = (axis @ cell_dirs.T) >= math.cos(math.radians(SUN_CONE_DEG))
    return ((rgb - sky.unsqueeze(-1)).clamp_min(0) * (covered & near).unsqueeze(1) * solid_angle).sum(-1)


def fibonacci_axes(k: int) -> torch.Tensor:
    """(k, 3) directions spread evenly over the sphere."""
    i = torch.arange(k, dtype=torch.float32) + 0.5
    z = 1 - 2 * i / k
    phi = math.pi * (1 + 5 ** 0.5) * i
    return torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)


def sample_grid(grid: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear values of (B, C, H, W) equirect grids at directions (K, 3), or (B, K, 3) per grid, -> (B, K, C)."""
    uv = conventions.direction_to_equirect_uv(dirs)
    xy = (2 * uv - 1).view(-1, 1, uv.shape[-2], 2).expand(grid.shape[0], -1, -1, -1)
    return F.grid_sample(grid, xy.to(grid), align_corners=False, padding_mode="border")[:, :, 0].permute(0, 2, 1)


def sg_on_grid(axis: torch.Tensor, sharpness: torch.Tensor, amplitude: torch.Tensor,
               cell_dirs: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) radiance of an equirect grid holding one SG lobe per image (unit ``axis`` (B, 3), ``sharpness``
    (B, 1), ``amplitude`` (B, 3)): the lobe at the cells' centres ``cell_dirs`` (1, 3, H, W), scaled so that the
    grid's integral is the lobe's (a lobe narrower than a cell is not lost between the centres)."""
    h, w = cell_dirs.shape[2:]
    cells = cell_dirs.flatten(2)[0].T  # (H*W, 3)
    solid = conventions.equirect_solid_angles(h, w, cells.device, cells.dtype).expand(-1, w).flatten()
    lobe = torch.exp(sharpness * (axis @ cells.T - 1))  # (B, H*W)
    lobe = lobe * sg_integral(sharpness[:, 0]).unsqueeze(-1) / (lobe * solid).sum(-1, keepdim=True).clamp_min(1e-30)
    return (amplitude.unsqueeze(-1) * lobe.unsqueeze(1)).view(-1, 3, h, w)


class ProbeLightHead(nn.Module):
    """Light from the probe grid and the global code, in the probe frame: SG lobes (``kind="sg"``) or MC's env grid
    (``kind="env"``), each a sky and a sun.

    - **Features** (:meth:`features`): a small CNN on the grid (wrap-around in azimuth), its middle layer scaled and
      shifted by the global code; its last layer starts at zero, so the light starts as the projected cue.
    - **Sky** (:meth:`sky`): K - 1 lobes at fixed, evenly spread axes whose amplitudes are the refined log map sampled
      there (the sky, the ground, walls).
    - **Sun** (:meth:`place_sun`): a distribution over the grid's cells, starting at the mirror cue's brightest region
      (the cue read off the pixels that face the camera), shifted on paint by a learnt residual (a metal's cue is the
      light's picture; paint adds its diffuse shading), above the horizon; its soft arg-max is the sun's axis, the
      features there give its sharpness and intensity.
    - SG (:meth:`sg_light`): the sky's lobes, the sun's, and on metal a K+1-th lobe on the sun's axis carrying what
      the cue shows near it above the head's own sun (:func:`cue_sun_power`; training shades it on a held surface),
      so that the image loss cannot switch the sun off. MC (:meth:`env_light`): the same sky and sun on MC's grid,
      also returned apart (training shades the sun's lobe in closed form).
    """

    def __init__(self, kind: str, lobes: int, height: int, width: int, max_sharpness: float,
                 max_log_radiance: float, code: int = 512, channels: int = 32, sky_ground: bool = False):
        super().__init__()
        if kind not in ("env", "sg"):
            raise ValueError(f"the probe light head predicts env maps (mc) or SG lobes (sg, sh-sg), not {kind!r}")
        if lobes < 2:
            raise ValueError(f"the probe light head needs at least 2 SG lobes (sky and sun), got {lobes}")
        self.kind, self.lobes, self.height, self.width = kind, lobes, height, width
        self.max_sharpness, self.max_log_radiance = max_sharpness, max_log_radiance
        cin = 8 + 3  # the grid and each cell's direction
        self.inp = nn.Conv2d(cin, channels, 3)
        self.film = nn.Linear(code, 2 * channels)  # the global code scales and shifts the features
        self.mid = nn.Conv2d(channels, channels, 3)
        self.out = nn.Conv2d(channels, 4, 3)  # log-radiance residual (3), sun logit residual (1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        nn.init.zeros_(self.film.weight)
        nn.init.zeros_(self.film.bias)
        self.register_buffer("cell_dirs", conventions.equirect_directions(height, width).permute(2, 0, 1)[None])
        # the sun's prior over cells: their solid angles (not saved: derived from the grid's size)
        self.register_buffer("cell_log_solid_angle", conventions.equirect_solid_angles(height, width).expand(
            -1, width).flatten().log(), persistent=False)
        self.log_gain = nn.Parameter(torch.zeros(()))
        self.register_buffer("axes", fibonacci_axes(lobes - 1))
        if kind == "env":  # MC's light's grid (not saved: derived from the probe grid's size)
            self.register_buffer("fine_cell_dirs", conventions.equirect_directions(
                SUN_GRID_SCALE * height, SUN_GRID_SCALE * width).permute(2, 0, 1)[None], persistent=False)
        self.log_sharpness = nn.Parameter(torch.tensor(math.log(max(2.0, 2 * lobes ** 0.5))))
        self.sun_temperature = nn.Parameter(torch.tensor(4.0))  # sun logits = t * log luminance + residual
        self.sun = nn.Linear(channels + code, 4)  # sun sharpness and rgb intensity (log, relative)
        nn.init.zeros_(self.sun.weight)
        with torch.no_grad():
            self.sun.bias.copy_(torch.tensor([math.log(100.0), 3.0, 3.0, 3.0]))  # a sharp lobe ~20x the sky
        self.sky_ground = None
        if sky_ground:  # its own draws (zeroed anyway): every other weight starts as white light alone's
            with torch.random.fork_rng(devices=[]):
                self.sky_ground = nn.Linear(code, 6)  # log colour of the sky and of the ground, beside the cue's
            nn.init.zeros_(self.sky_ground.weight)
            nn.init.zeros_(self.sky_ground.bias)

    def _conv(self, layer: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
        return layer(F.pad(F.pad(x, (1, 1, 0, 0), mode="circular"), (0, 0, 1, 1), mode="replicate"))

    def features(self, grid: torch.Tensor, code: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, H, W) features of the grid, and the (B, 4, H, W) residuals: log radiance (3), sun logit (1)."""
        b = grid.shape[0]
        x = torch.cat([compress_radiance(grid), self.cell_dirs.expand(b, -1, -1, -1)], 1)
        h = F.leaky_relu(self._conv(self.inp, x), 0.2)
        scale, shift = self.film(code).view(b, 2, -1, 1, 1).unbind(1)
        h = F.leaky_relu(self._conv(self.mid, h * (1 + scale) + shift), 0.2)
        return h, self._conv(self.out, h)

    def sky(self, grid: torch.Tensor, residual: torch.Tensor, code: torch.Tensor,
            probe_to_world: torch.Tensor) -> torch.Tensor:
        """(B, K-1, 3) the sky lobes' amplitudes: the mirror cue's luminance (on glossy paint the cue's colour is
        mostly the paint's), refined by the residual (and with ``sky_ground``, tinted by the sky's and the ground's
        colours), sampled at the fixed axes."""
        cue = grid[:, :3].mean(1, keepdim=True)
        log_map = torch.log(cue + LOG_EPS) + residual[:, :3] + self.log_gain
        if self.sky_ground is not None:
            log_map = log_map + self.hemisphere_colour(grid, code, probe_to_world)
        return torch.exp(sample_grid(log_map, self.axes).clamp_max(self.max_log_radiance))

    def hemisphere_colour(self, grid: torch.Tensor, code: torch.Tensor, probe_to_world: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) log colour (mean 0 over RGB) of the sky above the world's horizon and of the ground below it.
        Read off the mirror cue: the ratio of its colour above to its colour below, which the paint's colour, common
        to both, divides out (half of it to each side), shifted by what the global code adds."""
        up = probe_to_world[:, 2]  # the world's up in the probe frame (B, 3)
        above = torch.sigmoid(torch.einsum("bc,chw->bhw", up, self.cell_dirs[0]) / SKY_GROUND_SOFTNESS).unsqueeze(1)
        seen = grid[:, 3:4]

        def log_chroma(weight: torch.Tensor) -> torch.Tensor:  # (B, 3) the cue's mean colour under weight, as log chroma
            mean = (grid[:, :3] * seen * weight).sum((2, 3)) / (seen * weight).sum((2, 3)).clamp_min(1e-6)
            log = torch.log(mean + LOG_EPS)
            return log - log.mean(-1, keepdim=True)

        half = 0.5 * (log_chroma(above) - log_chroma(1 - above))
        shift = self.sky_ground(code).view(-1, 2, 3)
        shift = shift - shift.mean(-1, keepdim=True)
        sky, ground = (half + shift[:, 0]), (-half + shift[:, 1])
        return above * sky[..., None, None] + (1 - above) * ground[..., None, None]

    def place_sun(self, sun_grid: torch.Tensor, residual: torch.Tensor, h: torch.Tensor, code: torch.Tensor,
            probe_to_world: torch.Tensor, metal: torch.Tensor, sky: torch.Tensor) -> tuple:
        """The sun: its axis (B, 3), its distribution over cells as log-probabilities (B, H*W), its sharpness (B, 1)
        and amplitude (B, 3) from the features where it is, relative to the sky's mean (B, 3)."""
        luminance = sun_grid[:, :3].mean(1, keepdim=True)
        shift = residual[:, 3:] * (1 - metal.detach()).view(-1, 1, 1, 1)  # a metal's cue stays where it shows
        logits = (self.sun_temperature * torch.log(luminance + LOG_EPS) + shift).flatten(1)
        cells = self.cell_dirs.flatten(2)[0].T  # (H*W, 3), probe frame
        # above the horizon: the world's up in the probe frame
        logits = logits + F.logsigmoid(cells @ probe_to_world[:, 2].T / HORIZON_SOFTNESS).T
        p = torch.softmax(logits + self.cell_log_solid_angle, -1)  # a distribution over cells
        log_p = torch.log_softmax(logits + self.cell_log_solid_angle, -1)  # (p.log() would underflow to -inf)
        axis = F.normalize(p @ cells, dim=-1, eps=1e-6)
        pooled = (h.flatten(2) * p.unsqueeze(1)).sum(-1)  # features where the sun is
        raw = self.sun(torch.cat([pooled, code], -1))
        sharpness = raw[:, :1].exp().clamp(SUN_BROADEST, self.max_sharpness)
        amplitude = torch.exp((raw[:, 1:] + sky.log()).clamp_max(self.max_log_radiance))
        return axis, log_p, sharpness, amplitude

    def forward(self, grid: torch.Tensor, code: torch.Tensor, probe_to_world: torch.Tensor, metal: torch.Tensor,
                sun_grid: torch.Tensor | None = None) -> dict:
        """grid (B, 8, H, W) from :func:`probe_grid`; code (B, C) the global code; probe_to_world (B, 3, 3) the
        rotation from the probe frame to the world's (the sun's horizon); metal (B,) how metallic each view's
        surface is predicted; sun_grid (B, 4, H, W) the mirror cue the sun is read off (the model's: the facing
        pixels', :func:`facing_mirror_cue`; default: ``grid``'s own)."""
        sun_grid = grid[:, :4] if sun_grid is None else sun_grid
        h, residual = self.features(grid, code)
        sky = self.sky(grid, residual, code, probe_to_world)
        sun = self.place_sun(sun_grid, residual, h, code, probe_to_world, metal, sky.mean(1))
        return self.env_light(sky, *sun) if self.kind == "env" else self.sg_light(sky, *sun, sun_grid, metal)

    def sg_light(self, sky: torch.Tensor, axis: torch.Tensor, log_p: torch.Tensor, sharpness: torch.Tensor,
                 amplitude: torch.Tensor, sun_grid: torch.Tensor, metal: torch.Tensor) -> dict:
        """SG lobes: the sky's, the sun's, and the sun's floor on metal (what the cue adds to the head's sun)."""
        b, k = sky.shape[0], self.lobes - 1
        cells = self.cell_dirs.flatten(2)[0].T
        power = cue_sun_power(sun_grid.detach(), axis.detach(), cells, self.cell_log_solid_angle.exp())
        # a metal shows only what it reflects, so its cue is a bound on the sun; paint adds its diffuse shading
        # to the cue (on glossy cars the bound would give the sun ~80 % of the light's power)
        floor = metal.detach().view(-1, 1) * power / sg_integral(sharpness.detach())
        suns = torch.stack([amplitude, (floor - amplitude).clamp_min(0)], 1)  # a second lobe, same axis and size
        return {"axis": torch.cat([self.axes.expand(b, k, 3), axis.unsqueeze(1).expand(b, 2, 3)], 1),
                "sharpness": torch.cat([self.log_sharpness.exp().expand(b, k), sharpness.expand(b, 2)], 1),
                "amplitude": torch.cat([sky, suns], 1), "sun_log_p": log_p}

    def env_light(self, sky: torch.Tensor, axis: torch.Tensor, log_p: torch.Tensor, sharpness: torch.Tensor,
                  amplitude: torch.Tensor) -> dict:
        """MC's light: SG's sky and sun on a grid, so that only the sun can be compact. "image" is the light (what
        predict writes, what evaluate scores), on a grid SUN_GRID_SCALE times finer than the probe's so that the
        sun keeps about its lobe's size; training shades "sky" by MC and the sun's SG lobe in closed form
        (Prediction.sky_and_sun)."""
        sun = sg_on_grid(axis, sharpness, amplitude, self.fine_cell_dirs)
        clamp = lambda image: image.clamp_max(math.exp(self.max_log_radiance)).permute(0, 2, 3, 1)  # noqa: E731
        return {"image": clamp(self.sky_on_grid(sky, self.fine_cell_dirs) + sun),
                "sky": clamp(self.sky_on_grid(sky, self.cell_dirs)), "sun_axis": axis,
                "sun_sharpness": sharpness, "sun_amplitude": amplitude, "sun_log_p": log_p}

    def sky_on_grid(self, amplitude: torch.Tensor, cell_dirs: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) MC's grid of an SG sky: amplitudes (B, K-1, 3) at the fixed axes, evaluated at the cells of
        ``cell_dirs`` (1, 3, H, W). The sun's lobe is added to it (:func:`sg_on_grid`); on a free grid the sky
        held the highlights itself, at the raw cue's brightest cell, and the loss left the sun 3 % of the power."""
        cells = cell_dirs.flatten(2)[0].T  # (H*W, 3)
        lobes = torch.exp(self.log_sharpness.exp() * (cells @ self.axes.T - 1))  # (H*W, K-1)
        return torch.einsum("nk,bkc->bcn", lobes, amplitude).view(-1, 3, *cell_dirs.shape[2:])

    # how many of the last SG lobes are the sun: its own, and what the cue adds to it
    sun_lobes = 2
