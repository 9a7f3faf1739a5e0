"""Fields put together from others: a source field and stylized parts, each inside its region.

:class:`CompositeField` renders ``out = out_src + Σ_i w_i m_i(x) (out_i − out_src)`` for colour (``m_i``: part
i's region, ``w_i``: its strength) and blends the parts' geometry the same way with a dilated mask (opacity,
normals, the SDF or density of meshes and the occupancy grid), so that

* where every ``w_i m_i`` is 0 the composite is the source field, sample for sample (nothing changes outside
  the regions);
* where one ``w_i m_i`` is 1 it is that part, exactly (a region covering the scene renders the part itself);
* each field is evaluated only where its coefficient is not 0, so a composite costs about one field per
  sample (both in the feather band).

It honours the field contract (:class:`~nerfart_plugin.fields.field.Field`), so the renderer, the two-pass patch
backprop, mesh export and the viewer need no special case. Its parameters are those of its parts; the source
is frozen by whoever built it.
"""

from __future__ import annotations

import math
from typing import Any, Iterator, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfart_plugin.fields.compiled import evaluate
from nerfart_plugin.fields.field import Field

#: the per-sample keys a part's output is stored under inside the composite's output
_SOURCE, _PART = "source.", "part{}."
#: mask values this close to 0 or 1 are taken as exactly 0 or 1 (float error of the bilinear lookup)
_SNAP = 1e-6


