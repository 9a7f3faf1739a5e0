"""Rendering: Eq. 1 compositing, ray samplers, the volume renderer."""

from __future__ import annotations

from nerfart_plugin.rendering.renderer import VolumeRenderer
from nerfart_plugin.rendering.samplers import (occupancy_samples, ray_aabb, stratified_edges, stratified_samples,
    weighted_samples)
from nerfart_plugin.rendering.volume import ALPHA_T_EPS, volume_weights, weights_from_alpha

__all__ = [
    "volume_weights", "weights_from_alpha", "ALPHA_T_EPS",
    "stratified_edges", "stratified_samples", "occupancy_samples", "weighted_samples", "ray_aabb",
    "VolumeRenderer",
]
