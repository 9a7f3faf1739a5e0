"""NeuS backbone (``backbone: neus``): SDF with logistic-CDF unbiased opacity (Wang et al. 2021)."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional

import torch
import torch.nn as nn
from torch import Tensor

from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Float, Int, Limits, Setting
from nerfart_plugin.fields.opacity import neus_alpha, neus_alpha_sections
from nerfart_plugin.fields.sdf import SDFField

__all__ = ["NeuSField"]


@register("backbone", "neus")
class NeuSField(SDFField):
    """SDF field rendered with ``neus_alpha``.

    Settings: :class:`NeuSField.Config` (besides :class:`SDFField.Config`); the variance is stored as
    ``variance / variance_lr_scale`` so that Adam moves it that many times slower or faster than the other MLP
    parameters (NeuS trains it at the network rate 5e-4; at the grid's larger ``lr_mlp`` 0.2 keeps inv_s from
    sharpening before the shape forms). ``alpha_mode=sections`` needs no gradient, so ``grad_samples < 1`` can
    skip most of the gradient cost; cos-annealing does not apply to it.
    """

    class Config(SDFField.Config):
        init_variance: Annotated[Float, Limits(ge=-10.0, le=10.0)] = Setting(
            0.3, description="initial variance: inv_s = exp(10 * variance) starts at about 20")
        inv_s_max: Annotated[Float, Limits(gt=1.0, le=1e9)] = Setting(1e5, description="clamp of inv_s")
        anneal_steps: Annotated[Int, Limits(ge=0, le=10**9)] = Setting(
            500, description="steps of the cos-anneal ratio going 0 -> 1 (0: no annealing)")
        alpha_mode: Literal["gradient", "sections"] = Setting(
            "gradient", description="gradient: the reference code's mid-point estimate from dot(d, grad sdf); "
            "sections: NeuS Eq. 13 on consecutive samples (no gradient needed)")
        variance_lr_scale: Annotated[Float, Limits(gt=0.0, le=100.0)] = Setting(
            0.2, description="the variance moves this many times as fast as the other MLP parameters")

    def __init__(self, cfg: Optional[Any] = None, *, encoding_cfg: Optional[dict] = None, bound: float = 1.0,
                 **options: Any) -> None:
        c = self.Config.build(cfg, **options)
        alpha_mode, init_variance = c.alpha_mode, c.init_variance
        self.alpha_needs_gradient = alpha_mode == "gradient"
        super().__init__(c, encoding_cfg=encoding_cfg, bound=bound)
        self.alpha_mode = alpha_mode
        self.alpha_lookahead = 1 if alpha_mode == "sections" else 0  # Eq. 13 reads the next sample's SDF
        self.variance_lr_scale = float(c.variance_lr_scale)
        self.variance = nn.Parameter(torch.tensor(float(init_variance) / self.variance_lr_scale))
        self.inv_s_max = float(c.inv_s_max)
        self.anneal_steps = int(c.anneal_steps)
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
