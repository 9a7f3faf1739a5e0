"""How the SDF backbones turn geometry into opacity (each field owns its conversion; the renderer composites).

Every function computes in float32 (inputs are up-cast) and returns finite values *and* finite gradients for the
extreme inputs listed in its docstring (checked by ``tests/test_stability_rendering.py``).

Epsilons and clamps (and why)
-----------------------------
* ``volsdf_density``: no epsilon. ``beta`` is only required to be > 0; the
  fields keep it >= ``beta_min``. Both branches of the Laplace CDF are written
  with ``exp`` of a non-positive argument (``-|d|/beta``) so nothing overflows.
* ``neus_alpha``: ``NEUS_EPS`` = 1e-5 added to numerator and denominator (as in
  the NeuS reference code) so the ratio is defined when ``Phi_s(prev) -> 0``
  (deep inside the surface, where it tends to 1, i.e. opaque, which is harmless
  because the transmittance is already ~0 there); the result is clamped to
  [0, 1] because the section-end estimates can make ``prev - next`` negative
  (ray leaving the surface) and rounding can push the ratio above 1. A
  zero-length section (``delta == 0``) is defined as transparent (alpha = 0),
  otherwise the eps would make it opaque inside the surface.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

NEUS_EPS = 1e-5

__all__ = ["volsdf_density", "neus_alpha", "neus_alpha_sections", "NEUS_EPS"]


def volsdf_density(sdf: Tensor, beta: Tensor | float) -> Tensor:
    """VolSDF density ``sigma = (1/beta) * Psi_beta(-d)``, Psi_beta the zero-mean Laplace CDF of scale beta.

    ``Psi_beta(s) = 0.5 exp(s/beta)`` for s <= 0 and ``1 - 0.5 exp(-s/beta)`` for s > 0; with
    ``s = -d``: outside (d >= 0) ``sigma = 0.5 exp(-d/beta)/beta``, inside
    ``sigma = (1 - 0.5 exp(d/beta))/beta = (0.5 - 0.5 expm1(d/beta))/beta``.
    Both branches only exponentiate ``-|d|/beta <= 0``, and ``torch.where`` is fed
    branch-safe inputs so the unused branch cannot produce inf*0 in backward.

    Args:
        sdf: [...] signed distances (negative inside).
        beta: scalar or broadcastable tensor > 0 (length unit).

    Returns:
        sigma [...] float32 in [0, 1/beta]. Finite values and gradients for
        beta in [1e-6, 10] and |sdf| <= 1e4.
    """
    d = sdf.float()
    beta = torch.as_tensor(beta, dtype=torch.float32, device=d.device)
    outside = d >= 0
    d_out = torch.where(outside, d, torch.zeros_like(d))  # >= 0
    d_in = torch.where(outside, torch.zeros_like(d), d)  # <= 0
    psi_out = 0.5 * torch.exp(-d_out / beta)
    psi_in = 0.5 - 0.5 * torch.expm1(d_in / beta)
    return torch.where(outside, psi_out, psi_in) / beta


def neus_alpha(
    sdf: Tensor,
    dirs_dot_normals: Tensor,
    deltas: Tensor,
    inv_s: Tensor | float,
    cos_anneal_ratio: float = 1.0,
) -> Tensor:
    """NeuS unbiased, occlusion-aware opacity of each section (Wang et al. 2021, Eq. 13).

    The SDF at the section ends is estimated from the midpoint value and the
    directional derivative: ``sdf_prev/next = sdf -/+ iter_cos * delta / 2`` with
    ``iter_cos = -(relu(-cos/2 + 1/2)(1 - r) + relu(-cos) r)`` (``r`` = cos-anneal
    ratio: r < 1 early in training keeps gradients alive for back-facing samples).
    Then ``alpha = clamp((Phi_s(prev) - Phi_s(next) + eps) / (Phi_s(prev) + eps), 0, 1)``
    with ``Phi_s(x) = sigmoid(inv_s x)`` (logistic CDF) and eps = ``NEUS_EPS``.

    Args:
        sdf: [R,K] SDF at the sample midpoints.
        dirs_dot_normals: [R,K] ``dot(ray dir (unit), grad sdf)`` at the samples.
        deltas: [R,K] section lengths (same unit as the sdf).
        inv_s: scalar / broadcastable tensor, the logistic sharpness 1/s.
        cos_anneal_ratio: r in [0,1].

    Returns:
        alpha [R,K] float32 in [0,1]. Finite values and gradients for inv_s in
        [1, 1e5] and |sdf| <= 1e4 (``sigmoid`` saturates instead of overflowing).
    """
    sdf = sdf.float()
    cos = dirs_dot_normals.float()
    deltas = deltas.float().clamp_min(0.0)
    inv_s = torch.as_tensor(inv_s, dtype=torch.float32, device=sdf.device)
    r = float(cos_anneal_ratio)
    iter_cos = -(F.relu(-cos * 0.5 + 0.5) * (1.0 - r) + F.relu(-cos) * r)
    next_sdf = sdf + iter_cos * deltas * 0.5
    prev_sdf = sdf - iter_cos * deltas * 0.5
    prev_cdf = torch.sigmoid(prev_sdf * inv_s)
    next_cdf = torch.sigmoid(next_sdf * inv_s)
    alpha = ((prev_cdf - next_cdf + NEUS_EPS) / (prev_cdf + NEUS_EPS)).clamp(0.0, 1.0)
    return torch.where(deltas > 0, alpha, torch.zeros_like(alpha))


def neus_alpha_sections(sdf: Tensor, deltas: Tensor, inv_s: Tensor | float) -> Tensor:
    """NeuS discrete opacity (Wang et al. 2021, Eq. 13) from the SDF at consecutive samples, no gradient needed.

    ``alpha_k = clamp((Phi_s(f_k) - Phi_s(f_{k+1}) + eps) / (Phi_s(f_k) + eps), 0, 1)``: the opacity
    of the stretch from sample k to sample k+1 (colour ``c_k``). The last sample has no successor; its
    ``f_{K+1}`` is extrapolated linearly, ``f_K + (f_K - f_{K-1}) * delta_K / delta_{K-1}``.

    Args:
        sdf: [R,K] SDF at the (sorted) sample points.
        deltas: [R,K] section lengths; zero-length sections are transparent.
        inv_s: scalar / broadcastable tensor, the logistic sharpness 1/s.

    Returns:
        alpha [R,K] float32 in [0,1]; finite values and gradients as :func:`neus_alpha`.
    """
    sdf = sdf.float()
    deltas = deltas.float().clamp_min(0.0)
    inv_s = torch.as_tensor(inv_s, dtype=torch.float32, device=sdf.device)
    if sdf.shape[-1] > 1:
        ratio = deltas[..., -1:] / deltas[..., -2:-1].clamp_min(1e-12)
        last = sdf[..., -1:] + (sdf[..., -1:] - sdf[..., -2:-1]) * ratio.clamp(max=4.0)
        nxt = torch.cat([sdf[..., 1:], last], dim=-1)
    else:
        nxt = sdf
    prev_cdf = torch.sigmoid(sdf * inv_s)
    next_cdf = torch.sigmoid(nxt * inv_s)
    alpha = ((prev_cdf - next_cdf + NEUS_EPS) / (prev_cdf + NEUS_EPS)).clamp(0.0, 1.0)
    return torch.where(deltas > 0, alpha, torch.zeros_like(alpha))
