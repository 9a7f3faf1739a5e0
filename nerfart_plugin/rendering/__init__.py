"""Rendering: Eq. 1 volume-rendering primitives, ray samplers, the volume renderer."""

from __future__ import annotations

from nerfart_plugin.rendering.volume import (  # noqa: I001  (volume first: fields import it)
    ALPHA_T_EPS, NEUS_EPS, neus_alpha, neus_alpha_sections, volsdf_density, volume_weights, weights_from_alpha,
)
from nerfart_plugin.rendering.samplers import (
    occupancy_samples, ray_aabb, stratified_edges, stratified_samples, weighted_samples,
)
from nerfart_plugin.rendering.renderer import VolumeRenderer

__all__ = [
    "volume_weights", "weights_from_alpha", "volsdf_density", "neus_alpha", "neus_alpha_sections", "ALPHA_T_EPS", "NEUS_EPS",
    "stratified_edges", "stratified_samples", "occupancy_samples", "weighted_samples", "ray_aabb",
    "VolumeRenderer",
]
