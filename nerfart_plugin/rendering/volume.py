"""Volume-rendering primitives (NeRF-Art Eq. 1): opacities and densities to compositing weights (the fields
turn their geometry into opacity: :mod:`nerfart_plugin.fields.opacity`).

Every function here computes in float32 (inputs are up-cast) so that they stay
finite under float16/bfloat16 autocast, and every one of them returns finite
values *and* finite gradients for the extreme inputs listed in its docstring
(checked by ``tests/test_stability_rendering.py``).

Epsilons and clamps (and why)
-----------------------------
* ``volume_weights``: ``sigma`` and ``deltas`` are clamped at 0 (negative
  optical depth is meaningless and would make T > 1). No epsilon: the
  transmittance is ``exp(-exclusive_cumsum(sigma*delta))`` which is exact for
  sigma = 0, sigma = 1e8, delta = 0 (near == far) alike.
* ``weights_from_alpha``: ``1 - alpha`` is clamped to ``>= ALPHA_T_EPS`` (1e-10)
  before the log, so the log-space cumulative product never sees ``log(0)``
  (whose gradient is infinite). Effect: after a fully opaque sample the
  transmittance is 1e-10 instead of 0, i.e. invisible (< 1/2^32 of a colour).
"""

from __future__ import annotations

import torch
from torch import Tensor

ALPHA_T_EPS = 1e-10

__all__ = [
    "volume_weights",
    "weights_from_alpha",
    "block_weights",
    "exclusive_cumsum",
    "ALPHA_T_EPS",
]


def exclusive_cumsum(x: Tensor) -> Tensor:
    """``y_k = sum_{j<k} x_j`` along the last dim (``y_0 = 0``), without the cancellation of ``cumsum(x) - x``."""
    zeros = torch.zeros_like(x[..., :1])
    return torch.cat([zeros, torch.cumsum(x[..., :-1], dim=-1)], dim=-1)


def volume_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """NeRF-Art Eq. 1 volume-rendering weights from densities.

    ``w_k = T_k (1 - exp(-sigma_k delta_k))``, ``T_k = exp(-sum_{j<k} sigma_j delta_j)``.

    Args:
        sigma: [R,K] densities (1/length), clamped at 0.
        deltas: [R,K] segment lengths (same length unit), clamped at 0.

    Returns:
        ``(weights [R,K], transmittance [R,K])`` in float32; ``T_0 = 1``.

    Stable (finite values and gradients) for sigma in [0, 1e8], delta = 0 and
    near == far: the optical depth is accumulated with an exclusive cumsum and
    exponentiated once (log-space product), and ``1 - exp(-x)`` is ``-expm1(-x)``.
    """
    tau = sigma.float().clamp_min(0.0) * deltas.float().clamp_min(0.0)  # optical depth per segment
    transmittance = torch.exp(-exclusive_cumsum(tau))
    alpha = -torch.expm1(-tau)
    return transmittance * alpha, transmittance


def weights_from_alpha(alpha: Tensor) -> tuple[Tensor, Tensor]:
    """Eq. 1 weights from per-sample opacities: ``w_k = T_k alpha_k``, ``T_k = prod_{j<k}(1 - alpha_j)``.

    The exclusive cumulative product is evaluated in log space,
    ``T = exp(exclusive_cumsum(log(max(1 - alpha, ALPHA_T_EPS))))``: this avoids the
    division-by-element backward of ``torch.cumprod`` (unbounded gradients when a
    factor is ~0) and ``log(0)``. The clamp makes T after an opaque sample 1e-10
    rather than exactly 0 (see module docstring).

    Args:
        alpha: [R,K] opacities in [0,1] (clamped to [0,1]).

    Returns:
        ``(weights [R,K], transmittance [R,K])`` in float32.
    """
    alpha = alpha.float().clamp(0.0, 1.0)
    log_one_minus = torch.log((1.0 - alpha).clamp_min(ALPHA_T_EPS))
    transmittance = torch.exp(exclusive_cumsum(log_one_minus))
    return transmittance * alpha, transmittance


def block_weights(alpha: Tensor, log_transmittance: Tensor) -> tuple[Tensor, Tensor]:
    """Eq. 1 weights of a block of sections behind the part of the ray already composited (a ray marched a
    few sections at a time): ``w_k = T alpha_k prod_{j<k in the block}(1 - alpha_j)``, in log space with
    the clamp of :func:`weights_from_alpha`.

    Args:
        alpha: [n,B] opacities in [0,1] of the block's sections, front to back.
        log_transmittance: [n] log of the transmittance T in front of the block.

    Returns:
        ``(weights [n,B], log transmittance through the block [n])``: add the second to
        ``log_transmittance`` for the next block.
    """
    log_one_minus = torch.log((1.0 - alpha).clamp_min(ALPHA_T_EPS))
    weights = torch.exp(log_transmittance[:, None] + exclusive_cumsum(log_one_minus)) * alpha
    return weights, log_one_minus.sum(-1)
