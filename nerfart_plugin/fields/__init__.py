"""Fields: encodings, backbones (nerf | volsdf | neus), background model, occupancy grid.

Importing this package registers the ``encoding`` and ``backbone`` components.
"""

from __future__ import annotations

from typing import Any

from nerfart_plugin.config import registry
from nerfart_plugin.config.sections import typed_section
from nerfart_plugin.fields import encodings, nerf, neus, volsdf  # noqa: F401  (registration)
from nerfart_plugin.fields.background import EnvironmentMap, build_background
from nerfart_plugin.fields.encodings import build_encoding
from nerfart_plugin.fields.field import Field
from nerfart_plugin.fields.nerf import NeRFField
from nerfart_plugin.fields.neural import NeuralField
from nerfart_plugin.fields.neus import NeuSField
from nerfart_plugin.fields.occupancy import OccupancyGrid
from nerfart_plugin.fields.sdf import SDFField
from nerfart_plugin.fields.volsdf import VolSDFField

__all__ = [
    "Field", "NeuralField", "SDFField", "NeRFField", "VolSDFField", "NeuSField", "EnvironmentMap", "OccupancyGrid",
    "build_field", "build_encoding", "build_background", "occupancy_scores_opacity",
]


def occupancy_scores_opacity(backbone_cfg: Any) -> bool:
    """Whether the occupancy grid of ``backbone_cfg``'s field (the ``backbone`` section: typed or a mapping)
    scores cells by opacity (``Field.occupancy_threshold`` None: density fields), which weighted sampling reads as
    a proposal; SDF fields score a shell around the surface instead."""
    backbone = typed_section("backbone", backbone_cfg)
    return registry.get("backbone", backbone.name).occupancy_threshold is None


def build_field(backbone_cfg: Any, encoding_cfg: Any = None, bound: float = 1.0) -> Field:
    """Build a backbone (the ``backbone`` section, typed or a mapping: ``name`` in nerf|volsdf|neus, the other keys
    its settings, checked by its ``Config``) on an encoding (the ``encoding`` section: ``name`` in frequency|grid,
    the other keys its settings)."""
    backbone = typed_section("backbone", backbone_cfg)
    cls = registry.get("backbone", backbone.name)
    return cls(backbone, encoding_cfg=encoding_cfg, bound=bound)
