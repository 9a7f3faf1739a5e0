"""Backbone-agnostic volume renderer (NeRF-Art Eq. 1).

The renderer places K sections per ray (stratified, or occupancy-guided when an
``OccupancyGrid`` is given), queries ``field.forward`` at the section
midpoints, converts to opacities with ``field.alpha`` and composites:
``rgb = sum_k w_k c_k + T_final * c_bg``, ``w_k = T_k alpha_k``.
"""

from __future__ import annotations

import copy
import math
from typing import Any, Callable, Optional, Sequence

import torch
import torch.nn as nn
from torch import Tensor

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.fields.compiled import evaluate
from nerfart_plugin.fields.field import Field
from nerfart_plugin.fields.occupancy import OccupancyGrid
from nerfart_plugin.rendering.samplers import occupancy_samples, ray_aabb, stratified_samples, weighted_samples
from nerfart_plugin.rendering.volume import block_weights, weights_from_alpha

__all__ = ["VolumeRenderer"]


class VolumeRenderer(nn.Module):
    """Render ray batches through a ``Field``.

    Args:
        field: any :class:`~nerfart_plugin.fields.field.Field` (only ``query``, ``alpha``, ``regularizers``
            and ``bound`` are used; the occupancy grid uses ``cell_occupancy``).
        num_samples: K sections per ray.
        background: optional direction-conditioned model ``c_bg(d)`` (e.g.
            ``EnvironmentMap``) composited with the remaining transmittance.
        occupancy: optional ``OccupancyGrid``; enables empty-space skipping.
        background_color: constant background ``(r,g,b)`` used when there is no
            background model (default white); ``None`` = no compositing (the
            remaining transmittance shows black). A batch may override it per
            ray with ``batch["bg_color"]`` ([R,3] or [3]), e.g. random
            backgrounds for masked training.
        num_coarse: coarse occupancy queries per ray for occupancy sampling
            (default: twice the occupancy grid resolution).
        clip_to_bound: restrict [near, far] to the ray's intersection with the
            field's box [-bound, bound]^3 (rays that miss it get zero-length
            sections and render the background).
        compact: query the field only at non-empty sections (``delta > 0``);
            empty ones are transparent anyway, so results are unchanged.
        stop_transmittance: no-grad renders (:meth:`render_chunked`, :meth:`march`) stop marching a
            ray once its transmittance falls below this, so each pixel (and opacity) changes by less
            than it (nerfacc's early ray termination); 0 marches every sample.
        march_block: samples per ray evaluated between two transmittance checks of :meth:`march`.
        occupancy_sampling: with a grid: ``occupied`` (uniform over the occupied cells,
            :func:`occupancy_samples`) or ``weighted`` (density fields: sections as dense as the grid's
            transmittance-weighted cell opacities, :func:`weighted_samples`).
        uniform_share: ``weighted``: share of the pdf spread uniformly over the occupied cells of a ray.
        view_samples: K of full views rendered without grad (:meth:`render_chunked`: validation,
            evaluation, videos); None: ``num_samples``. Taken only with an occupancy grid
            (:meth:`guided_samples`).
    """

    def __init__(
        self,
        field: Field,
        num_samples: int = 64,
        background: Optional[nn.Module] = None,
        occupancy: Optional[OccupancyGrid] = None,
        background_color: Optional[Sequence[float]] = (1.0, 1.0, 1.0),
        num_coarse: Optional[int] = None,
        clip_to_bound: bool = True,
        compact: bool = True,
        stop_transmittance: float = 1e-4,
        march_block: int = 4,
        view_samples: Optional[int] = None,
        occupancy_sampling: str = "occupied",
        uniform_share: float = 0.2,
    ) -> None:
        super().__init__()
        self.compact = bool(compact)
        self.stop_transmittance = float(stop_transmittance)
        self.march_block = max(1, int(march_block))
        self.field = field
        self.num_samples = int(num_samples)
        self.background = background
        self.occupancy = occupancy
        if occupancy_sampling not in ("occupied", "weighted"):
            raise ConfigError(f"render.occupancy.sampling={occupancy_sampling!r}: use occupied or weighted.")
        if occupancy_sampling == "weighted" and field.occupancy_threshold is not None:
            raise ConfigError("render.occupancy.sampling=weighted reads cell opacities, and this field's grid "
                              "scores a shell around an SDF surface: use a density backbone (backbone=nerf) or "
                              "render.occupancy.sampling=occupied.")
        self.occupancy_sampling = occupancy_sampling
        self.uniform_share = float(uniform_share)
        self.view_samples = self.guided_samples(view_samples)
        if num_coarse is None:  # ~2 bins per cell crossed: with the sampler's 1-bin dilation no cell is missed
            num_coarse = 2 * occupancy.resolution if occupancy is not None else 256
        self.num_coarse = int(num_coarse)
        self.clip_to_bound = bool(clip_to_bound)
        if background_color is None:
            self.background_color: Optional[Tensor] = None
        else:
            self.register_buffer("background_color", torch.tensor(list(background_color), dtype=torch.float32), persistent=False)

    # ------------------------------------------------------------------------------------------
    @property
    def occupied_fraction(self) -> Optional[float]:
        """Share of occupied cells of the occupancy grid (None without a grid)."""
        return self.occupancy.occupied_fraction if self.occupancy is not None else None

    def guided_samples(self, k: Optional[int]) -> Optional[int]:
        """``k`` where the occupancy grid places the samples at the surface, so that a few per ray render the
        scene (``render.view_samples``, ``stylize.num_samples``); None without a grid (e.g. NDC captures), whose
        uniform samples need :attr:`num_samples`, the density the field was trained with."""
        return int(k) if k and self.occupancy is not None else None

    def with_field(self, field: Any, share_occupancy: bool = True) -> "VolumeRenderer":
        """This renderer (its sampling settings, background) rendering ``field`` instead: a composite of this
        field with others (:class:`~nerfart_plugin.fields.composite.CompositeField`). The occupancy grid is
        shared (``share_occupancy``: a grid updated through either renderer serves both, as a stylization
        inside a region trains) or copied."""
        out = copy.copy(self)
        out._modules = dict(self._modules)
        out._modules["field"] = field
        if not share_occupancy and self.occupancy is not None:
            out._modules["occupancy"] = copy.deepcopy(self.occupancy)
        return out

    def reduce_samples(self, k: Optional[int]) -> Optional[int]:
        """Sample ``k`` per ray in training and full views where :meth:`guided_samples` allows it (the
        stylization's ``stylize.num_samples``); elsewhere keep :attr:`num_samples` for both. Returns the K taken."""
        self.view_samples = self.guided_samples(k)
        if self.view_samples:
            self.num_samples = self.view_samples
        return self.view_samples

    @torch.no_grad()
    def update_occupancy(self, step: int, force: bool = False) -> bool:
        """Refresh the occupancy grid from the field (see :meth:`OccupancyGrid.update`); False without a grid."""
        return self.occupancy.update(self.field, step, force=force) if self.occupancy is not None else False

    def widen_occupancy_band(self, cells: float) -> None:
        """Sample at least ``cells`` occupancy cells around an SDF surface (no-op without a grid)."""
        if self.occupancy is not None:
            self.occupancy.sdf_band = max(self.occupancy.sdf_band, float(cells) * self.occupancy.cell_size)

    def ray_bounds(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
        """[near, far] per ray, clipped to the field's box if ``clip_to_bound`` (near == far if it misses)."""
        near = near.float().reshape(-1)
        far = far.float().reshape(-1)
        if self.clip_to_bound:
            t0, t1 = ray_aabb(rays_o, rays_d, self.field.bound)
            near = torch.maximum(near, t0)
            far = torch.minimum(far, t1)
        far = torch.maximum(far, near)
        return near, far

    def sample(self, batch: dict[str, Any], perturb: bool, generator: Optional[torch.Generator] = None,
               num_samples: Optional[int] = None) -> Tensor:
        """``t_samples`` [R,K,2] (section start/end in ray parameter), no grad; K = ``num_samples`` (default
        :attr:`num_samples`)."""
        rays_o, rays_d = batch["rays_o"], batch["rays_d"]
        near, far = self.ray_bounds(rays_o, rays_d, batch["near"], batch["far"])
        k = int(num_samples or self.num_samples)
        if self.occupancy is not None and self.occupancy_sampling == "weighted":
            return weighted_samples(rays_o, rays_d, near, far, self.occupancy, k, self.num_coarse, perturb, generator,
                                    self.uniform_share)
        if self.occupancy is not None:
            return occupancy_samples(rays_o, rays_d, near, far, self.occupancy, k, self.num_coarse, perturb, generator)
        return stratified_samples(near, far, k, perturb, generator)

    def _background(self, batch: dict[str, Any], dirs: Tensor) -> Optional[Tensor]:
        if "bg_color" in batch and batch["bg_color"] is not None:
            return torch.as_tensor(batch["bg_color"], dtype=torch.float32, device=dirs.device).expand(dirs.shape[0], 3)
        if self.background is not None:
            return self.background(dirs).float()
        if self.background_color is not None:
            return self.background_color.to(dirs.device).expand(dirs.shape[0], 3)
        return None

    # ------------------------------------------------------------------------------------------
    def forward(
        self,
        batch: dict[str, Any],
        perturb: bool = False,
        t_samples: Optional[Tensor] = None,
        generator: Optional[torch.Generator] = None,
        with_normals: bool = True,
    ) -> dict[str, Tensor]:
        """Render rays ``batch`` (``rays_o`` [R,3], ``rays_d`` [R,3], ``near`` [R], ``far`` [R]).

        Returns a dict with ``rgb`` [R,3], ``depth`` [R] (expected ray
        parameter of termination ``sum w t / opacity``, clamped to the sampled
        range; for NDC rays it is NDC t), ``opacity`` [R] (``sum w``),
        ``weights`` [R,K], ``t`` [R,K] (section midpoints), ``deltas`` [R,K]
        (section lengths ``(t_end - t_start) ||rays_d||``), ``t_samples``
        [R,K,2] (pass back to reproduce the same samples); SDF fields add
        ``normal`` [R,3] (``sum w n``; with ``with_normals=False`` a no-grad
        render may omit it and skip the gradient taps) and, when grad is enabled,
        ``regularizers``: the field's regularizer terms (a dict of 0-dim tensors, e.g. ``eikonal``: the
        mean over samples of ``(|grad sdf| - 1)^2``, ``grid_tv``), see ``Field.regularizers``.
        """
        _check_ray_batch(batch)
        rays_o = batch["rays_o"].float()
        rays_d = batch["rays_d"].float()
        R, K = rays_o.shape[0], self.num_samples
        if t_samples is None:
            t_samples = self.sample(batch, perturb, generator)
        elif t_samples.shape[:1] != (R,) or t_samples.shape[-1] != 2:
            raise DataError(f"t_samples has shape {tuple(t_samples.shape)}, expected [{R},K,2]: pass back the 't_samples' a previous call returned.")
        t_samples = t_samples.detach()
        K = t_samples.shape[1]
        t_start, t_end = t_samples[..., 0], t_samples[..., 1]
        t = 0.5 * (t_start + t_end)  # [R,K]
        d_norm = rays_d.norm(dim=-1, keepdim=True)  # [R,1]
        deltas = (t_end - t_start).clamp_min(0.0) * d_norm
        dirs = rays_d / d_norm.clamp_min(1e-12)  # unit
        pts = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]  # [R,K,3]
        dirs_k = dirs[:, None, :].expand(R, K, 3)

        out, reg_out = self._query_field(pts.reshape(-1, 3), dirs_k.reshape(-1, 3), deltas.reshape(-1) > 0,
                                         with_normals)
        alpha = self.field.alpha(out, deltas, dirs_k).float()
        alpha = torch.where(deltas > 0, alpha, torch.zeros_like(alpha))  # zero-length section = transparent
        weights, _ = weights_from_alpha(alpha)
        normal_k = out["normal"].reshape(R, K, 3).float() if "normal" in out else None
        result = self._composite(batch, dirs, t_samples, weights, out["rgb"].reshape(R, K, 3).float(), normal_k)
        result["deltas"] = deltas
        if torch.is_grad_enabled():
            result["regularizers"] = self.field.regularizers(reg_out)
        return result

    def _composite(self, batch: dict[str, Any], dirs: Tensor, t_samples: Tensor, weights: Tensor, rgb_k: Tensor,
                   normal_k: Optional[Tensor]) -> dict[str, Tensor]:
        """Eq. 1 from the weights [R,K] and per-sample colours [R,K,3] (normals [R,K,3] or None) of the
        sections ``t_samples`` [R,K,2] along unit ``dirs`` [R,3]: :meth:`forward`'s ``rgb``, ``depth``,
        ``opacity``, ``weights``, ``t``, ``t_samples`` and ``normal``."""
        t_start, t_end = t_samples[..., 0], t_samples[..., 1]
        t = 0.5 * (t_start + t_end)
        opacity = weights.sum(-1)
        rgb = (weights[..., None] * rgb_k).sum(-2)
        bg = self._background(batch, dirs)
        if bg is not None:
            rgb = rgb + (1.0 - opacity).clamp_min(0.0)[..., None] * bg
        depth = (weights * t).sum(-1) / opacity.clamp_min(1e-10)
        depth = torch.minimum(torch.maximum(depth, t_start[:, 0]), t_end[:, -1])
        result: dict[str, Tensor] = {
            "rgb": rgb, "depth": depth, "opacity": opacity, "weights": weights, "t": t, "t_samples": t_samples,
        }
        if normal_k is not None:
            result["normal"] = (weights[..., None] * normal_k).sum(-2)
        return result

    def _query_field(self, x: Tensor, d: Tensor, valid: Tensor,
                     with_normals: bool = True) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """``field(x, d)`` evaluated only where ``valid`` [N] (non-empty sections), zero-filled elsewhere.

        Occupancy sampling gives rays that miss every occupied cell zero-length
        sections (transparent whatever the field says); skipping them saves
        most of the field cost on object captures. Returns ``(out [N,...],
        compact_out)``; the regularizers use ``compact_out`` (valid samples only).
        """
        n = x.shape[0]
        if not self.compact or bool(valid.all()):
            out = evaluate(self.field, x, d, with_normal=with_normals)
            return out, out
        idx = valid.nonzero()[:, 0]
        if idx.numel() == 0:  # keep shapes/graph alive: evaluate one (transparent) sample
            idx = torch.zeros(1, dtype=torch.long, device=x.device)
        sub = evaluate(self.field, x.index_select(0, idx), d.index_select(0, idx), with_normal=with_normals)
        full = {}
        for k, v in sub.items():
            if torch.is_tensor(v) and v.dim() >= 1 and v.shape[0] == idx.shape[0]:
                full[k] = v.new_zeros((n, *v.shape[1:])).index_copy(0, idx, v)
            else:
                full[k] = v
        return full, sub

    @torch.no_grad()
    def march(self, batch: dict[str, Any], perturb: bool = False, t_samples: Optional[Tensor] = None,
              generator: Optional[torch.Generator] = None, with_normals: bool = True,
              num_samples: Optional[int] = None) -> dict[str, Tensor]:
        """No-grad render with early ray termination: the same image as :meth:`forward`, cheaper.

        The K sections of each ray are evaluated ``march_block`` at a time, front to back, and
        only on rays still visible: a ray leaves once its transmittance is below
        ``stop_transmittance`` (so its colour, opacity and depth weights change by less than
        that), and rays with no non-empty section (they miss the occupancy grid) are never
        evaluated. A field whose opacity reads following samples (``Field.alpha_lookahead``,
        e.g. NeuS' section estimate) gets them evaluated with each block.

        Returns ``rgb`` [R,3], ``depth`` [R], ``opacity`` [R] (``normal`` [R,3] for SDF fields
        unless ``with_normals=False``) and ``t_samples`` [R,K,2] in which the sections no longer
        needed (behind the stop, beyond the lookahead) have zero length: passed back to
        :meth:`forward` (the two-pass backprop of Section 4.4) they render the same pixels
        without evaluating those sections. ``samples_evaluated`` is a 0-dim count. ``num_samples``: K
        when sampling here (default :attr:`num_samples`).
        """
        if t_samples is None:
            t_samples = self.sample(batch, perturb, generator, num_samples)
        if self.stop_transmittance <= 0:
            out = self.forward(batch, t_samples=t_samples, with_normals=with_normals)
            n = int((out["deltas"] > 0).sum())
            keep = ("rgb", "depth", "opacity", "normal", "t_samples")
            return {**{k: out[k] for k in keep if k in out}, "samples_evaluated": torch.tensor(n)}
        rays_o, rays_d = batch["rays_o"].float(), batch["rays_d"].float()
        t_start, t_end = t_samples[..., 0], t_samples[..., 1]
        d_norm = rays_d.norm(dim=-1, keepdim=True)
        dirs = rays_d / d_norm.clamp_min(1e-12)
        t, deltas = 0.5 * (t_start + t_end), (t_end - t_start).clamp_min(0.0) * d_norm
        acc = _MarchState(t.shape[0], rays_o.device)
        log_stop = math.log(self.stop_transmittance)

        def composite(idx: Tensor, b0: int, b1: int, w1: int, out: dict[str, Tensor], compact: dict[str, Tensor],
                      alpha: Tensor) -> Tensor:
            acc.add(idx, alpha, t[idx, b0:b1], out, w1 - b0)
            return acc.log_t[idx] < log_stop

        stop_at = self._march_blocks(rays_o, rays_d, dirs, t, deltas, with_normals, composite)
        if acc.evaluated == 0:  # every ray missed: one probe sample tells which outputs the field gives
            probe = self.field.query(rays_o[:1], dirs[:1], with_normal=with_normals)
            if "normal" in probe:
                acc.normal = torch.zeros_like(acc.rgb)
        result = acc.finish(self._background(batch, dirs), t_start[:, 0], t_end[:, -1])
        result["t_samples"] = self._collapse_behind_stop(t_samples, stop_at)
        result["samples_evaluated"] = torch.tensor(acc.evaluated)
        return result

    def _collapse_behind_stop(self, t_samples: Tensor, stop_at: Tensor) -> Tensor:
        """``t_samples`` [R,K,2] with zero length from each ray's ``stop_at`` [R] on, past the samples the
        field's opacities read (:attr:`Field.alpha_lookahead`): what a re-render need not evaluate."""
        t_start, t_end = t_samples[..., 0], t_samples[..., 1]
        look = int(self.field.alpha_lookahead)
        collapse = torch.arange(t_samples.shape[1], device=t_samples.device)[None, :] >= (stop_at + look)[:, None]
        return torch.stack([t_start, torch.where(collapse, t_start, t_end)], dim=-1)

    def _march_blocks(self, rays_o: Tensor, rays_d: Tensor, dirs: Tensor, t: Tensor, deltas: Tensor,
                      with_normals: bool, composite: Callable[..., Tensor]) -> Tensor:
        """Evaluate sections ``t``/``deltas`` [R,K] front to back, ``march_block`` at a time, on the rays still
        visible (rays that miss the occupancy grid are never evaluated), and hand each block to
        ``composite(idx [n], b0, b1, w1, out, compact, alpha [n,b1-b0]) -> stops [n] bool`` (the field's output on
        sections ``b0:w1``, the block and the samples its opacities read: :meth:`_evaluate_block`), which
        composites it and says which of the rays ``idx`` stop there. Returns, per ray, the first section not
        evaluated [R] (K if none)."""
        R, K = t.shape
        look = int(self.field.alpha_lookahead)
        active = (deltas > 0).any(-1)
        stop_at = torch.full((R,), K, dtype=torch.long, device=t.device)
        for b0 in range(0, K, self.march_block):
            idx = active.nonzero()[:, 0]
            if idx.numel() == 0:
                break
            b1 = min(K, b0 + self.march_block)
            w1 = min(K, b1 + look)
            out, compact, alpha = self._evaluate_block(rays_o, rays_d, dirs, t, deltas, idx, b0, b1, w1, with_normals)
            done = idx[composite(idx, b0, b1, w1, out, compact, alpha)]
            stop_at[done] = b1
            active[done] = False
        return stop_at

    def _evaluate_block(self, rays_o: Tensor, rays_d: Tensor, dirs: Tensor, t: Tensor, deltas: Tensor, idx: Tensor,
                        b0: int, b1: int, w1: int, with_normals: bool) -> tuple[dict[str, Tensor], dict[str, Tensor], Tensor]:
        """The field on sections ``b0:w1`` (a block ``b0:b1`` and the samples its opacities read) of rays ``idx``:
        its output over the [n, w1-b0] samples, its compact output (:meth:`_query_field`) and the block's
        opacities [n, b1-b0] (zero on empty sections)."""
        dl = deltas[idx, b0:w1]
        pts = rays_o[idx, None, :] + rays_d[idx, None, :] * t[idx, b0:w1, None]
        dk = dirs[idx, None, :].expand(-1, w1 - b0, 3)
        out, compact = self._query_field(pts.reshape(-1, 3), dk.reshape(-1, 3), dl.reshape(-1) > 0, with_normals)
        alpha = self.field.alpha(out, dl, dk).float()
        return out, compact, torch.where(dl > 0, alpha, torch.zeros_like(alpha))[:, : b1 - b0]

    def march_with_grad(self, batch: dict[str, Any], perturb: bool = False,
                        generator: Optional[torch.Generator] = None, with_normals: bool = True) -> dict[str, Tensor]:
        """:meth:`march` with grad: early ray termination for a view rendered once and back-propagated
        later through the kept graph (``stylize.backprop=retain``), instead of a no-grad render and a
        re-render at the same samples.

        Sections are sampled here (``perturb``, ``generator``) and evaluated ``march_block`` at a time on
        the rays still visible, as :meth:`march`; the stop is decided on values, the compositing is
        differentiable. Returns :meth:`forward`'s keys (``weights`` [R,K] are zero behind each ray's stop;
        ``t_samples``, ``t`` and ``deltas`` as :meth:`march` returns them: the sections no longer needed
        have zero length), ``regularizers`` over every evaluated sample, and ``samples_evaluated``.
        """
        _check_ray_batch(batch)
        t_samples = self.sample(batch, perturb, generator).detach()
        if self.stop_transmittance <= 0:
            return self.forward(batch, t_samples=t_samples, with_normals=with_normals)
        rays_o, rays_d = batch["rays_o"].float(), batch["rays_d"].float()
        R, K = t_samples.shape[:2]
        t_start, t_end = t_samples[..., 0], t_samples[..., 1]
        d_norm = rays_d.norm(dim=-1, keepdim=True)
        dirs = rays_d / d_norm.clamp_min(1e-12)
        t, deltas = 0.5 * (t_start + t_end), (t_end - t_start).clamp_min(0.0) * d_norm
        blocks: list[dict[str, Any]] = []
        stop_at = self._march_blocks(rays_o, rays_d, dirs, t, deltas, with_normals, _GradBlocks(blocks, R, t, deltas,
                                                                                                self.stop_transmittance))
        kept = self._collapse_behind_stop(t_samples, stop_at)
        if not blocks:  # every ray misses the occupancy grid: forward keeps the graph alive with one probe
            return self.forward(batch, t_samples=kept, with_normals=with_normals)
        rows = torch.cat([b["rows"].reshape(-1) for b in blocks])
        cols = torch.cat([b["cols"].reshape(-1) for b in blocks])

        def scatter(key: str, *shape: int) -> Tensor:
            values = torch.cat([b[key].reshape(-1, *shape) for b in blocks])
            return values.new_zeros(R, K, *shape).index_put((rows, cols), values)

        weights = scatter("weights")
        normal_k = scatter("normal", 3) if "normal" in blocks[0] else None
        result = self._composite(batch, dirs, kept, weights, scatter("rgb", 3), normal_k)
        result["deltas"] = (kept[..., 1] - kept[..., 0]).clamp_min(0.0) * d_norm
        result["regularizers"] = self.field.regularizers(_concat_samples([b["compact"] for b in blocks]))
        result["samples_evaluated"] = torch.tensor(sum(b["evaluated"] for b in blocks))
        return result


    @torch.no_grad()
    def render_chunked(self, batch: dict[str, Any], chunk: int = 8192, perturb: bool = False,
                       with_normals: bool = True) -> dict[str, Tensor]:
        """Render a large ray batch (e.g. a full view) in chunks without grad (:meth:`march`) with
        :attr:`view_samples` samples per ray.

        Returns ``rgb`` [R,3], ``depth`` [R], ``opacity`` [R] (and ``normal``
        [R,3] for SDF fields unless ``with_normals=False``), concatenated over chunks; ints ``H``/``W`` in the
        batch are passed through unchanged.
        """
        R = batch["rays_o"].shape[0]
        keys = ("rgb", "depth", "opacity", "normal")
        parts: dict[str, list[Tensor]] = {}
        for s in range(0, R, int(chunk)):
            sub = {k: (v[s : s + chunk] if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == R else v)
                   for k, v in batch.items()}
            res = self.march(sub, perturb=perturb, with_normals=with_normals, num_samples=self.view_samples)
            for k in keys:
                if k in res:
                    parts.setdefault(k, []).append(res[k])
        merged: dict[str, Any] = {k: torch.cat(v, 0) for k, v in parts.items()}
        for k in ("H", "W"):
            if k in batch:
                merged[k] = batch[k]
        return merged


