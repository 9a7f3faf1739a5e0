"""VolSDF backbone (``backbone: volsdf``): SDF -> Laplace-CDF density (Yariv et al. 2021)."""

from __future__ import annotations

from typing import Any, Optional

import torch
import torch.nn as nn
from torch import Tensor

from nerfart_plugin.fields.base import SDFField
from nerfart_plugin.registry import register
from nerfart_plugin.rendering.volume import volsdf_density

__all__ = ["VolSDFField"]


@register("backbone", "volsdf")
class VolSDFField(SDFField):
    """SDF field rendered with ``sigma = volsdf_density(sdf, beta)``.

    Config (besides the common ``Field`` keys and ``radius``): ``beta_init``
    (default 0.1, world units), ``beta_min`` (default 1e-4: lower bound that
    keeps 1/beta finite and training stable). ``beta = beta_min + |b|`` with a
    learnable ``b`` (a geometry parameter).
    """

    def __init__(self, encoding_cfg: Optional[dict] = None, bound: float = 1.0,
                 beta_init: float = 0.1, beta_min: float = 1e-4, **kw: Any) -> None:
        super().__init__(encoding_cfg, bound, **kw)
        self.beta_min = float(beta_min)
        self.beta_param = nn.Parameter(torch.tensor(max(float(beta_init) - self.beta_min, 1e-6)))

    @property
    def beta(self) -> Tensor:
        return self.beta_min + self.beta_param.abs()

    def surface_width(self) -> float:
        """beta (world units): the Laplace density falls by e per beta away from the surface."""
        return float(self.beta.detach())

    def density(self, sdf: Tensor) -> Tensor:
        return volsdf_density(sdf, self.beta)

    def alpha(self, out: dict[str, Tensor], deltas: Tensor, dirs: Tensor) -> Tensor:
        """``1 - exp(-volsdf_density(sdf, beta) delta)`` [R,K]."""
        sigma = self.density(out["sdf"].reshape(deltas.shape))
        return -torch.expm1(-sigma * deltas.float().clamp_min(0))
