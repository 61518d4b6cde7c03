"""How Cycles renders: :class:`RenderSettings` (image size, samples, light paths, pixel filter, film, denoiser,
device) and :func:`configure_render`, which applies them to any bpy scene."""
from __future__ import annotations

from dataclasses import dataclass

from .blender import bpy_module


@dataclass
class RenderSettings:
    """How Cycles renders: image size, samples, light paths, pixel filter, film and device.

    ``resolution`` is the image height (and width, unless ``width`` is set: panoramas are 2:1).
    ``max_bounces`` bounds every kind of bounce (total, diffuse, glossy, transmission).
    ``filter_width`` is the Blackman-Harris pixel filter's width in pixels (0.01 = pixel centres).
    ``clamp_indirect``: Cycles' indirect sample clamp (0 = unclamped, the unbiased truth).
    ``adaptive_threshold`` > 0 turns on Cycles' adaptive sampling (noise threshold; ``spp`` is then the
    maximum, ``adaptive_min_samples`` the minimum, 0 = automatic). ``denoise`` runs OpenImageDenoise on
    the shaded render with albedo and normal guides (never on the albedo render).
    ``threads`` = 0 lets Cycles use every core. ``albedo_aov`` adds the albedo render to :func:`render`.
    """

    resolution: int = 64
    spp: int = 64
    seed: int = 0
    max_bounces: int = 1
    filter_width: float = 1.5
    film_transparent: bool = True
    width: int | None = None
    clamp_indirect: float = 0.0
    adaptive_threshold: float = 0.0
    adaptive_min_samples: int = 0
    denoise: bool = False
    device: str = "CPU"
    threads: int = 0
    albedo_aov: bool = False

    def validate(self) -> None:
        if int(self.resolution) <= 0 or (self.width is not None and int(self.width) <= 0):
            raise ValueError(f"resolution must be a positive number of pixels, got {self.resolution}"
                             + (f" x {self.width}" if self.width is not None else ""))
        if int(self.spp) <= 0:
            raise ValueError(f"spp must be positive, got {self.spp}")
        if int(self.max_bounces) < 0:
            raise ValueError(f"max_bounces must be >= 0, got {self.max_bounces}")
        if not 0.01 <= float(self.filter_width) <= 10.0:
            raise ValueError(f"filter_width must be in [0.01, 10] pixels (Cycles' range), got {self.filter_width}")
        if self.device not in ("CPU", "GPU"):
            raise ValueError(f"device must be 'CPU' or 'GPU', got {self.device!r}")
        if float(self.adaptive_threshold) < 0 or int(self.adaptive_min_samples) < 0:
            raise ValueError("adaptive_threshold and adaptive_min_samples must be >= 0")
        if float(self.clamp_indirect) < 0:
            raise ValueError(f"clamp_indirect must be >= 0 (0 = off), got {self.clamp_indirect}")


def configure_render(scene, settings: RenderSettings) -> None:
    """Apply ``settings`` to a bpy scene: Cycles on CPU (or GPU), fixed seed, Blackman-Harris filter, no
    light tree / guiding / caustic tricks, Standard view transform (linear output), 32-bit multilayer EXR
    output. Works on any scene (the one :func:`build_scene` makes, or one built by hand with bpy)."""
    settings.validate()
    _configure_image(scene.render, settings)
    _configure_sampling(scene.cycles, settings)
    _configure_light_paths(scene.cycles, settings)
    _configure_colour_and_output(scene)
    if settings.device == "GPU":
        _enable_gpu()


def _configure_image(r, st: RenderSettings) -> None:
    """Image size, film, threads; nothing but the render itself (no compositor, no sequencer)."""
    r.engine = "CYCLES"
    r.resolution_x = r.resolution_y = int(st.resolution)
    if st.width is not None:
        r.resolution_x = int(st.width)
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = bool(st.film_transparent)
    r.use_persistent_data = True  # keep the BVH/images between the views of one scene
    r.use_compositing = False
    r.use_sequencer = False
    r.threads_mode = "FIXED" if st.threads else "AUTO"
    if st.threads:
        r.threads = int(st.threads)


def _configure_sampling(c, st: RenderSettings) -> None:
    """Device, samples (fixed or adaptive), denoiser, seed and pixel filter."""
    c.device = st.device
    c.samples = int(st.spp)
    c.use_adaptive_sampling = float(st.adaptive_threshold) > 0
    if c.use_adaptive_sampling:
        c.adaptive_threshold = float(st.adaptive_threshold)
        c.adaptive_min_samples = int(st.adaptive_min_samples)
    c.use_denoising = bool(st.denoise)
    if st.denoise:
        c.denoiser = "OPENIMAGEDENOISE"
        c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        c.denoising_prefilter = "ACCURATE"
        c.denoising_quality = "HIGH"
    c.use_light_tree = False
    c.use_guiding = False
    c.seed = int(st.seed)
    c.use_animated_seed = False
    c.pixel_filter_type = "BLACKMAN_HARRIS"
    c.filter_width = float(st.filter_width)


def _configure_light_paths(c, st: RenderSettings) -> None:
    """Bounces, clamping and culling: every shortcut off, so the render is the unbiased truth."""
    c.max_bounces = int(st.max_bounces)
    c.diffuse_bounces = int(st.max_bounces)
    c.glossy_bounces = int(st.max_bounces)
    c.transmission_bounces = int(st.max_bounces)
    c.volume_bounces = 0
    c.transparent_max_bounces = 8
    c.blur_glossy = 0.0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = float(st.clamp_indirect)
    c.use_fast_gi = False
    c.use_camera_cull = False
    c.use_distance_cull = False
    c.texture_limit_render = "OFF"


def _configure_colour_and_output(scene) -> None:
    """Standard view transform (Blender's default AgX changes colours) and 32-bit multilayer EXR output."""
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = False
    im = scene.render.image_settings
    im.media_type = "MULTI_LAYER_IMAGE"
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"
    im.exr_codec = "NONE"


def gpu_backend() -> str | None:
    """The first GPU backend Cycles finds devices of (OptiX, CUDA, HIP, Metal, oneAPI), with its devices
    enabled; None where there is none."""
    bpy = bpy_module()
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for backend in ("OPTIX", "CUDA", "HIP", "METAL", "ONEAPI"):
        try:
            prefs.compute_device_type = backend
        except TypeError:
            continue
        prefs.get_devices()
        gpus = [d for d in prefs.devices if d.type == backend]
        if gpus:
            for d in prefs.devices:
                d.use = d.type == backend
            return backend
    return None


def _enable_gpu():
    if gpu_backend() is None:
        raise RuntimeError("device='GPU' but Cycles found no GPU backend; use device='CPU'")
