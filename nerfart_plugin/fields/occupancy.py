"""Occupancy grid for empty-space skipping (instant-ngp / nerfacc style, pure torch)."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Optional

import torch
import torch.nn as nn
from torch import Tensor

if TYPE_CHECKING:  # pragma: no cover
    from nerfart_plugin.fields.field import Field

log = logging.getLogger(__name__)

__all__ = ["OccupancyGrid"]


class OccupancyGrid(nn.Module):
    """A ``resolution^3`` grid over [-bound, bound]^3 marking where the field is non-empty.

    Each cell keeps a score updated every ``update_every`` training steps from
    ``field.cell_occupancy`` at one random point per cell (the field contract: the grid
    never asks which backbone it is), with the nerfacc rule
    ``score = max(score * ema_decay, new)``, and ``occupied = score > threshold``.

    * density fields: ``new = 1 - exp(-sigma * cell_size)`` (opacity of one cell),
      threshold ``clamp(mean score, min_threshold, threshold)`` (defaults 1e-4, 0.01:
      nerfacc's ``min(threshold, mean)`` plus a floor so that an empty field
      does not mark the above-mean half of its ~0-density cells occupied);
    * SDF fields (``field.occupancy_threshold`` 0.5): ``new = 1`` if ``|sdf| < band`` else 0, i.e. occupied near
      the surface; ``sdf_band`` defaults to one cell diagonal (a cell that the
      zero level set crosses has every point within one diagonal of it, so a
      true SDF never misses it), widened to ``band_widths`` (default 3) times
      the field's current ``surface_width()`` while the surface is still blurry
      (see :meth:`band`). Deep interior is skipped too: it is hidden
      behind the surface. Threshold 0.5: a cell left by the surface stays
      occupied for ~13 updates (0.95^13 ~ 0.5).

    Before the first update every cell is occupied (scores start at 0, so the
    first update alone decides). During the first
    ``warmup_steps`` every cell is re-evaluated at each update; afterwards a
    random quarter of the cells plus all currently occupied cells (as nerfacc).
    State (``score``, ``occupied``) lives in buffers, so it is saved in checkpoints.
    """

    #: look up the rays' cells through ``torch.compile`` (:meth:`query_rays`; the ``compile`` setting sets it)
    compiled: bool = False

    def __init__(
        self,
        resolution: int = 64,
        bound: float = 1.0,
        threshold: float = 0.01,
        min_threshold: float = 1e-4,
        ema_decay: float = 0.95,
        update_every: int = 16,
        warmup_steps: int = 256,
        sdf_band: Optional[float] = None,
        chunk: int = 65536,
        band_widths: float = 3.0,
    ) -> None:
        super().__init__()
        self.resolution = int(resolution)
        self.bound = float(bound)
        self.threshold = float(threshold)
        self.min_threshold = float(min_threshold)
        self.ema_decay = float(ema_decay)
        self.update_every = max(1, int(update_every))
        self.warmup_steps = int(warmup_steps)
        self.cell_size = 2.0 * self.bound / self.resolution
        self.sdf_band = float(sdf_band) if sdf_band is not None else math.sqrt(3.0) * self.cell_size
        self.chunk = int(chunk)
        self.band_widths = float(band_widths)
        n = self.resolution**3
        self.register_buffer("score", torch.zeros(n))
        self.register_buffer("occupied", torch.ones(n, dtype=torch.bool))
        #: cells held as they are by every update (a stylization inside a region: the source's cells outside it,
        #: so a ray that misses the region is sampled, hence rendered, exactly as the source renders it)
        self.register_buffer("keep", torch.zeros(n, dtype=torch.bool), persistent=False)
        self._warned_empty = False
        self._padded_cache: dict[str, Tensor] = {}
        self._padded_version: dict[str, tuple] = {}

    def _padded(self, name: str = "occupied") -> Tensor:
        """Buffer ``name`` (``occupied`` or ``score``) with a border of empty cells, flat [(r+2)^3]: a point
        outside the box falls in the border, so a lookup needs no inside test. Rebuilt when the buffer
        changes (update, load)."""
        buf = getattr(self, name)
        version = (buf.data_ptr(), buf._version, buf.device)
        if self._padded_version.get(name) != version:
            r = self.resolution
            pad = torch.zeros(r + 2, r + 2, r + 2, dtype=buf.dtype, device=buf.device)
            pad[1:-1, 1:-1, 1:-1] = buf.view(r, r, r)
            self._padded_cache[name], self._padded_version[name] = pad.reshape(-1), version
        return self._padded_cache[name]

    def _flat(self, u: Tensor) -> Tensor:
        """Flat index into :meth:`_padded` of grid coordinates ``u`` [...,3] (cell units, offset by the border)."""
        r2 = float(self.resolution + 2)
        u = u.clamp_(0.0, r2 - 0.5).floor_()
        if r2**3 <= 2**24:  # the flat index is exact in float32: one matmul instead of integer arithmetic
            with torch.autocast(u.device.type, enabled=False):  # a bfloat16 matmul rounds the index
                return (u.float() @ torch.tensor([r2 * r2, r2, 1.0], device=u.device)).long()
        ijk = u.long()
        return (ijk[..., 0] * int(r2) + ijk[..., 1]) * int(r2) + ijk[..., 2]

    @torch.no_grad()
    def query(self, x: Tensor) -> Tensor:
        """Occupancy (nearest cell) of points x [N,3] -> bool [N]; points outside the box are empty."""
        scale = self.resolution / (2.0 * self.bound)
        return self.at(self._flat((x.float() + self.bound) * scale + 1.0))

    @torch.no_grad()
    def ray_cells(self, rays_o: Tensor, rays_d: Tensor, t: Tensor) -> Tensor:
        """The cells of ``rays_o + t rays_d`` for ray parameters ``t`` [R,M] -> index [R,M] for :meth:`at`
        (without materialising the points in world units)."""
        scale = self.resolution / (2.0 * self.bound)
        u0 = (rays_o.float() + self.bound) * scale + 1.0
        return self._flat(torch.addcmul(u0[:, None, :], (rays_d.float() * scale)[:, None, :], t.float()[..., None]))

    def at(self, cells: Tensor, name: str = "occupied") -> Tensor:
        """Buffer ``name`` at the cells of :meth:`ray_cells`: ``occupied`` bool, or ``score`` float (0 outside
        the box)."""
        return self._padded(name)[cells]

    @torch.no_grad()
    def query_rays(self, rays_o: Tensor, rays_d: Tensor, t: Tensor) -> Tensor:
        """Occupancy at ``rays_o + t rays_d`` for ray parameters ``t`` [R,M] -> bool [R,M] (as :meth:`query`);
        through ``torch.compile`` when :attr:`compiled` is set (the same cells: one fused loop instead of
        [R,M,3] intermediates)."""
        if self.compiled and t.numel() > 1:
            scale = self.resolution / (2.0 * self.bound)
            u0 = (rays_o.float() + self.bound) * scale + 1.0
            try:
                return _compiled_cells_lookup()(self._padded("occupied"), u0, rays_d.float() * scale, t.float(),
                                                self.resolution + 2)
            except torch._dynamo.exc.TorchDynamoException as exc:  # the compiler's own failure: eager from now on
                self.compiled = False
                log.warning("compile: the occupancy lookup is evaluated uncompiled: the compiler failed (%s)",
                            type(exc).__name__)
        return self.at(self.ray_cells(rays_o, rays_d, t))

    def _cell_points(self, idx: Tensor, generator: Optional[torch.Generator] = None, centre: bool = False) -> Tensor:
        """One point in each cell ``idx`` [M] (flat, x slowest): uniformly at random, or its ``centre``."""
        r = self.resolution
        ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], -1).float()
        if centre:
            return (ijk + 0.5) * self.cell_size - self.bound
        jitter = torch.rand(ijk.shape, generator=generator, device=ijk.device if generator is None else generator.device)
        return (ijk + jitter.to(ijk.device)) * self.cell_size - self.bound

    @torch.no_grad()
    def update(self, field: "Field", step: int, force: bool = False, generator: Optional[torch.Generator] = None) -> bool:
        """Refresh from ``field.cell_occupancy`` if ``step % update_every == 0`` (or ``force``). Returns True if updated."""
        if not force and step % self.update_every != 0:
            return False
        device = self.score.device
        n = self.score.numel()
        if step < self.warmup_steps or force:
            idx = torch.arange(n, device=device)
        else:
            rand = torch.randperm(n, device=device)[: n // 4]
            idx = torch.unique(torch.cat([rand, self.occupied.nonzero()[:, 0]]))
        idx = idx[~self.keep[idx]]
        new = torch.empty(idx.shape[0], device=device)
        band = self.band(field)
        for s in range(0, idx.shape[0], self.chunk):
            pts = self._cell_points(idx[s : s + self.chunk], generator)
            new[s : s + self.chunk] = field.cell_occupancy(pts, self.cell_size, band)
        new = torch.nan_to_num(new, nan=1.0)  # a NaN field must not silently empty the grid
        self.score[idx] = torch.maximum(self.score[idx] * self.ema_decay, new)
        thr = field.occupancy_threshold
        if thr is None:  # density evidence: nerfacc's min(threshold, mean) with a floor
            thr = min(self.threshold, max(self.min_threshold, float(self.score.mean())))
        occupied = torch.where(self.keep, self.occupied, self.score > thr)
        if not bool(occupied.any()):
            # An empty grid is absorbing: no samples -> no gradient -> the field can never bring
            # its surface back (seen: NeuS + frequency encoding losing its surface for a few
            # hundred steps). Nothing occupied is never a valid scene, so fall back to sampling
            # everywhere until the field has a surface again.
            if not self._warned_empty:
                log.warning("occupancy grid step %d: no cell occupied (the field lost its surface); "
                            "sampling the whole box until it has one again", step)
                self._warned_empty = True
            occupied = torch.ones_like(occupied)
        self.occupied.copy_(occupied)
        log.debug("occupancy grid step %d: %.1f%% occupied", step, 100.0 * float(self.occupied.float().mean()))
        return True

    def cell_centres(self) -> Tensor:
        """[n^3, 3] the centre of every cell (field coordinates), in the grid's flat order."""
        return self._cell_points(torch.arange(self.score.numel(), device=self.score.device), None, centre=True)

    def band(self, field: "Field") -> float:
        """SDF band half-width (world units): ``max(sdf_band, band_widths * field.surface_width())``.

        Early in training the surface is blurry (VolSDF beta ~0.1, NeuS 1/inv_s
        ~0.05): samples up to a few widths away from the zero level set get
        weight and gradient, and the surface must be able to move there, so
        the band follows the field's current width and shrinks as it sharpens.
        """
        return max(self.sdf_band, self.band_widths * float(field.surface_width()))

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())


def _cells_lookup(padded: Tensor, u0: Tensor, step: Tensor, t: Tensor, side: int) -> Tensor:
    """``padded`` (flat [side^3]) at the cells of ``u0 + t step`` (grid units with the border: ``u0`` [R,3], ``step``
    [R,3], ``t`` [R,M]) -> [R,M]: :meth:`OccupancyGrid.ray_cells` and :meth:`OccupancyGrid.at` in one expression
    (integer flat index, exact like the eager float one)."""
    u = torch.addcmul(u0[:, None, :], step[:, None, :], t[..., None]).clamp(0.0, side - 0.5).floor().long()
    return padded[(u[..., 0] * side + u[..., 1]) * side + u[..., 2]]


_COMPILED_LOOKUP: Optional[object] = None


def _compiled_cells_lookup():  # noqa: ANN202 - a compiled callable
    """:func:`_cells_lookup` through ``torch.compile`` (dynamic shapes), made once."""
    global _COMPILED_LOOKUP
    if _COMPILED_LOOKUP is None:
        _COMPILED_LOOKUP = torch.compile(_cells_lookup, dynamic=True)
    return _COMPILED_LOOKUP
