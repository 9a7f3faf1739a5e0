"""``NeuralField``: MLPs on an encoding, the base of every shipped backbone, with the settings they all share."""

from __future__ import annotations

from typing import Any, ClassVar, Iterator, Optional

import torch
import torch.nn as nn
from torch import Tensor

from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.types import Depth, Setting, Width
from nerfart_plugin.fields.encodings import Encoding, build_encoding
from nerfart_plugin.fields.field import Field


class NeuralField(Field):
    """A field of MLPs on an encoding (the base of every shipped backbone).

    Its settings (every backbone): :class:`NeuralField.Config`; ``encoding_cfg`` and ``bound`` come from the
    run (``encoding`` section, the field box).
    """

    class Config(ComponentConfig):
        """The settings every backbone has (``backbone.<key>``)."""

        section: ClassVar[str] = "backbone"

        feature_dim: Width = Setting(15, description="geometry features fed to the colour net")
        hidden_dim: Width = Setting(64, description="width of the geometry net")
        n_layers: Depth = Setting(2, description="hidden layers of the geometry net")
        color_hidden_dim: Width = Setting(64, description="width of the colour net")
        color_layers: Depth = Setting(2, description="hidden layers of the colour net")
        dir_encoding: Optional[dict[str, Any]] = Setting(
            None, description="the view-direction encoding (an encoding section: name + settings); null: "
            "{name: sh, degree: 4}")

    #: this backbone's settings (:class:`Config`, checked)
    cfg: "NeuralField.Config"

    def __init__(self, cfg: Optional[Any] = None, *, encoding_cfg: Optional[dict] = None, bound: float = 1.0,
                 **options: Any) -> None:
        c = type(self).Config.build(cfg, **options)
        feature_dim, hidden_dim, n_layers = c.feature_dim, c.hidden_dim, c.n_layers
        color_hidden_dim, color_layers, dir_encoding = c.color_hidden_dim, c.color_layers, c.dir_encoding
        super().__init__()
        self.cfg = c
        self.bound = float(bound)
        self.encoding: Encoding = build_encoding(encoding_cfg, bound)
        self.dir_encoding: Encoding = build_encoding(dir_encoding or {"name": "sh", "degree": 4})
        self.feature_dim = int(feature_dim)
        self.hidden_dim = int(hidden_dim)
        self.n_layers = int(n_layers)
        self.color_hidden_dim = int(color_hidden_dim)
        self.color_layers = int(color_layers)

    def regularizers(self, out: dict[str, Tensor]) -> dict[str, Tensor]:
        """The encoding's parameter regularizers (e.g. ``grid_tv``, already weighted by ``tv_weight``)."""
        return dict(self.encoding.regularizers())

    @property
    def regularizer_names(self) -> tuple[str, ...]:
        return self.encoding.regularizer_names

    def grid_parameters(self) -> Iterator[nn.Parameter]:
        return self.encoding.parameters()

    @property
    def mlp_lr_scale(self) -> float:
        return float(self.encoding.mlp_lr_scale)

    def color_parameters(self) -> Iterator[nn.Parameter]:
        return iter(list(self.color_net.parameters()) + list(self.dir_encoding.parameters()))

    def _color(self, feats: list[Tensor], d: Tensor) -> Tensor:
        h = torch.cat(feats + [self.dir_encoding(d).to(feats[0].dtype)], dim=-1)
        return torch.sigmoid(self.color_net(h).float())
