"""The ``Field`` contract shared by all backbones.

A field maps points x [N,3] (world units, inside [-bound, bound]^3) and unit
view directions d [N,3] to colour and geometry. The renderer calls ``query``,
``alpha`` and ``regularizers``; the occupancy grid ``cell_occupancy`` and
``surface_width``; mesh export ``geometry`` and ``forward``; the stages
``signed_distance``, the parameter groups and ``scalars``. See
``docs/developers/architecture.md`` ("The field contract").
"""

from __future__ import annotations

from typing import Any, Iterator, Optional

import torch
import torch.nn as nn
from torch import Tensor


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
        compiled: whether callers evaluate :meth:`query` through ``torch.compile`` (:func:`fields.compiled.evaluate`).
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
    #: evaluate ``query`` compiled (:mod:`nerfart_plugin.fields.compiled`; the ``compile`` setting sets it)
    compiled: bool = False
    #: whether ``query`` may run compiled: False for a field that takes autograd inside it (an analytic SDF
    #: gradient: compiled graphs honour neither its ``enable_grad`` under a no-grad caller nor its double backward)
    compilable: bool = True

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
