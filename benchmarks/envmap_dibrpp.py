"""Table B, the dibrpp side: the env-map optimisation with ``Renderer(MCShader(...))`` and torch Adam.

With ``Task.dibrpp_native`` (default) the shading runs in dibrpp's C++ kernel (only the map needs a gradient);
otherwise in PyTorch through torch.compile, the path this benchmark measured before the kernel existed."""
from __future__ import annotations

import math

import numpy as np
import torch

from benchmarks.envmap_task import ALBEDO, CAMERA, INIT_RADIANCE, ROUGHNESS, SPHERE_SUBDIVISIONS, Task, learning_rate
from dibrpp import Cameras, Material, RasterSettings, Renderer, icosphere
from dibrpp.shading import MCShader
from dibrpp import conventions as conv
from dibrpp.lights import EnvMap


# Only the shaded colour is optimised: no soft silhouette and no anti-aliased alpha (neither changes the RGB
# image), and back faces culled (exact for the closed sphere). Less memory and a faster set-up, the same render.
SHADING_ONLY = RasterSettings(soft=False, filter_width=0.0, cull_backfaces=True)


class DibrppBackend:
    """Env-map optimisation with dibrpp; texels live at Blender's texel centres ((i + .5) / W, (j + .5) / H)."""

    name = "dibrpp"

    def __init__(self, task: Task):
        self.task, self.device = task, torch.device(task.device)
        self.mesh = icosphere(SPHERE_SUBDIVISIONS, device=self.device)
        self.cameras = Cameras.orbit(CAMERA["distance"], CAMERA["elevation_deg"], CAMERA["azimuth_deg"],
                                     CAMERA["fov_deg"], task.resolution, device=self.device)
        self.material = Material(albedo=torch.tensor([ALBEDO], device=self.device), roughness=ROUGHNESS, metallic=1.0)
        self.gbuffer = None  # (Fragments, GBuffer), built by the first render

    def texel_directions(self) -> torch.Tensor:
        return conv.equirect_directions(self.task.env_height, self.task.env_width)

    def render(self, env: torch.Tensor, spp: int, seed: int | None = None, grad_seed: int | None = None) -> torch.Tensor:
        # torch.compile of the MC path takes minutes on CUDA (its first iteration did not end in 110 s): eager there
        shader = MCShader(spp=spp, mis=True, seed=seed, compile=self.device.type == "cpu", grad_seed=grad_seed,
                          native=self.task.dibrpp_native)
        renderer = Renderer(shader, raster_settings=SHADING_ONLY)
        if self.gbuffer is None:  # only the light is optimised: rasterize once, as Mitsuba builds its BVH once
            with torch.no_grad():
                self.gbuffer = renderer.gbuffer(self.mesh, self.cameras, self.material)
        return renderer.shade(*self.gbuffer, EnvMap(env.unsqueeze(0))).rgb[0]

    def render_still(self, env: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """A map (H, W, 3) on this renderer's texel grid rendered without gradients."""
        with torch.no_grad():
            return self.render(torch.from_numpy(env).to(self.device), spp, seed).cpu().numpy()

    def start(self, ref: np.ndarray) -> None:
        """Fresh grey log-texels and optimiser."""
        self.ref = torch.from_numpy(ref).to(self.device)
        shape = (self.task.env_height, self.task.env_width, 3)
        self.log_env = torch.full(shape, math.log(INIT_RADIANCE), device=self.device, requires_grad=True)
        self.opt = torch.optim.Adam([self.log_env], lr=self.task.lr)

    def step(self, it: int) -> float:
        self.opt.param_groups[0]["lr"] = learning_rate(self.task, it)
        self.opt.zero_grad(set_to_none=True)
        env = self.log_env.exp()
        if self.task.dibrpp_gradient == "correlated":
            # the residual and d image / d env share their samples: E[gradient] also minimises the render's
            # variance, which pulls the optimum towards a blurred sun
            loss = (self.render(env, self.task.spp) - self.ref).square().mean()
            loss.backward()
        else:
            # one render whose backward replays independent samples (grad_seed): residual times an independent
            # estimate's gradient is an unbiased gradient of |E[image] - ref|^2, as Mitsuba's prb with its
            # seed / seed_grad
            grad_seed = int(torch.randint(0, 2 ** 62, (1,)))
            image = self.render(env, self.task.spp, grad_seed=grad_seed)
            residual = image.detach() - self.ref
            loss = residual.square().mean()
            (2 * residual * image).mean().backward()
        self.opt.step()
        return loss.item()

    def native_envmap(self) -> np.ndarray:
        return self.log_env.detach().exp().cpu().numpy()

    envmap = native_envmap  # already on Blender's grid
