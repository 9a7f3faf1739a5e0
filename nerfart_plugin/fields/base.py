"""The ``Field`` contract shared by all backbones, plus MLP building blocks.

A field maps points x [N,3] (world units, inside [-bound, bound]^3) and unit
view directions d [N,3] to colour and geometry. The renderer calls ``query``,
``alpha`` and ``regularizers``; the occupancy grid ``cell_occupancy`` and
``surface_width``; mesh export ``geometry`` and ``forward``; the stages
``signed_distance``, the parameter groups and ``scalars``. See
``docs/architecture.md`` ("The field contract").
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Iterator, Literal, Optional

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.components import ComponentConfig
from nerfart_plugin.config_types import Depth, Fraction, Limits, PositiveFloat, Setting, Width
from nerfart_plugin.fields.encodings import Encoding, build_encoding

__all__ = ["Field", "NeuralField", "SDFField", "make_mlp", "GeometricInitMLP", "SharpSoftplus"]


class _SharpSoftplusFn(torch.autograd.Function):
    """``softplus_beta(x) = (relu(beta x) + log(1 + exp(-|beta x|))) / beta``; gradient ``sigmoid(beta x)``.

    The same function as ``F.softplus(x, beta)`` (to 6e-8 absolute in float32: for ``|beta x| > 17``
    ``log(1 + e)`` rounds to 0 where log1p would give ``e < 4e-8``), computed with ``log`` instead of
    ``log1p``, whose CPU kernel is several times slower than ``exp`` and ``log``. Its backward is one
    sigmoid instead of softplus_backward's exp, and is itself differentiable (the analytic eikonal
    gradient takes the double backward), since it is written in differentiable ops of the saved input.
    """

    @staticmethod
    def forward(ctx: Any, x: Tensor, beta: float) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        ctx.beta = beta
        z = x * beta
        return (torch.relu(z) + torch.log(1.0 + torch.exp(-z.abs()))) / beta

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return grad * torch.sigmoid(x * ctx.beta), None


class SharpSoftplus(nn.Module):
    """``nn.Softplus(beta)`` (no threshold: exact everywhere), about 2x faster forward and backward on a
    CPU (:class:`_SharpSoftplusFn`). x [...] -> [...], same dtype."""

    def __init__(self, beta: float = 100.0) -> None:
        super().__init__()
        self.beta = float(beta)

    def forward(self, x: Tensor) -> Tensor:
        return _SharpSoftplusFn.apply(x, self.beta)

    def extra_repr(self) -> str:
        return f"beta={self.beta}"


def make_mlp(in_dim: int, hidden_dim: int, out_dim: int, n_hidden_layers: int, act: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """``n_hidden_layers`` Linear+act layers of width ``hidden_dim``, then a Linear to ``out_dim``."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(max(0, n_hidden_layers)):
        layers += [nn.Linear(d, hidden_dim), act()]
        d = hidden_dim
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