class _GradBlocks:
    """The compositing of :meth:`VolumeRenderer.march_with_grad`'s blocks: each block's differentiable weights
    [n,B], colours [n,B,3] (normals), their ``rows``/``cols`` in [R,K] and the field's compact output, appended to
    ``blocks``; the log transmittance in front of the next block is kept differentiable."""

    def __init__(self, blocks: list[dict[str, Any]], R: int, t: Tensor, deltas: Tensor, stop_transmittance: float):
        self.blocks, self.t, self.deltas = blocks, t, deltas
        self.log_t = torch.zeros(R, device=t.device)
        self.log_stop = math.log(stop_transmittance)

    def __call__(self, idx: Tensor, b0: int, b1: int, w1: int, out: dict[str, Tensor], compact: dict[str, Tensor],
                 alpha: Tensor) -> Tensor:
        alpha = alpha.clamp(0.0, 1.0)  # as weights_from_alpha, so the weights are forward's
        weights, log_t_block = block_weights(alpha, self.log_t[idx])
        device = self.t.device
        block = {"weights": weights, "rows": idx[:, None].expand(-1, b1 - b0),
                 "cols": torch.arange(b0, b1, device=device).expand(idx.numel(), -1),
                 "evaluated": int(idx.numel() * (w1 - b0))}
        for key in ("rgb", "normal"):
            if key in out:
                block[key] = out[key].reshape(-1, w1 - b0, 3)[:, : b1 - b0].float()
        self.log_t = self.log_t.index_add(0, idx, log_t_block)
        stops = self.log_t.detach()[idx] < self.log_stop
        # each sample once in the regularizers: a lookahead sample joins the next block, unless the ray stops
        own = (torch.arange(b0, w1, device=device)[None, :] < b1) | stops[:, None]
        block["compact"] = _select_samples(compact, own.reshape(-1), self.deltas[idx, b0:w1].reshape(-1) > 0)
        self.blocks.append(block)
        return stops


