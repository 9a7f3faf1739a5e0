"""Fields: encodings, backbones (nerf | volsdf | neus), background model, occupancy grid.

Importing this package registers the ``encoding`` and ``backbone`` components.
"""

from __future__ import annotations

from typing import Any, Optional

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields import encodings, nerf, neus, volsdf  # noqa: F401  (registration)
from nerfart_plugin.fields.background import EnvironmentMap, build_background
from nerfart_plugin.fields.field import Field
from nerfart_plugin.fields.neural import NeuralField
from nerfart_plugin.fields.sdf import SDFField
from nerfart_plugin.fields.encodings import build_encoding
from nerfart_plugin.fields.nerf import NeRFField
from nerfart_plugin.fields.neus import NeuSField
from nerfart_plugin.fields.occupancy import OccupancyGrid
from nerfart_plugin.fields.volsdf import VolSDFField

__all__ = [
    "Field", "NeuralField", "SDFField", "NeRFField", "VolSDFField", "NeuSField", "EnvironmentMap", "OccupancyGrid",
    "build_field", "build_encoding", "build_background", "occupancy_scores_opacity",
]


def occupancy_scores_opacity(backbone_cfg: dict[str, Any]) -> bool:
    """Whether the occupancy grid of ``backbone_cfg``'s field (its ``name``) scores cells by opacity
    (``Field.occupancy_threshold`` None: density fields), which weighted sampling reads as a proposal;
    SDF fields score a shell around the surface instead."""
    from nerfart_plugin.config import registry

    name = (backbone_cfg or {}).get("name")
    return name is not None and registry.get("backbone", str(name)).occupancy_threshold is None


def build_field(backbone_cfg: dict[str, Any], encoding_cfg: Optional[dict[str, Any]] = None, bound: float = 1.0) -> Field:
    """Build a backbone (``backbone_cfg["name"]`` in nerf|volsdf|neus, other keys its settings, checked by its
    ``Config``) on an encoding (``encoding_cfg["name"]`` in frequency|grid, other keys its settings)."""
    from nerfart_plugin.config import registry

    cfg = dict(backbone_cfg or {})
    name = cfg.pop("name", None)
    if name is None:
        raise ConfigError("backbone config has no 'name'; set backbone.name to one of: " + ", ".join(registry.names("backbone")))
    cls = registry.get("backbone", str(name))
    return cls(cfg, encoding_cfg=dict(encoding_cfg) if encoding_cfg else None, bound=bound)