class GeometricInitMLP(nn.Module):
    """SDF MLP with the geometric initialisation of SAL/IDR (Atzmon & Lipman 2020).

    Input is ``[x, extra]`` with x [N,3] raw world coordinates and ``extra``
    [N,E] encoding features. At init the first layer only sees x (weights on
    ``extra`` are zero, so any encoding can be attached without breaking the
    init), hidden weights are N(0, 2/width), and the last layer's SDF row is
    N(sqrt(pi)/sqrt(width), 1e-4) with bias ``-radius``: the network starts as
    (approximately) the SDF of a sphere of ``radius``, ``sdf(x) ~ |x| - radius``.
    Activation: softplus with beta=100 (smooth, so the eikonal gradient is
    well defined). Output [N, 1 + feature_dim]: sdf then geometry features.

    With small widths (64) the random init is only a rough sphere (mean error
    ~0.35 radius), so by default (``refine_init``) the SDF output row is then
    re-fitted by ridge least squares to ``|x| - radius`` on 8192 fixed points
    in [-2 radius, 2 radius]^3 (mean error ~0.02 radius, eikonal ~ satisfied).
    """

    def __init__(self, extra_dim: int, hidden_dim: int, n_hidden_layers: int, feature_dim: int, radius: float,
                 refine_init: bool = True) -> None:
        super().__init__()
        dims = [3 + extra_dim] + [hidden_dim] * max(1, n_hidden_layers)
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.out = nn.Linear(dims[-1], 1 + feature_dim)
        self.act = SharpSoftplus(beta=100.0)
        with torch.no_grad():
            for i, lin in enumerate(self.hidden):
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(lin.out_features))
                nn.init.zeros_(lin.bias)
                if i == 0 and extra_dim > 0:
                    lin.weight[:, 3:].zero_()
            nn.init.normal_(self.out.weight, 0.0, 1e-2)
            nn.init.zeros_(self.out.bias)
            nn.init.normal_(self.out.weight[:1], math.sqrt(math.pi) / math.sqrt(dims[-1]), 1e-4)
            self.out.bias[:1].fill_(-float(radius))
            if refine_init:
                self._refine_sphere(float(radius), extra_dim)

    @torch.no_grad()
    def _refine_sphere(self, radius: float, extra_dim: int) -> None:
        gen = torch.Generator().manual_seed(0)
        x = (torch.rand(8192, 3, generator=gen) * 2.0 - 1.0) * 2.0 * radius
        h = torch.cat([x, torch.zeros(x.shape[0], extra_dim)], -1).to(self.out.weight.device)
        for lin in self.hidden:
            h = self.act(lin(h))
        A = torch.cat([h, torch.ones_like(h[:, :1])], -1)
        y = x.norm(dim=-1, keepdim=True).to(A.device) - radius
        eye = torch.eye(A.shape[1], device=A.device)
        sol = torch.linalg.solve(A.T @ A + 1e-4 * eye, A.T @ y)[:, 0]
        if torch.isfinite(sol).all():
            self.out.weight[0] = sol[:-1]
            self.out.bias[0] = sol[-1]

    def forward(self, h: Tensor) -> Tensor:
        for lin in self.hidden:
            h = self.act(lin(h))
        return self.out(h)


