"""``SDFField``: the machinery the SDF backbones (VolSDF, NeuS) share: geometric init, normals by autograd or
finite differences, the eikonal regularizer, the SDF shell of the occupancy grid."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.config.types import Depth, Fraction, Limits, PositiveFloat, Setting
from nerfart_plugin.fields.mlp import GeometricInitMLP, make_mlp
from nerfart_plugin.fields.neural import NeuralField


class SDFField(NeuralField):
    """Shared machinery of SDF backbones (VolSDF, NeuS).

    Geometry net: ``GeometricInitMLP`` on ``[x, encoding(x)]`` (config
    ``radius``: initial sphere radius in world units, default 0.8 (object scenes fill the unit sphere;
    null: ``0.5 * bound``); ``n_layers``: hidden layers of the geometry net, default 1;
    ``refine_init``: least-squares refinement of the sphere init, default True).
    Colour net: MLP on ``[geometry features, normal, SH(d)]`` with sigmoid output.
    ``forward`` also returns ``gradient`` = d sdf / dx [N,3]. ``grad_type``
    (default "auto"): "analytic" = autograd inside ``torch.enable_grad()``, so it
    works under ``no_grad`` rendering, with the graph of the gradient kept
    (``create_graph``) only if grad was enabled by the caller (training: eikonal
    term and normal-dependent colour), so no-grad rendering stays cheap;
    "finite_difference" = tetrahedron differences with step ``fd_eps`` (default
    1e-3 * bound), much faster to train with the grid encoding because
    ``grid_sample`` has no fast double backward on CPU (BENCHMARKS.md). "auto" picks
    finite_difference for the grid encoding, analytic otherwise.

    Speed knobs: ``color_normal`` (default True: the colour net sees the
    normal, as in IDR/NeuS; False: features and direction only) and
    ``grad_samples`` (default 1.0): with ``color_normal=false`` and an alpha
    that does not read the gradient (VolSDF; NeuS with ``alpha_mode=sections``)
    the training forward evaluates the geometry once per sample and the
    (4-tap) gradient only on this random fraction of samples, for the eikonal
    term: several times cheaper per sample with the grid encoding. No-grad rendering
    computes every gradient (normal maps) unless the caller passes
    ``with_normal=False`` and neither colour nor alpha reads the gradient: then
    the geometry net runs once per sample (1 instead of 4 taps), e.g. in the
    colour-only first pass of stylization (Section 4.4).
    """

    is_sdf = True
    mesh_level = 0.0
    mesh_inside_is_below = True
    occupancy_threshold = 0.5  # cell_occupancy is 0 or 1: occupied while the shell touched it recently

    # Regular tetrahedron vertices: sum v = 0, sum v v^T = 4 I  =>  grad g ~ sum_i v_i g(x + h v_i) / (4h).
    _TETRA = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))

    #: whether ``alpha`` reads ``out["gradient"]`` (then every sample needs its gradient)
    alpha_needs_gradient: bool = False

    class Config(NeuralField.Config):
        n_layers: Depth = Setting(1, description="hidden layers of the geometry net")
        radius: Optional[Annotated[PositiveFloat, Limits(le=100.0)]] = Setting(
            0.8, description="radius of the initial sphere (geometric initialisation); null: half the field box")
        refine_init: bool = Setting(True, description="refine the initial network to a sphere before training")
        grad_type: Literal["auto", "analytic", "finite_difference"] = Setting(
            "auto", description="how d sdf / dx is taken: analytic (autograd) | finite_difference (tetrahedron); "
            "auto: finite_difference on the grid encoding, analytic otherwise")
        fd_eps: Optional[Annotated[PositiveFloat, Limits(le=1.0)]] = Setting(
            None, description="finite-difference step; null: 1e-3 x the field box")
        color_normal: bool = Setting(True, description="the colour net sees the normal (IDR/NeuS); false: faster")
        grad_samples: Fraction = Setting(
            1.0, description="with color_normal=false and an alpha without gradients: the share of samples whose "
            "gradient is taken for the eikonal term")

    def __init__(self, cfg: Optional[Any] = None, *, encoding_cfg: Optional[dict] = None, bound: float = 1.0,
                 **options: Any) -> None:
        super().__init__(cfg, encoding_cfg=encoding_cfg, bound=bound, **options)
        c = self.cfg
        grad_type, fd_eps, radius = c.grad_type, c.fd_eps, c.radius
        self.color_normal = bool(c.color_normal)
        self.grad_samples = float(c.grad_samples)
        if grad_type == "auto":
            grad_type = "finite_difference" if self.encoding.slow_double_backward else "analytic"
        self.grad_type = grad_type
        self.compilable = grad_type != "analytic"  # autograd inside the query (see Field.compilable)
        self.fd_eps = float(fd_eps) if fd_eps is not None else 1e-3 * self.bound
        self.register_buffer("_tetra", torch.tensor(self._TETRA), persistent=False)
        self.radius = float(radius) if radius is not None else 0.5 * self.bound
        self.geo_net = GeometricInitMLP(self.encoding.n_output_dims, self.hidden_dim, self.n_layers, self.feature_dim,
                                        self.radius, refine_init=c.refine_init)
        color_in = self.feature_dim + 3 * int(self.color_normal) + self.dir_encoding.n_output_dims
        self.color_net = make_mlp(color_in, self.color_hidden_dim, 3, self.color_layers)

    def auto_choices(self, device: torch.device) -> dict[str, str]:
        """What ``backbone.grad_type=auto`` became (:mod:`nerfart_plugin.config.auto`)."""
        return {"backbone.grad_type": self.grad_type}

    def _geo(self, x: Tensor) -> Tensor:
        """``[sdf, features]`` [N, 1 + feature_dim] of points x [N,3], in the weights' precision under any
        autocast.

        The surface is beta (VolSDF) or 1/inv_s (NeuS) wide, a few thousandths of the box on trained
        scenes, and the gradient is a difference quotient over ``fd_eps`` (1e-3 of the box): a bfloat16
        SDF (8 significant bits; x itself rounded to 0.004 at |x| = 1) moved a trained selfie's SDF by up to
        0.007 and made the difference quotient noise. The colour net keeps the autocast. The analytic gradient
        (``grad_type=analytic``) is taken with autocast off as well: inside one, its backward matmuls ran in
        bfloat16 and moved the gradient by up to 1.1% of its length (tests/test_stability_rendering.py)."""
        dtype = self.geo_net.out.weight.dtype  # float32, or what the whole model was cast to (64-true)
        with torch.autocast(x.device.type, enabled=False):
            x = x.to(dtype)
            return self.geo_net(torch.cat([x, self.encoding(x).to(dtype)], dim=-1))

    def geometry(self, x: Tensor) -> Tensor:
        """SDF [N] (world units, negative inside)."""
        return self._geo(x)[..., 0].float()

    def _subsample_gradient(self) -> bool:
        return (self.grad_samples < 1.0 and torch.is_grad_enabled() and not self.color_normal
                and not self.alpha_needs_gradient)

    def _gradient_free(self, with_normal: bool) -> bool:
        """True when nothing asked for reads the SDF gradient (no-grad, colour-only rendering)."""
        return (not with_normal and not torch.is_grad_enabled() and not self.color_normal
                and not self.alpha_needs_gradient)

    def forward(self, x: Tensor, d: Tensor, with_normal: bool = True) -> dict[str, Tensor]:
        """x [N,3], d [N,3] unit -> ``rgb`` [N,3], ``sdf`` [N], ``gradient`` [N,3], ``normal`` [N,3] (unit).

        ``with_normal=False`` under no-grad with ``color_normal=false`` and an alpha that
        ignores the gradient: only ``rgb`` and ``sdf`` (one geometry evaluation per sample).

        With ``grad_samples < 1`` (training only, needs ``color_normal=false`` and
        an alpha that ignores the gradient) the gradient is computed for a random
        ``grad_samples`` fraction of the points only; the other rows of
        ``gradient``/``normal`` are 0 and ``gradient_mask`` [N] (bool) marks
        the computed rows (the eikonal term uses those).
        """
        if self._gradient_free(with_normal):
            h = self._geo(x).float()
            return {"rgb": self._color([h[..., 1:]], d), "sdf": h[..., 0]}
        if self._subsample_gradient():
            return self._forward_subset(x, d)
        if self.grad_type == "finite_difference":
            return self._forward_fd(x, d)
        training_graph = torch.is_grad_enabled()
        with torch.enable_grad():
            xg = x if x.requires_grad else x.detach().requires_grad_(True)
            h = self._geo(xg)
            sdf = h[..., 0]
            with torch.autocast(x.device.type, enabled=False):  # the float32 net's backward stays float32 (_geo)
                gradient = torch.autograd.grad(
                    sdf, xg, grad_outputs=torch.ones_like(sdf), create_graph=training_graph, retain_graph=training_graph
                )[0]
        feat = h[..., 1:]
        if not training_graph:
            sdf, feat, gradient = sdf.detach(), feat.detach(), gradient.detach()
        gradient = gradient.float()
        normal = F.normalize(gradient, dim=-1, eps=1e-8)
        rgb = self._color([feat, normal.to(feat.dtype)] if self.color_normal else [feat], d)
        return {"rgb": rgb, "sdf": sdf.float(), "gradient": gradient, "normal": normal}

    def _gradient(self, x: Tensor) -> Tensor:
        """d sdf / dx [M,3] (finite differences or autograd per ``grad_type``), differentiable."""
        if self.grad_type == "finite_difference":
            h = self.fd_eps
            tetra = self._tetra.to(device=x.device, dtype=x.dtype)
            vals = self._geo((x[None] + h * tetra[:, None, :]).reshape(-1, 3))[..., 0].float().view(4, -1)
            return (tetra[:, None, :] * vals[..., None]).sum(0) / (4.0 * h)
        xg = x.detach().requires_grad_(True)
        sdf = self._geo(xg)[..., 0]
        with torch.autocast(x.device.type, enabled=False):  # see forward
            return torch.autograd.grad(sdf, xg, torch.ones_like(sdf), create_graph=True)[0].float()

    def _forward_subset(self, x: Tensor, d: Tensor) -> dict[str, Tensor]:
        """Training forward with the gradient on a random ``grad_samples`` subset (see ``forward``)."""
        N = x.shape[0]
        h = self._geo(x).float()
        sdf, feat = h[..., 0], h[..., 1:]
        m = max(1, int(round(self.grad_samples * N)))
        idx = torch.randperm(N, device=x.device)[:m]
        g_sub = self._gradient(x.index_select(0, idx))
        gradient = g_sub.new_zeros(N, 3).index_copy(0, idx, g_sub)
        mask = torch.zeros(N, dtype=torch.bool, device=x.device).index_fill_(0, idx, True)
        normal = F.normalize(gradient, dim=-1, eps=1e-8)
        return {"rgb": self._color([feat], d), "sdf": sdf, "gradient": gradient, "normal": normal,
                "gradient_mask": mask}

    def _forward_fd(self, x: Tensor, d: Tensor) -> dict[str, Tensor]:
        """Finite-difference variant: the geometry net runs once on the 4 tetrahedron points x + h v_i.

        Only first-order autograd is needed for training (the double backward of
        ``F.grid_sample`` is a very slow composite on CPU); ``sdf``/features are
        the mean over the 4 points (= value at x + O(h^2)). Under low-precision
        autocast the difference quotient is coarse (but finite).
        """
        N = x.shape[0]
        h = self.fd_eps
        tetra = self._tetra.to(device=x.device, dtype=x.dtype)
        xs = (x[None, :, :] + h * tetra[:, None, :]).reshape(-1, 3)
        out = self._geo(xs).float().view(4, N, -1)
        vals = out[..., 0]  # [4,N]
        gradient = (tetra[:, None, :] * vals[..., None]).sum(0) / (4.0 * h)
        mean = out.mean(0)
        sdf, feat = mean[..., 0], mean[..., 1:]
        normal = F.normalize(gradient, dim=-1, eps=1e-8)
        rgb = self._color([feat, normal] if self.color_normal else [feat], d)
        return {"rgb": rgb, "sdf": sdf, "gradient": gradient, "normal": normal}

    def query(self, x: Tensor, d: Tensor, with_normal: bool = True) -> dict[str, Tensor]:
        return self(x, d, with_normal=with_normal)

    def cell_occupancy(self, x: Tensor, cell_size: float, band: float) -> Tensor:
        """1 where ``|sdf| < band`` (the cell is near the surface), else 0: deep inside is hidden behind it."""
        return (self.geometry(x).float().abs() < band).float()

    def signed_distance(self) -> Any:
        return self.geometry

    @property
    def regularizer_names(self) -> tuple[str, ...]:
        return ("eikonal", *self.encoding.regularizer_names)

    def regularizers(self, out: dict[str, Tensor]) -> dict[str, Tensor]:
        """``eikonal``: mean over samples of ``(|grad sdf| - 1)^2``; plus encoding terms."""
        reg = super().regularizers(out)
        g = out["gradient"]
        if "gradient_mask" in out:
            g = g[out["gradient_mask"]]
        reg["eikonal"] = (g.norm(dim=-1) - 1.0).square().mean()
        return reg
