"""Appearance: what surfaces and lights look like, as plain data the renderer reads (numpy; no Warp kernel): materials
sampled and resolved from a seed, lights, image textures and procedural natural images."""

from flowsynth.appearance.lights import Light, resolve_lights, sample_lights
from flowsynth.appearance.materials import check_texture_families, resolve_material, sample_material
from flowsynth.appearance.textures import list_textures, mip_pyramid, natural_image, srgb_to_linear

__all__ = [
    "Light",
    "check_texture_families",
    "list_textures",
    "mip_pyramid",
    "natural_image",
    "resolve_lights",
    "resolve_material",
    "sample_lights",
    "sample_material",
    "srgb_to_linear",
]