class Field(nn.Module):
    """The field contract: everything the renderer, the occupancy grid, mesh export and the
    training stages ask of a backbone (``docs/architecture.md``). Nothing outside
    ``fields/`` branches on the backbone: what differs is answered here.

    A field maps points x [N,3] (world units, inside [-bound, bound]^3) and unit view
    directions d [N,3] to colour and geometry. A custom field only needs ``forward(x, d)``,
    ``alpha`` and ``geometry``; every other method has a default that fits a density field.

    Attributes:
        is_sdf: True for SDF backbones (for the fields' own use and for reports).
        bound: half side of the scene box [-bound, bound]^3.
        mesh_level / mesh_inside_is_below: iso-level of ``geometry`` for meshing.
        occupancy_threshold: score above which the occupancy grid marks a cell occupied
            (None: the grid's adaptive density threshold).
        regularizer_names: the terms :meth:`regularizers` returns while training.
        alpha_lookahead: how many following samples of a ray :meth:`alpha` reads besides the section's
            own (0: each opacity is local; NeuS' section estimate reads the next sample's SDF: 1), so
            that a renderer marching a ray block by block evaluates them with each block.
    """

    is_sdf: bool = False
    bound: float = 1.0
    mesh_level: float = 0.0
    mesh_inside_is_below: bool = True
    occupancy_threshold: Optional[float] = None
    alpha_lookahead: int = 0

    # ---- what the renderer calls ----------------------------------------------------------
    def forward(self, x: Tensor, d: Tensor) -> dict[str, Tensor]:  # pragma: no cover
        """x [N,3], d [N,3] unit -> ``rgb`` [N,3] in [0,1] plus what :meth:`alpha` reads (``sigma`` [N]
        or ``sdf`` [N], ...); ``normal`` [N,3] when the field has normals."""
        raise NotImplementedError

    def query(self, x: Tensor, d: Tensor, with_normal: bool = True) -> dict[str, Tensor]:
        """What the renderer calls. ``with_normal=False``: the caller needs no normals (a colour-only
        no-grad render), so a field may skip work that only normals need. Default: ``forward(x, d)``
        (a field with the plain contract renders its normals, if any, every time)."""
        return self(x, d)

    def alpha(self, out: dict[str, Tensor], deltas: Tensor, dirs: Tensor) -> Tensor:  # pragma: no cover
        """Section opacities [R,K] from the ``query`` output reshaped to ``deltas`` [R,K] (world lengths)."""
        raise NotImplementedError

    def regularizers(self, out: dict[str, Tensor]) -> dict[str, Tensor]:
        """Regularizer terms (0-dim tensors) of a training ``query`` output, named as in
        :attr:`regularizer_names`; a stage weighs each by its ``lambda_<name>`` when its config has one,
        else by 1 (the component weighs it itself, e.g. ``encoding.tv_weight``)."""
        return {}

    @property
    def regularizer_names(self) -> tuple[str, ...]:
        return ()

    # ---- geometry: the occupancy grid, mesh export, geometry metrics -----------------------
    def geometry(self, x: Tensor) -> Tensor:  # pragma: no cover
        """The scalar field that defines the shape, [N]: density (1/world units) or signed distance."""
        raise NotImplementedError

    def cell_occupancy(self, x: Tensor, cell_size: float, band: float) -> Tensor:
        """Occupancy evidence [N] in [0,1] at one random point x [N,3] per occupancy cell of side
        ``cell_size`` (world units). Default (density): the opacity of one cell, ``1 - exp(-sigma cell_size)``;
        ``band`` (the half-width of the sampled shell, world units) is for SDF fields."""
        return -torch.expm1(-self.geometry(x).float().clamp_min(0) * cell_size)

    def surface_width(self) -> float:
        """Current thickness scale of the rendered surface (world units; 0 = sharp or no surface)."""
        return 0.0

    def signed_distance(self) -> Optional[Any]:
        """The signed distance function x [N,3] -> [N] (world units) if the geometry is one, else None."""
        return None

    # ---- training ------------------------------------------------------------------------
    def update_step(self, global_step: int, total_steps: int) -> None:
        """Advance training schedules (no-op by default)."""

    def grid_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters trained at the grid learning rate (``reconstruct.lr``); none by default."""
        return iter(())

    @property
    def mlp_lr_scale(self) -> float:
        """Factor on the MLP learning rate (``reconstruct.lr_mlp``) for this field's other parameters."""
        return 1.0

    def geometry_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters defining the shape (frozen by ``stylize.freeze_geometry``): all but the colour net's."""
        color = {id(p) for p in self.color_parameters()}
        return (p for p in self.parameters() if id(p) not in color)

    def color_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters of the view-dependent colour net only (none by default)."""
        return iter(())

    def scalars(self) -> dict[str, float]:
        """Scalars worth logging while training (e.g. VolSDF's beta as ``train/beta``)."""
        return {}

    def extra_repr(self) -> str:
        return f"bound={self.bound}, is_sdf={self.is_sdf}"


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
        self.fd_eps = float(fd_eps) if fd_eps is not None else 1e-3 * self.bound
        self.register_buffer("_tetra", torch.tensor(self._TETRA), persistent=False)
        self.radius = float(radius) if radius is not None else 0.5 * self.bound
        self.geo_net = GeometricInitMLP(self.encoding.n_output_dims, self.hidden_dim, self.n_layers, self.feature_dim,
                                        self.radius, refine_init=c.refine_init)
        color_in = self.feature_dim + 3 * int(self.color_normal) + self.dir_encoding.n_output_dims
        self.color_net = make_mlp(color_in, self.color_hidden_dim, 3, self.color_layers)

    def auto_choices(self, device: torch.device) -> dict[str, str]:
        """What ``backbone.grad_type=auto`` became (:mod:`nerfart_plugin.auto`)."""
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