class RegionMask(nn.Module):
    """A region bound to a field's frame: the colour mask m(x) and the geometry mask (m dilated) on a small grid
    over the field box, read trilinearly.

    Args:
        masks: [2, D, H, W] values in [0, 1]: the colour mask and the geometry mask, on a grid whose corners
            are the field box's (``align_corners``): voxel (k, j, i) at field point
            ``bound * (-1 + 2 * (i, j, k) / (W-1, H-1, D-1))``.
        bound: half side of the field box.
        outside: the value beyond the grid (0; 1 for an inverted region).
    """

    def __init__(self, masks: Tensor, bound: float, outside: float = 0.0) -> None:
        super().__init__()
        if masks.dim() != 4 or masks.shape[0] != 2:
            raise ValueError(f"RegionMask: masks must be [2, D, H, W], got {tuple(masks.shape)}")
        self.register_buffer("masks", (masks.float().clamp(0, 1) - float(outside))[None], persistent=False)
        self.bound, self.outside = float(bound), float(outside)

    @classmethod
    def everywhere(cls, bound: float) -> "RegionMask":
        """The region that covers the whole field box (m = 1): a whole-scene part in a composite."""
        return cls(torch.ones(2, 2, 2, 2), bound, outside=1.0)

    def grown(self, reach: float) -> "RegionMask":
        """The same region with its geometry mask grown by ``reach`` (field units): what a ray must stay clear of
        to be rendered as the source renders it (the region plus the occupancy cells around it)."""
        masks = self.masks[0] + self.outside
        cell = 2.0 * self.bound / (masks.shape[-1] - 1)
        k = int(math.ceil(reach / cell))
        geo = F.max_pool3d(masks[1:2][None], kernel_size=2 * k + 1, stride=1, padding=k)[0] if k > 0 else masks[1:2]
        return RegionMask(torch.cat([masks[:1], geo]), self.bound, self.outside)

    def cells_outside(self, centres: Tensor, cell_size: float) -> Tensor:
        """[M] bool: the cells (``centres`` [M,3], side ``cell_size``) that the geometry mask does not reach: 0 at
        the centre and at the centres of the cells around it (the region's cell grid is finer than a cell)."""
        reach = torch.zeros(centres.shape[0], dtype=torch.bool, device=centres.device)
        offsets = torch.tensor([[a, b, c] for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)],
                               dtype=torch.float32, device=centres.device) * cell_size
        for off in offsets:
            _, geo = self(centres + off)
            reach |= geo > 0
        return ~reach

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x [N,3] (field coordinates) -> (colour mask [N], geometry mask [N]) in [0, 1]."""
        g = (x.float() / self.bound).reshape(1, -1, 1, 1, 3).to(self.masks.device)
        m = F.grid_sample(self.masks, g, mode="bilinear", padding_mode="zeros", align_corners=True)
        m = (m.reshape(2, -1) + self.outside).clamp(0, 1)
        # bilinear weights of a cell whose corners are all 1 can sum to 1 - 1 ulp: snapped, so a sample wholly
        # inside (or outside) a region is exactly the part's (the source's), with no trace of the other field
        m = torch.where(m > 1.0 - _SNAP, torch.ones_like(m), torch.where(m < _SNAP, torch.zeros_like(m), m))
        return m[0].to(x.device), m[1].to(x.device)


class CompositeField(Field):
    """``source`` with ``parts`` [(field, strength, RegionMask)] blended in (see the module docstring).

    The parts' and the source's outputs ride along in the composite's output under ``source.<key>`` and
    ``part<i>.<key>`` (per-sample tensors, as the renderer selects and concatenates them), so that :meth:`alpha`
    and :meth:`regularizers` read each field's own.
    """

    compilable = False  # its parts are compiled instead (its own query selects samples by the regions)

    def __init__(self, source: Field, parts: Sequence[tuple[Field, float, RegionMask]]) -> None:
        super().__init__()
        if not parts:
            raise ValueError("CompositeField needs at least one part")
        self.source = source
        self.parts = nn.ModuleList([p[0] for p in parts])
        self.regions = nn.ModuleList([p[2] for p in parts])
        self.strengths = [float(p[1]) for p in parts]
        lead = parts[0][0]
        self.is_sdf, self.bound = source.is_sdf, source.bound
        self.mesh_level, self.mesh_inside_is_below = source.mesh_level, source.mesh_inside_is_below
        self.occupancy_threshold = source.occupancy_threshold
        self.alpha_lookahead = max(source.alpha_lookahead, *(p[0].alpha_lookahead for p in parts))
        self._lead = lead

    # ---- the coefficients ---------------------------------------------------------------------
    def cells_outside(self, grid: Any) -> Tensor:
        """[n^3] bool: the cells of occupancy ``grid`` (:class:`~nerfart_plugin.fields.occupancy.OccupancyGrid`)
        that no part's region reaches: there the composite is the source (a part strengthless there too)."""
        centres = grid.cell_centres()
        outside = torch.ones(centres.shape[0], dtype=torch.bool, device=centres.device)
        for w, region in zip(self.strengths, self.regions):
            if w != 0:
                outside &= region.cells_outside(centres, grid.cell_size)
        return outside

    def coefficients(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x [N,3] -> (colour, geometry) coefficients [P,N] of the parts: ``w_i m_i(x)``."""
        pairs = [region(x) for region in self.regions]
        colour = torch.stack([w * c for w, (c, _) in zip(self.strengths, pairs)])
        geometry = torch.stack([w * g for w, (_, g) in zip(self.strengths, pairs)])
        return colour, geometry

    @staticmethod
    def _evaluate(field: Field, x: Tensor, d: Tensor, where: Tensor, with_normal: bool) -> dict[str, Tensor]:
        """``field.query`` on the samples ``where`` [N] only, zero-filled elsewhere (one probe sample when none,
        to keep the shapes and the graph)."""
        n = x.shape[0]
        idx = where.nonzero()[:, 0]
        if idx.numel() == n:
            return evaluate(field, x, d, with_normal=with_normal)
        if idx.numel() == 0:
            idx = torch.zeros(1, dtype=torch.long, device=x.device)
        sub = evaluate(field, x.index_select(0, idx), d.index_select(0, idx), with_normal=with_normal)
        full = {}
        for k, v in sub.items():
            if torch.is_tensor(v) and v.dim() >= 1 and v.shape[0] == idx.shape[0]:
                full[k] = v.new_zeros((n, *v.shape[1:])).index_copy(0, idx, v)
        return full

    def query(self, x: Tensor, d: Tensor, with_normal: bool = True) -> dict[str, Tensor]:
        colour, geometry = self.coefficients(x)
        own = 1.0 - colour.sum(0)
        own_geo = 1.0 - geometry.sum(0)
        src = self._evaluate(self.source, x, d, (own != 0) | (own_geo != 0), with_normal)
        out: dict[str, Tensor] = {_SOURCE + k: v for k, v in src.items()}
        rgb = own[:, None] * src["rgb"].float()
        normal = own_geo[:, None] * src["normal"].float() if "normal" in src else None
        geo_key = "sdf" if "sdf" in src else "sigma"
        geo = own_geo * src[geo_key].float()
        for i, part in enumerate(self.parts):
            where = (colour[i] != 0) | (geometry[i] != 0)
            o = self._evaluate(part, x, d, where, with_normal)
            out.update({_PART.format(i) + k: v for k, v in o.items()})
            out[_PART.format(i) + "evaluated"] = where
            rgb = rgb + colour[i][:, None] * o["rgb"].float()
            geo = geo + geometry[i] * o[geo_key].float()
            if normal is not None and "normal" in o:
                normal = normal + geometry[i][:, None] * o["normal"].float()
        out["rgb"] = rgb.clamp(0, 1)
        out[geo_key] = geo
        if normal is not None:
            out["normal"] = F.normalize(normal, dim=-1, eps=1e-8)
        out["composite.geometry"] = geometry.T.contiguous()  # [N,P]
        return out

    def forward(self, x: Tensor, d: Tensor) -> dict[str, Tensor]:
        return self.query(x, d)

    @staticmethod
    def _own(out: dict[str, Tensor], prefix: str) -> dict[str, Tensor]:
        return {k[len(prefix):]: v for k, v in out.items() if k.startswith(prefix)}

    def alpha(self, out: dict[str, Tensor], deltas: Tensor, dirs: Tensor) -> Tensor:
        """``(1 − Σ_i w_i m_geo_i) α_src + Σ_i w_i m_geo_i α_i`` [R,K]: each field's opacity from its own output,
        blended with the geometry masks (exactly the source's where they are 0, a part's where its is 1); clamped
        to [0, 1] (strengths past 1 extrapolate)."""
        geometry = out["composite.geometry"].reshape(*deltas.shape, -1).float()
        alpha = (1.0 - geometry.sum(-1)) * self.source.alpha(self._own(out, _SOURCE), deltas, dirs).float()
        for i, part in enumerate(self.parts):
            alpha = alpha + geometry[..., i] * part.alpha(self._own(out, _PART.format(i)), deltas, dirs).float()
        return alpha.clamp(0, 1)

    def regularizers(self, out: dict[str, Tensor]) -> dict[str, Tensor]:
        """The first part's (the one that trains) over the samples it was evaluated on."""
        own = self._own(out, _PART.format(0))
        where = own.pop("evaluated")
        if not bool(where.any()):  # none of these samples reaches the region: nothing to regularize
            zero = next(v for v in own.values() if torch.is_tensor(v) and v.is_floating_point()).sum() * 0.0
            return {name: zero for name in self._lead.regularizer_names}
        if "gradient_mask" in own:
            own["gradient_mask"] = own["gradient_mask"] & where
        elif "gradient" in own:
            own["gradient_mask"] = where
        return self._lead.regularizers(own)

    @property
    def regularizer_names(self) -> tuple[str, ...]:
        return self._lead.regularizer_names

    # ---- geometry -----------------------------------------------------------------------------
    def geometry(self, x: Tensor) -> Tensor:
        """The SDF or density blended with the geometry masks [N] (meshes, the occupancy grid)."""
        _, geometry = self.coefficients(x)
        out = (1.0 - geometry.sum(0)) * self.source.geometry(x).float()
        for i, part in enumerate(self.parts):
            where = geometry[i] != 0
            if bool(where.any()):
                g_i = torch.zeros_like(out)
                g_i[where] = part.geometry(x[where]).float()
                out = out + geometry[i] * g_i
        return out

    def cell_occupancy(self, x: Tensor, cell_size: float, band: float) -> Tensor:
        """The most occupied of the source and the parts that reach the cell (conservative: a cell any of them
        renders stays occupied)."""
        _, geometry = self.coefficients(x)
        occ = self.source.cell_occupancy(x, cell_size, band)
        for i, part in enumerate(self.parts):
            where = geometry[i] != 0
            if bool(where.any()):
                occ = occ.clone()
                occ[where] = torch.maximum(occ[where], part.cell_occupancy(x[where], cell_size, band))
        return occ

    def surface_width(self) -> float:
        return max(self.source.surface_width(), *(p.surface_width() for p in self.parts))

    def signed_distance(self) -> Optional[Any]:
        return self.geometry if self.is_sdf else None

    # ---- training: the first part trains ------------------------------------------------------
    def update_step(self, global_step: int, total_steps: int) -> None:
        self._lead.update_step(global_step, total_steps)

    def grid_parameters(self) -> Iterator[nn.Parameter]:
        return self._lead.grid_parameters()

    @property
    def mlp_lr_scale(self) -> float:
        return self._lead.mlp_lr_scale

    def geometry_parameters(self) -> Iterator[nn.Parameter]:
        return self._lead.geometry_parameters()

    def color_parameters(self) -> Iterator[nn.Parameter]:
        return self._lead.color_parameters()

    def scalars(self) -> dict[str, float]:
        return self._lead.scalars()

    def extra_repr(self) -> str:
        return f"parts={len(self.parts)}, strengths={self.strengths}"
