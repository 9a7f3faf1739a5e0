"""Background model for unbounded captures without masks: radiance at infinity."""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn
from torch import Tensor

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields.encodings import build_encoding
from nerfart_plugin.fields.mlp import make_mlp

__all__ = ["EnvironmentMap", "build_background"]


class EnvironmentMap(nn.Module):
    """Direction-conditioned colour ``c_bg(d) = sigmoid(MLP(enc(d)))`` (an environment map at infinity).

    The renderer composites it where transmittance remains:
    ``rgb = sum_k w_k c_k + T_final * c_bg(d)``.

    Config: ``dir_encoding`` (default ``{"name": "sh", "degree": 4}``),
    ``hidden_dim`` (default 32), ``n_layers`` (default 1).
    """

    def __init__(self, dir_encoding: Optional[dict] = None, hidden_dim: int = 32, n_layers: int = 1) -> None:
        super().__init__()
        self.encoding = build_encoding(dir_encoding or {"name": "sh", "degree": 4})
        self.net = make_mlp(self.encoding.n_output_dims, hidden_dim, 3, n_layers)

    def forward(self, d: Tensor) -> Tensor:
        """d [N,3] unit directions -> rgb [N,3] in [0,1]."""
        return torch.sigmoid(self.net(self.encoding(d)).float())


def build_background(cfg: Optional[dict]) -> Optional[EnvironmentMap]:
    """``None`` / ``{}`` / ``{"name": "none"}`` -> None; ``{"name": "envmap", **kw}`` -> EnvironmentMap."""
    if not cfg:
        return None
    cfg = dict(cfg)
    name = cfg.pop("name", "envmap")
    if name in (None, "none", "constant"):
        return None
    if name != "envmap":

        raise ConfigError(f"background.name={name!r} unknown; use 'envmap' or 'none'.")
    return EnvironmentMap(**cfg)