class _MarchState:
    """Per-ray sums of :meth:`VolumeRenderer.march`: log transmittance, colour, depth, opacity, normal."""

    def __init__(self, n: int, device: torch.device) -> None:
        self.log_t = torch.zeros(n, device=device)
        self.rgb = torch.zeros(n, 3, device=device)
        self.depth = torch.zeros(n, device=device)
        self.opacity = torch.zeros(n, device=device)
        self.normal: Optional[Tensor] = None
        self.evaluated = 0

    def add(self, idx: Tensor, alpha: Tensor, t: Tensor, out: dict[str, Tensor], width: int) -> None:
        """Composite one block: ``alpha`` [n,B] and midpoints ``t`` [n,B] of rays ``idx`` [n]; ``out``
        the field's output over [n, width] samples (the block plus its lookahead)."""
        n, B = alpha.shape
        w, log_t_block = block_weights(alpha, self.log_t[idx])
        self.rgb[idx] += (w[..., None] * out["rgb"].reshape(n, width, 3)[:, :B].float()).sum(1)
        self.depth[idx] += (w * t).sum(-1)
        self.opacity[idx] += w.sum(-1)
        if "normal" in out:
            if self.normal is None:
                self.normal = torch.zeros_like(self.rgb)
            self.normal[idx] += (w[..., None] * out["normal"].reshape(n, width, 3)[:, :B].float()).sum(1)
        self.log_t[idx] += log_t_block
        self.evaluated += int(n * width)

    def finish(self, bg: Optional[Tensor], t_first: Tensor, t_last: Tensor) -> dict[str, Tensor]:
        rgb = self.rgb
        if bg is not None:
            rgb = rgb + (1.0 - self.opacity).clamp_min(0.0)[..., None] * bg
        depth = self.depth / self.opacity.clamp_min(1e-10)
        result = {"rgb": rgb, "depth": torch.minimum(torch.maximum(depth, t_first), t_last), "opacity": self.opacity}
        if self.normal is not None:
            result["normal"] = self.normal
        return result


