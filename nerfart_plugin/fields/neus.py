"""NeuS backbone (``backbone: neus``): SDF with logistic-CDF unbiased opacity (Wang et al. 2021)."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional

import torch
import torch.nn as nn
from torch import Tensor

from nerfart_plugin.config_types import Float, Int, Limits
from nerfart_plugin.fields.base import SDFField
from nerfart_plugin.registry import register
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.rendering.volume import neus_alpha, neus_alpha_sections

__all__ = ["NeuSField"]


@register("backbone", "neus")
class NeuSField(SDFField):
    """SDF field rendered with ``neus_alpha``.

    Config (besides the common ``Field`` keys and ``radius``): ``init_variance``
    (default 0.3; ``inv_s = exp(10 * variance)`` starts at ~20), ``inv_s_max``
    (default 1e5, clamp of inv_s), ``anneal_steps`` (default 500; 0 = no cos
    annealing; otherwise the cos-anneal ratio goes linearly 0 -> 1 over the
    first ``anneal_steps`` steps, driven by ``update_step``), ``alpha_mode``
    ("gradient", default: the reference code's mid-point estimate from
    ``dot(d, grad sdf)``; "sections": NeuS Eq. 13 on the SDF at consecutive
    samples, which needs no gradient, so ``grad_samples < 1`` can skip most of
    the gradient cost; cos-annealing does not apply), ``variance_lr_scale``
    (default 0.2: the stored parameter is ``variance / variance_lr_scale``, so
    Adam moves the variance that many times slower or faster than the other
    MLP parameters; NeuS trains it at the network rate 5e-4, and at the grid's larger
    ``lr_mlp`` 0.2 keeps inv_s from sharpening before the shape forms; 1.0: the network rate).
    """

    def __init__(self, encoding_cfg: Optional[dict] = None, bound: float = 1.0,
                 init_variance: Annotated[Float, Limits(ge=-10.0, le=10.0)] = 0.3,
                 inv_s_max: Annotated[Float, Limits(gt=1.0, le=1e9)] = 1e5,
                 anneal_steps: Annotated[Int, Limits(ge=0, le=10**9)] = 500,
                 alpha_mode: Literal["gradient", "sections"] = "gradient",
                 variance_lr_scale: Annotated[Float, Limits(gt=0.0, le=100.0)] = 0.2, **kw: Any) -> None:
        if alpha_mode not in ("gradient", "sections"):
            raise ConfigError(f"backbone neus: alpha_mode={alpha_mode!r}; use 'gradient' or 'sections'.")
        self.alpha_needs_gradient = alpha_mode == "gradient"
        super().__init__(encoding_cfg, bound, **kw)
        self.alpha_mode = alpha_mode
        self.alpha_lookahead = 1 if alpha_mode == "sections" else 0  # Eq. 13 reads the next sample's SDF
        self.variance_lr_scale = float(variance_lr_scale)
        self.variance = nn.Parameter(torch.tensor(float(init_variance) / self.variance_lr_scale))
        self.inv_s_max = float(inv_s_max)
        self.anneal_steps = int(anneal_steps)
        # checkpointed state: a loaded reconstruction renders with the ratio it ended at (1 after
        # annealing), and a stylization continuing from it does not restart the anneal
        self.register_buffer("cos_anneal", torch.tensor(1.0 if self.anneal_steps <= 0 else 0.0))

    @property
    def cos_anneal_ratio(self) -> float:
        """Cos-annealing ratio r in [0, 1] of the alpha estimate (1 = NeuS' unbiased estimate)."""
        return float(self.cos_anneal)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # noqa: ANN001
        # checkpoints from before the ratio was saved: they come from finished runs, fully annealed
        state_dict.setdefault(prefix + "cos_anneal", torch.tensor(1.0))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def inv_s(self) -> Tensor:
        """Logistic sharpness ``exp(10 variance)`` clamped to [1, inv_s_max]."""
        return torch.exp(self.variance * (10.0 * self.variance_lr_scale)).clamp(1.0, self.inv_s_max)

    def surface_width(self) -> float:
        """1 / inv_s (world units): the scale of the logistic density around the surface."""
        return float(1.0 / self.inv_s.detach())

    def update_step(self, global_step: int, total_steps: int) -> None:
        """Advance the cos-anneal schedule (linear over ``anneal_steps``); it never goes back."""
        target = 1.0 if self.anneal_steps <= 0 else min(1.0, global_step / self.anneal_steps)
        self.cos_anneal.fill_(max(float(self.cos_anneal), target))

    def alpha(self, out: dict[str, Tensor], deltas: Tensor, dirs: Tensor) -> Tensor:
        """NeuS section opacity [R,K]: from sdf, ``dot(dir, grad sdf)`` and deltas (``alpha_mode=gradient``),
        or from the SDF at consecutive samples (``alpha_mode=sections``, see :func:`neus_alpha_sections`)."""
        if self.alpha_mode == "sections":
            return neus_alpha_sections(out["sdf"].reshape(deltas.shape), deltas, self.inv_s)
        grad = out["gradient"].reshape(*deltas.shape, 3)
        cos = (dirs.float() * grad.float()).sum(-1)
        return neus_alpha(out["sdf"].reshape(deltas.shape), cos, deltas, self.inv_s, self.cos_anneal_ratio)
