"""Input encodings (registry kind ``encoding``): ``frequency``, ``grid``, ``sh``.

Position encodings take points x [N,3] in world units inside [-bound, bound]^3
(points outside are clamped to the box) and return features [N, n_output_dims].
``sh`` encodes unit view directions d [N,3].
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal, Optional, Union

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.config import registry
from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.sections import typed_section
from nerfart_plugin.config.types import Float, Int, Limits, Setting
from nerfart_plugin.data.setup import AUTO_CELL_PIXELS, AUTO_GRID_MIN
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields import fused_grid

__all__ = ["Encoding", "FrequencyEncoding", "TensorVMGridEncoding", "SHEncoding", "build_encoding",
           "level_sides"]


class Encoding(nn.Module):
    """Base class: ``forward(x [N,in_dim]) -> [N, n_output_dims]``.

    ``mlp_lr_scale`` (config key of every encoding, default 1.0) multiplies the learning
    rate of the MLPs fed by this encoding (``systems.base.param_groups``): MLPs on a
    high-frequency positional encoding diverge at the rate that suits MLPs on a grid.
    """

    class Config(ComponentConfig):
        """The settings every encoding has (``encoding.<key>``)."""

        section: ClassVar[str] = "encoding"

        mlp_lr_scale: Annotated[Float, Limits(gt=0.0, le=100.0)] = Setting(
            1.0, description="multiplies the learning rate of the MLPs fed by this encoding (reconstruct.lr_mlp, "
            "stylize.lr_mlp)")

    n_input_dims: int = 3
    n_output_dims: int
    #: this encoding's settings (:class:`Config`, checked)
    cfg: "Encoding.Config"
    #: its backward has no fast backward of its own (``grid_sample`` on CPU): SDF fields on it take
    #: gradients by finite differences (``grad_type=auto``)
    slow_double_backward: bool = False

    def __init__(self, cfg: Optional[Any] = None, **options: Any) -> None:
        super().__init__()
        self.cfg = type(self).Config.build(cfg, **options)

    @property
    def mlp_lr_scale(self) -> float:
        return float(self.cfg.mlp_lr_scale)

    def regularizers(self) -> dict[str, Tensor]:
        """Parameter regularizers (0-dim tensors, weighted by the encoding's own settings), named as in
        :attr:`regularizer_names`."""
        return {}

    @property
    def regularizer_names(self) -> tuple[str, ...]:
        return ()


@register("encoding", "frequency")
class FrequencyEncoding(Encoding):
    """NeRF positional encoding ``[x, sin(2^k x), cos(2^k x)]_{k<n_freqs}`` on ``x / bound``.

    Output dims ``3*(include_input + 2*n_freqs)``. ``mlp_lr_scale`` defaults to 0.33: at the grid's MLP rate
    (3e-3) a NeuS on 10 frequencies lost its surface and never recovered (BENCHMARKS.md, trade-off); at 1e-3
    it trains.
    """

    class Config(Encoding.Config):
        mlp_lr_scale: Annotated[Float, Limits(gt=0.0, le=100.0)] = Setting(
            0.33, description="multiplies the learning rate of the MLPs fed by this encoding (a NeuS on 10 "
            "frequencies diverges at the grid's MLP rate)")
        n_freqs: Annotated[Int, Limits(ge=0, le=24)] = Setting(
            10, description="frequency bands 2^0 .. 2^(n-1) (4 is typical for directions; 2^24 is past float32)")
        include_input: bool = Setting(True, description="also pass x itself")

    def __init__(self, cfg: Optional[Any] = None, *, bound: float = 1.0, in_dim: int = 3, **options: Any) -> None:
        super().__init__(cfg, **options)
        self.bound = float(bound)
        self.n_input_dims = in_dim
        self.n_freqs = int(self.cfg.n_freqs)
        self.include_input = bool(self.cfg.include_input)
        self.register_buffer("freqs", 2.0 ** torch.arange(self.n_freqs, dtype=torch.float32), persistent=False)
        self.n_output_dims = in_dim * (int(self.include_input) + 2 * self.n_freqs)

    def forward(self, x: Tensor) -> Tensor:
        x = x / self.bound
        feats = [x] if self.include_input else []
        if self.n_freqs:
            xb = (x[..., None, :] * self.freqs[:, None].to(x.dtype)).flatten(-2)  # [N, F*3]
            feats += [torch.sin(xb), torch.cos(xb)]
        return torch.cat(feats, dim=-1)


#: grid side per level
GridSide = Annotated[Int, Limits(ge=2, le=2048)]
#: planes + lines of all levels: 2^27 float32 = 512 MiB (x4 with Adam's moments and the gradient)
MAX_GRID_PARAMS = 2**27
def level_sides(finest: int, levels: int) -> list[int]:
    """Sides of a ``levels``-level grid whose finest side is ``finest``, coarsest first, each level half the
    side of the next (the coarser ones at least 2): ``level_sides(128, 3) == [32, 64, 128]``."""
    return [max(2, int(finest) // 2**k) if k else int(finest) for k in reversed(range(int(levels)))]


@register("encoding", "grid")
class TensorVMGridEncoding(Encoding):
    """TensoRF vector-matrix (VM) decomposed feature grid, pure PyTorch (``F.grid_sample``).

    Per resolution level and per component c: three planes ``P_xy, P_xz, P_yz``
    [res,res] and three lines ``L_z, L_y, L_x`` [res]; the feature of x is
    ``[P_xy(x,y) L_z(z), P_xz(x,z) L_y(y), P_yz(y,z) L_x(x)]`` (3*n_components
    values per level, bilinear/linear interpolation, aligned corners), all
    levels concatenated, then optionally projected by a bias-free linear basis
    (TensoRF's "basis matrix") to ``out_features``.

    Its settings (:class:`TensorVMGridEncoding.Config`): the grid side(s), levels, components, projection,
    initialisation and total-variation weight; planes and lines start N(0, init_std), so products start small
    but non-zero; ``regularizers()`` returns the total variation when ``tv_weight`` > 0.
    """

    class Config(Encoding.Config):
        resolution: Union[Literal["auto"], GridSide, Annotated[list[GridSide], Limits(min_length=1, max_length=16)]] = \
            Setting("auto", description="grid side (the finest level's), or one side per level; auto: decided per "
                    "scene so that a cell spans about cell_pixels training-image pixels (built without a scene "
                    "setup: 128)")
        n_components: Annotated[Int, Limits(ge=1, le=256)] = Setting(8, description="VM components per level")
        levels: Union[Literal["auto"], Annotated[Int, Limits(ge=1, le=16)]] = Setting(
            "auto", description="levels, each coarser one half the side of the next; auto: decided per backbone "
            "(several for SDF fields, one for density fields)")
        out_features: Optional[Annotated[Int, Limits(ge=1, le=4096)]] = Setting(
            32, description="features after the bias-free linear basis (TensoRF's basis matrix); null: no projection")
        init_std: Annotated[Float, Limits(gt=0.0, le=10.0)] = Setting(
            0.1, description="standard deviation of the initial planes and lines")
        tv_weight: Annotated[Float, Limits(ge=0.0, le=1e6)] = Setting(
            0.0, description="weight of the total-variation regularizer of the planes (0: off)")
        cell_pixels: Annotated[Float, Limits(ge=0.25, le=64.0)] = Setting(
            AUTO_CELL_PIXELS, description="with resolution=auto: training-image pixels one grid cell spans")

    def __init__(self, cfg: Optional[Any] = None, *, bound: float = 1.0, **options: Any) -> None:
        super().__init__(cfg, **options)
        c = self.cfg
        resolution, levels, n_components, out_features = c.resolution, c.levels, c.n_components, c.out_features
        if resolution == "auto":  # built without a scene setup (which decides it and reads cell_pixels): the floor
            resolution = AUTO_GRID_MIN
        if levels == "auto":  # built without a scene setup (which decides it per backbone): one level
            levels = 1
        if isinstance(resolution, (int, float)):
            res_list = level_sides(int(resolution), levels)
        elif int(levels) not in (1, len(resolution)):
            raise ConfigError(f"encoding grid: resolution={list(resolution)} lists {len(resolution)} level sides but "
                              f"levels={levels}: give the sides as a list, or one side (or auto) and encoding.levels.")
        else:
            res_list = [int(r) for r in resolution]
        if not res_list or min(res_list) < 2 or n_components < 1:
            raise ConfigError(
                f"encoding grid: resolution={resolution!r}, n_components={n_components} invalid; "
                "use resolution >= 2 (int or list) and n_components >= 1."
            )
        n_params = sum(3 * int(n_components) * (r * r + r) for r in res_list)
        if n_params > MAX_GRID_PARAMS:
            raise ConfigError(
                f"encoding grid: resolution={resolution!r} with n_components={n_components} is {n_params:,} "
                f"parameters ({4 * n_params / 2**30:.1f} GiB, x4 with Adam); at most {MAX_GRID_PARAMS:,}: lower "
                "encoding.resolution or encoding.n_components."
            )
        self.bound = float(bound)
        self.resolutions = res_list
        self.n_components = int(n_components)
        self.tv_weight = float(c.tv_weight)
        C = self.n_components
        self.planes = nn.ParameterList([nn.Parameter(c.init_std * torch.randn(3, C, r, r)) for r in res_list])
        self.lines = nn.ParameterList([nn.Parameter(c.init_std * torch.randn(3, C, r, 1)) for r in res_list])
        raw = 3 * C * len(res_list)
        self.basis = nn.Linear(raw, out_features, bias=False) if out_features else None
        self.n_output_dims = int(out_features) if out_features else raw

    # plane axes (x,y), (x,z), (y,z); the matching line is the remaining axis z, y, x.
    _PLANE_AXES = ((0, 1), (0, 2), (1, 2))
    _LINE_AXES = (2, 1, 0)

    #: look up through the fused CPU kernel (:mod:`nerfart_plugin.fields.fused_grid`) for the points it serves;
    #: set by :meth:`set_fused` (the ``compile`` setting calls it)
    fused: bool = False

    def set_fused(self, on: bool) -> None:
        """Use the fused lookup kernel or ATen's ``grid_sample``: on where asked, the planes on a CPU and the kernel
        built (once per machine), and then the planes and lines are stored channels-last, the kernel's layout
        (same shapes and values; checkpoints unchanged). :attr:`fused` says which it is."""
        self.fused = bool(on) and self.planes[0].device.type == "cpu" and fused_grid.load() is not None
        if self.fused:
            for p in (*self.planes, *self.lines):
                if not p.is_contiguous(memory_format=torch.channels_last):
                    p.data = p.data.contiguous(memory_format=torch.channels_last)

    def forward(self, x: Tensor) -> Tensor:
        N = x.shape[0]
        xn = (x / self.bound).clamp(-1.0, 1.0)
        dtype = self.planes[0].dtype
        xn = xn.to(dtype)
        if self.fused and fused_grid.serves(xn):
            views = [fused_grid.channel_last(p, ln) for p, ln in zip(self.planes, self.lines)]
            out = fused_grid.tensorvm_features(xn, [v[0] for v in views], [v[1] for v in views])
            return self.basis(out) if self.basis is not None else out
        # grid_sample coords: last dim (u,v) = (W index, H index).
        plane_coords = torch.stack([xn[:, list(ax)] for ax in self._PLANE_AXES], 0)  # [3,N,2]
        line_c = torch.stack([xn[:, a] for a in self._LINE_AXES], 0)  # [3,N]
        line_coords = torch.stack([torch.zeros_like(line_c), line_c], -1)  # [3,N,2]: W=1 col, H=coord
        feats = []
        for planes, lines in zip(self.planes, self.lines):
            p, l = _grid_lookup(planes.to(dtype), lines.to(dtype), plane_coords, line_coords)
            f = (p * l)[..., 0]  # [3,C,N]
            feats.append(f.permute(2, 0, 1).reshape(N, -1))
        out = torch.cat(feats, -1) if len(feats) > 1 else feats[0]
        return self.basis(out) if self.basis is not None else out

    slow_double_backward = True

    @property
    def regularizer_names(self) -> tuple[str, ...]:
        return ("grid_tv",) if self.tv_weight > 0 else ()

    def regularizers(self) -> dict[str, Tensor]:
        """``grid_tv``: ``tv_weight`` x the mean squared difference of neighbouring plane cells (total variation)."""
        if self.tv_weight <= 0:
            return {}
        tv = sum(
            (p[..., 1:, :] - p[..., :-1, :]).pow(2).mean() + (p[..., :, 1:] - p[..., :, :-1]).pow(2).mean()
            for p in self.planes
        )
        return {"grid_tv": self.tv_weight * tv}


@torch.compiler.disable
def _grid_lookup(planes: Tensor, lines: Tensor, plane_coords: Tensor, line_coords: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear lookups of ``planes`` [3,C,r,r] and ``lines`` [3,C,r,1] at ``plane_coords`` / ``line_coords``
    [3,N,2] -> [3,C,N,1] each. Left to ATen's kernels when the field is compiled: the compiler's own
    ``grid_sample`` (a decomposition into gathers) is slower on a CPU, forward and backward (BENCHMARKS.md)."""
    p = F.grid_sample(planes, plane_coords[:, :, None, :], mode="bilinear", align_corners=True)
    l = F.grid_sample(lines, line_coords[:, :, None, :], mode="bilinear", align_corners=True)
    return p, l


@register("encoding", "sh")
class SHEncoding(Encoding):
    """Real spherical harmonics of unit directions, ``degree`` bands (1..4 -> 1,4,9,16 dims).

    Same convention/constants as tiny-cuda-nn's ``SphericalHarmonics`` (degree 4 = 16 coefficients).
    """

    class Config(Encoding.Config):
        degree: Annotated[Int, Limits(ge=1, le=4)] = Setting(4, description="bands: 1..4 -> 1, 4, 9, 16 features")

    def __init__(self, cfg: Optional[Any] = None, *, bound: float = 1.0, **options: Any) -> None:
        super().__init__(cfg, **options)
        degree = self.cfg.degree
        self.degree = int(degree)
        self.n_output_dims = self.degree**2

    def forward(self, d: Tensor) -> Tensor:
        x, y, z = d.unbind(-1)
        out = [torch.full_like(x, 0.28209479177387814)]
        if self.degree > 1:
            out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
        if self.degree > 2:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            out += [
                1.0925484305920792 * xy,
                -1.0925484305920792 * yz,
                0.94617469575755997 * zz - 0.31539156525251999,
                -1.0925484305920792 * xz,
                0.54627421529603959 * (xx - yy),
            ]
        if self.degree > 3:
            out += [
                0.59004358992664352 * y * (-3.0 * xx + yy),
                2.8906114426405538 * xy * z,
                0.45704579946446572 * y * (1.0 - 5.0 * zz),
                0.3731763325901154 * z * (5.0 * zz - 3.0),
                0.45704579946446572 * x * (1.0 - 5.0 * zz),
                1.4453057213202769 * z * (xx - yy),
                0.59004358992664352 * x * (-xx + 3.0 * yy),
            ]
        return torch.stack(out, -1)


def build_encoding(cfg: Any = None, bound: float = 1.0) -> Encoding:
    """Build an encoding from its section (typed or ``{"name": <registered name>, **its settings}``; None: the
    frequency encoding's defaults)."""
    encoding = typed_section("encoding", cfg if cfg is not None else {"name": "frequency"})
    return registry.get("encoding", encoding.name)(encoding, bound=bound)
