"""dibrpp: a hybrid differentiable renderer (DIB-R rasterization + MC / SG / SH shading), after DIB-R++."""
from .brdf import BRDFOptions, Material
from .camera import Cameras
from .lights import EnvMap, Light, SGLight, SHLight
from .mesh import Meshes, icosphere
from .raster import Fragments, RasterSettings, rasterize
from .renderer import Renderer, RenderOutput

__all__ = ["BRDFOptions", "Cameras", "EnvMap", "Fragments", "Light", "Material", "Meshes", "RasterSettings", "Renderer",
           "RenderOutput", "SGLight", "SHLight", "icosphere", "rasterize"]
__version__ = "0.1.0"
