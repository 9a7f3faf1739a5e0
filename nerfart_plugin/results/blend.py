"""The strength dial and style mixing, without retraining.

A stylization fine-tunes a copy of its source field, so every stylization of one source has the same
tensors and differs from it by a delta. Blending the deltas,

    θ = θ_src + Σ_i w_i · (θ_i − θ_src),

renders a view-consistent field for any weights: one run at weight ``s`` is the strength dial
(``s = 0`` the source, ``s = 1`` the run, ``s > 1`` past it), several runs with weights mix their styles.

Only floating-point tensors are blended (in float64, then cast back). The occupancy grid is not: its
buffers describe where *a* field is non-empty, so the blended field gets its own grid, estimated afresh
from the blended field (:func:`refresh_occupancy`). At the two ends no arithmetic is done: weights that
select one field (all zero: the source; one run at 1: that run) load that field's own tensors and grid,
so ``s = 0`` and ``s = 1`` reproduce the source and the run exactly.
"""

from __future__ import annotations

import copy
from typing import Any, Sequence

import torch
from torch import Tensor

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.utils.io import config_hash

#: the documented range of the strength dial (``strength=``, ``Run.with_strength``)
STRENGTH_RANGE = (0.0, 2.0)
#: the documented range of each weight of a mix (``api.mix``)
WEIGHT_RANGE = (-1.0, 2.0)
#: state-dict prefix of the renderer's occupancy grid (estimated for the blended field, never blended)
OCCUPANCY_PREFIX = "occupancy."
#: forced grid updates, one jittered point per cell each, that estimate a blended field's grid
OCCUPANCY_PASSES = 2


def check_strength(s: float, key: str = "strength") -> float:
    """``s`` as a float in :data:`STRENGTH_RANGE`, else a ConfigError naming ``key``."""
    lo, hi = STRENGTH_RANGE
    try:
        value = float(s)
    except (TypeError, ValueError):
        value = float("nan")
    if not lo <= value <= hi:  # NaN fails too
        raise ConfigError(f"{key}={s!r}: the style strength runs from {lo:g} (the source) through 1 (the run as "
                          f"trained) to {hi:g} (twice its change); pick a value in [{lo:g}, {hi:g}].")
    return value


def check_weights(weights: Sequence[float], n_runs: int) -> list[float]:
    """One weight per run, each in :data:`WEIGHT_RANGE`, else a ConfigError."""
    lo, hi = WEIGHT_RANGE
    if len(weights) != n_runs or n_runs == 0:
        raise ConfigError(f"mix: {n_runs} run(s) and {len(weights)} weight(s); give one weight per run.")
    out = []
    for i, w in enumerate(weights):
        try:
            value = float(w)
        except (TypeError, ValueError):
            value = float("nan")
        if not lo <= value <= hi:
            raise ConfigError(f"mix weight {i} = {w!r}: each weight must lie in [{lo:g}, {hi:g}] (0: leave that "
                              "style out, 1: all of it).")
        out.append(value)
    return out


def blend_states(source: dict[str, Tensor], styles: Sequence[dict[str, Tensor]],
                 weights: Sequence[float]) -> dict[str, Tensor]:
    """``source + Σ w_i (style_i − source)`` for every floating-point tensor outside the occupancy grid (in
    float64, cast back to each tensor's dtype); other tensors are the source's. Raises ConfigError when a
    style's tensors do not match the source's (names or shapes)."""
    out: dict[str, Tensor] = {}
    for name, base in source.items():
        for i, style in enumerate(styles):
            if name not in style or style[name].shape != base.shape:
                raise ConfigError(f"mix: run {i} has no tensor {name!r} of shape {tuple(base.shape)}: it is not a "
                                  "stylization of this source.")
        if not base.is_floating_point() or name.startswith(OCCUPANCY_PREFIX):
            out[name] = base.clone()
            continue
        acc = base.double()
        for style, w in zip(styles, weights):
            acc = acc + float(w) * (style[name].to(base.device).double() - base.double())
        out[name] = acc.to(base.dtype)
    return out


@torch.no_grad()
def refresh_occupancy(renderer: Any, passes: int = OCCUPANCY_PASSES) -> None:
    """Estimate the renderer's occupancy grid from its current field: scores cleared, then ``passes`` forced
    updates over every cell (fixed seeds: the same field gets the same grid), but the cells the grid holds
    (``keep``: outside every region of a composite). No-op without a grid."""
    grid = getattr(renderer, "occupancy", None)
    if grid is None:
        return
    grid.score[~grid.keep] = 0.0  # cells held (outside a region) keep the source's evidence
    for i in range(passes):
        gen = torch.Generator(device=grid.score.device).manual_seed(i)
        grid.update(renderer.field, step=0, force=True, generator=gen)


def blended_renderer(template: Any, source: Any, styles: Sequence[Any], weights: Sequence[float]) -> Any:
    """A copy of ``template`` (a stylization's renderer: its sampling settings) holding the blend of
    ``source`` and ``styles`` (renderers) with ``weights``; the ends load one field's own tensors."""
    out = copy.deepcopy(template)
    nonzero = [(r, w) for r, w in zip(styles, weights) if w != 0.0]
    if not nonzero:
        out.load_state_dict(source.state_dict())
    elif len(nonzero) == 1 and nonzero[0][1] == 1.0:
        out.load_state_dict(nonzero[0][0].state_dict())
    else:
        out.load_state_dict(blend_states(source.state_dict(), [r.state_dict() for r in styles], weights))
        refresh_occupancy(out)
    return out.eval()


def blend_tag(weights: Sequence[float], runs: Sequence[str] = ()) -> str:
    """The file-name part of a blend: "" for one run at 1, ``-s0.50`` for one run at 0.5, and for a mix its
    weights and a short hash of its ``runs`` (their folders, in order): ``-mix0.50_0.50-1a2b3c``."""
    if len(weights) == 1:
        return "" if weights[0] == 1.0 else f"-s{weights[0]:.2f}"

    return "-mix" + "_".join(f"{w:.2f}" for w in weights) + f"-{config_hash(list(runs), n=6)}"