def _concat_samples(parts: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One field output from several calls: per-sample tensors concatenated, other entries from the first."""
    first = parts[0]
    return {k: (torch.cat([p[k] for p in parts]) if torch.is_tensor(v) and v.dim() >= 1 else v)
            for k, v in first.items()}


def _check_ray_batch(batch: dict[str, Any]) -> None:
    for key in ("rays_o", "rays_d", "near", "far"):
        if key not in batch:
            raise DataError(f"ray batch lacks {key!r}; build it with nerfart_plugin.data.rays (keys rays_o, rays_d, "
                            "near, far).")


def _select_samples(out: dict[str, Any], keep: Tensor, valid: Tensor) -> dict[str, Any]:
    """The samples ``keep`` [N] of a :meth:`VolumeRenderer._query_field` output over N samples, whichever
    way they were evaluated: all N, or only the ``valid`` [N] ones (compact). A lone probe sample stays."""
    n = next((int(v.shape[0]) for v in out.values() if torch.is_tensor(v) and v.dim() >= 1), 0)
    if n == keep.numel():
        rows = keep
    elif n == int(valid.sum()) and n > 0:
        rows = keep[valid]
    else:  # the probe of a block without a non-empty section
        return out
    return {k: (v[rows] if torch.is_tensor(v) and v.dim() >= 1 and v.shape[0] == n else v) for k, v in out.items()}
