"""NeRF density backbone (``backbone: nerf``): density + view-dependent radiance."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Float, Limits, Setting
from nerfart_plugin.fields.mlp import make_mlp
from nerfart_plugin.fields.neural import NeuralField

__all__ = ["NeRFField", "trunc_exp"]

_TRUNC = 15.0


class _TruncExp(torch.autograd.Function):
    """``exp(min(x, 15))`` whose backward is ``exp(min(x, 15))`` too (Müller et al., instant-ngp).

    Clamping the forward at 15 (sigma <= 3.3e6) keeps float16/bfloat16 finite;
    the gradient is never zeroed by the clamp, so an overshooting density is
    still pushed back down.
    """

    @staticmethod
    def forward(ctx: Any, x: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=_TRUNC))

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> Tensor:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=_TRUNC))


def trunc_exp(x: Tensor) -> Tensor:
    """Truncated exponential activation (float32)."""
    return _TruncExp.apply(x.float())


@register("backbone", "nerf")
class NeRFField(NeuralField):
    """Density field: ``sigma = act(raw + density_bias)``, ``rgb = sigmoid(MLP([feat, SH(d)]))``.

    Settings: :class:`NeRFField.Config` (besides the common :class:`NeuralField.Config`).

    Init: the geometry net outputs raw ~ 0 at init, so sigma ~ exp(-1) = 0.37
    (trunc_exp) or softplus(-1) = 0.31: a faint uniform fog (over a ray of
    length 2 the transmittance is ~0.5), which gives every sample a gradient
    from the first step without occluding anything.

    ``input_xyz`` (default True): the geometry net also sees ``x / bound``
    (besides the encoding). A freshly initialised grid gives near-constant,
    ~0.01-sized features, so without it the field starts as a uniform grey fog
    and waits ~30-50 steps for the grid to grow before it can vary in space.
    """

    is_sdf = False
    mesh_inside_is_below = False

    class Config(NeuralField.Config):
        density_activation: Literal["trunc_exp", "softplus"] = Setting(
            "trunc_exp", description="sigma = act(raw + density_bias): trunc_exp | softplus")
        density_bias: Annotated[Float, Limits(ge=-100.0, le=100.0)] = Setting(
            -1.0, description="added to the raw density (a faint uniform fog at initialisation)")
        mesh_level: Annotated[Float, Limits(gt=0.0, le=1e6)] = Setting(
            10.0, description="density iso-level of the extracted mesh")
        input_xyz: bool = Setting(True, description="the geometry net also sees x / bound besides the encoding")

    def __init__(self, cfg: Optional[Any] = None, *, encoding_cfg: Optional[dict] = None, bound: float = 1.0,
                 **options: Any) -> None:
        super().__init__(cfg, encoding_cfg=encoding_cfg, bound=bound, **options)
        c = self.cfg
        density_activation, density_bias, mesh_level, input_xyz = (c.density_activation, c.density_bias,
                                                                   c.mesh_level, c.input_xyz)
        self.density_activation = density_activation
        self.density_bias = float(density_bias)
        self.mesh_level = float(mesh_level)
        self.input_xyz = bool(input_xyz)
        in_dim = self.encoding.n_output_dims + 3 * int(self.input_xyz)
        self.geo_net = make_mlp(in_dim, self.hidden_dim, 1 + self.feature_dim, self.n_layers)
        with torch.no_grad():  # start with raw density ~ 0 (see class docstring)
            self.geo_net[-1].weight[:1].mul_(0.1)
            self.geo_net[-1].bias[:1].zero_()
        self.color_net = make_mlp(self.feature_dim + self.dir_encoding.n_output_dims, self.color_hidden_dim, 3, self.color_layers)

    def _geo(self, x: Tensor) -> Tensor:
        enc = self.encoding(x)
        if self.input_xyz:
            enc = torch.cat([(x / self.bound).to(enc.dtype), enc], dim=-1)
        return self.geo_net(enc)

    def _density(self, raw: Tensor) -> Tensor:
        raw = raw.float() + self.density_bias
        return trunc_exp(raw) if self.density_activation == "trunc_exp" else F.softplus(raw)

    def geometry(self, x: Tensor) -> Tensor:
        """Density sigma [N] >= 0 (1/world units)."""
        return self._density(self._geo(x)[..., 0])

    def forward(self, x: Tensor, d: Tensor) -> dict[str, Tensor]:
        """x [N,3], d [N,3] unit -> ``rgb`` [N,3] in [0,1], ``sigma`` [N] >= 0 (no normals)."""
        h = self._geo(x)
        sigma = self._density(h[..., 0])
        rgb = self._color([h[..., 1:]], d)
        return {"rgb": rgb, "sigma": sigma}

    def alpha(self, out: dict[str, Tensor], deltas: Tensor, dirs: Tensor) -> Tensor:
        """``1 - exp(-sigma delta)`` [R,K] (Eq. 1's omega_k)."""
        tau = out["sigma"].reshape(deltas.shape).float().clamp_min(0) * deltas.float().clamp_min(0)
        return -torch.expm1(-tau)
