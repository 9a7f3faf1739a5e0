"""Sample placement along rays: stratified, occupancy-guided, density-weighted (proposal) sections.

Samples are *intervals*: a sampler returns ``t_samples`` of shape [R,K,2]
holding ``(t_start, t_end)`` of each of the K sections of each ray, sorted and
pairwise disjoint (gaps are allowed: that is how empty space is skipped). The
sample point is the interval midpoint and its length is the section length
``delta`` (times ``||rays_d||``). Keeping shapes fixed at [R,K] keeps everything
downstream dense. Passing the same ``t_samples`` back into the renderer
reproduces the exact same samples.

Random jitter takes an optional ``torch.Generator``; it is drawn on the
generator's device and moved to the rays' device, so a CPU generator also
drives CUDA rendering deterministically.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Optional

import torch
from torch import Tensor

log = logging.getLogger("nerfart_plugin")

if TYPE_CHECKING:  # pragma: no cover
    from nerfart_plugin.fields.occupancy import OccupancyGrid

__all__ = [
    "uniform_rand",
    "stratified_edges",
    "edges_to_intervals",
    "stratified_samples",
    "occupancy_samples",
    "weighted_samples",
    "ray_aabb",
]


def uniform_rand(shape: tuple[int, ...], device: torch.device, generator: Optional[torch.Generator] = None) -> Tensor:
    """U[0,1) float32 of ``shape`` on ``device``, drawn from ``generator`` (on its own device) if given."""
    gen_device = generator.device if generator is not None else device
    return torch.rand(shape, generator=generator, device=gen_device, dtype=torch.float32).to(device)


def stratified_edges(
    near: Tensor, far: Tensor, num_samples: int, perturb: bool = False, generator: Optional[torch.Generator] = None
) -> Tensor:
    """K+1 bin edges per ray from ``near`` to ``far`` (both included), sorted.

    Unperturbed: uniform edges. Perturbed: every interior edge moves by
    U(-1/2, 1/2) bin widths, so the edges stay sorted, the first/last stay at
    near/far and the midpoints cover each bin continuously.

    Args:
        near, far: [R] ray-parameter bounds (far >= near; equal is allowed).
    Returns:
        edges [R,K+1] float32.
    """
    near = near.float().reshape(-1, 1)
    far = torch.maximum(far.float().reshape(-1, 1), near)
    R, K = near.shape[0], int(num_samples)
    u = torch.linspace(0.0, 1.0, K + 1, device=near.device).expand(R, K + 1)
    if perturb and K > 1:
        jitter = (uniform_rand((R, K - 1), near.device, generator) - 0.5) / K
        u = torch.cat([u[:, :1], u[:, 1:-1] + jitter, u[:, -1:]], dim=-1)
    return near + (far - near) * u


def edges_to_intervals(edges: Tensor) -> Tensor:
    """Contiguous edges [R,K+1] -> intervals [R,K,2] ``(start, end)``."""
    return torch.stack([edges[..., :-1], edges[..., 1:]], dim=-1)


def stratified_samples(
    near: Tensor, far: Tensor, num_samples: int, perturb: bool = False, generator: Optional[torch.Generator] = None
) -> Tensor:
    """Stratified uniform sections between near and far: ``t_samples`` [R,K,2]."""
    return edges_to_intervals(stratified_edges(near, far, num_samples, perturb, generator))


def _invert_cdf(bins: Tensor, cdf: Tensor, u: Tensor) -> Tensor:
    """Piecewise-linear inverse of ``cdf`` (values at ``bins`` [R,B+1]) at sorted ``u`` [R,N]."""
    u = u.contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(0, cdf.shape[-1] - 1)
    above = idx.clamp(0, cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_lo, bin_hi = bins.gather(-1, below), bins.gather(-1, above)
    denom = cdf_hi - cdf_lo
    # Empty bins (denom == 0) contribute nothing; any t inside is fine, take the lower edge.
    frac = torch.where(denom > 1e-12, (u - cdf_lo) / denom.clamp_min(1e-12), torch.zeros_like(u))
    return bin_lo + frac.clamp(0.0, 1.0) * (bin_hi - bin_lo)


def ray_aabb(rays_o: Tensor, rays_d: Tensor, bound: float) -> tuple[Tensor, Tensor]:
    """Entry/exit ray parameters of the box [-bound, bound]^3 (slab test).

    Returns ``(t_min [R], t_max [R])``; rays missing the box get ``t_min > t_max``.
    Zero direction components are handled by a tiny substitute (1e-15 keeps the
    slab bounds finite and of the right sign).
    """
    d = rays_d.float()
    d = torch.where(d.abs() < 1e-15, torch.full_like(d, 1e-15), d)
    inv = 1.0 / d
    t0 = (-bound - rays_o.float()) * inv
    t1 = (bound - rays_o.float()) * inv
    t_min = torch.minimum(t0, t1).amax(-1)
    t_max = torch.maximum(t0, t1).amin(-1)
    return t_min, t_max


@torch.no_grad()
def occupancy_samples(
    rays_o: Tensor,
    rays_d: Tensor,
    near: Tensor,
    far: Tensor,
    occupancy: "OccupancyGrid",
    num_samples: int,
    num_coarse: int = 256,
    perturb: bool = False,
    generator: Optional[torch.Generator] = None,
    dilate: int = 1,
) -> Tensor:
    """Occupancy-guided sections: empty-space skipping with a fixed [R,K] shape.

    1. ``num_coarse`` uniform bins between near and far; the occupancy grid
       (no grad, nearest cell) is queried at each bin centre and the occupied
       set is dilated by ``dilate`` bins on each side (so thin shells sampled
       between two coarse centres are not lost).
    2. A pdf that is uniform over the occupied bins is inverted at K stratified
       ``u`` sections ``[u_k, u_{k+1}]``. Section k becomes the interval centred
       at ``t(u_mid)`` whose length is the *occupied* length it covers,
       ``(u_{k+1} - u_k) * L_occ``; because ``t`` is piecewise linear with
       slope >= 1/L_occ, these intervals are sorted and disjoint, lie within
       [near, far] and their lengths sum to the occupied length: the empty gaps
       are skipped, not integrated.
    3. Rays with no occupied bin keep uniform samples but get zero-length
       intervals: the field is still evaluated (valid points), but every alpha
       is 0, so the renderer returns the background colour for them.

    Returns:
        t_samples [R,K,2] float32, no gradient.
    """
    R = rays_o.shape[0]
    M = int(num_coarse)
    coarse = stratified_edges(near, far, M, perturb=False)  # [R,M+1]
    mids = 0.5 * (coarse[:, :-1] + coarse[:, 1:])
    occ = occupancy.query_rays(rays_o, rays_d, mids).float()
    u_edges = stratified_edges(torch.zeros(R, device=rays_o.device), torch.ones(R, device=rays_o.device),
                               num_samples, perturb, generator)
    if occupancy.compiled and R > 1:
        try:
            return _compiled_sections()(coarse, occ, u_edges, int(dilate))
        except torch._dynamo.exc.TorchDynamoException as exc:  # the compiler's own failure: eager from now on
            occupancy.compiled = False
            log.warning("compile: the occupancy sampler runs uncompiled: the compiler failed (%s)", type(exc).__name__)
    return _occupied_sections(coarse, occ, u_edges, int(dilate))


def _occupied_sections(coarse: Tensor, occ: Tensor, u_edges: Tensor, dilate: int) -> Tensor:
    """Steps 1-3 of :func:`occupancy_samples` from the coarse bins ``coarse`` [R,M+1], their occupancy ``occ``
    [R,M] (0/1) and the stratified ``u_edges`` [R,K+1] -> t_samples [R,K,2]."""
    if dilate > 0:
        occ = torch.nn.functional.max_pool1d(occ[:, None], 2 * dilate + 1, stride=1, padding=dilate)[:, 0]
    widths = coarse[:, 1:] - coarse[:, :-1]
    hit = (occ * widths).sum(-1) > 0
    weights = torch.where(hit[:, None], occ, torch.ones_like(occ)) * widths  # mass of each bin
    mass = weights.sum(-1, keepdim=True)  # L_occ (or far-near for the fallback)
    cdf = torch.cat([torch.zeros_like(mass), torch.cumsum(weights, -1)], -1) / mass.clamp_min(1e-12)
    cdf = torch.cat([cdf[:, :-1], torch.ones_like(mass)], -1).clamp(max=1.0)
    u_mid = 0.5 * (u_edges[:, :-1] + u_edges[:, 1:])
    centre = _invert_cdf(coarse, cdf, u_mid)
    length = (u_edges[:, 1:] - u_edges[:, :-1]) * mass * hit[:, None].float()
    lo = torch.maximum(centre - 0.5 * length, coarse[:, :1])
    hi = torch.minimum(centre + 0.5 * length, coarse[:, -1:])
    return torch.stack([lo, hi], dim=-1)


def _interp(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """Piecewise-linear ``f(x)`` [R,N] of the sorted knots ``xp`` [R,M+1] with values ``fp`` [R,M+1]."""
    idx = torch.searchsorted(xp.contiguous(), x.contiguous(), right=True).clamp(1, xp.shape[-1] - 1)
    x0, x1 = xp.gather(-1, idx - 1), xp.gather(-1, idx)
    f0, f1 = fp.gather(-1, idx - 1), fp.gather(-1, idx)
    frac = ((x - x0) / (x1 - x0).clamp_min(1e-12)).clamp(0.0, 1.0)
    return f0 + frac * (f1 - f0)


def _dilate(x: Tensor, reach: Tensor) -> Tensor:
    """Max of ``x`` [R,M] over ``reach`` [R,1] bins on each side (a per-ray window)."""
    out = x.clone()
    for s in range(1, int(reach.max()) + 1 if reach.numel() else 1):
        on = (reach >= s).to(x.dtype)
        out[:, s:] = torch.maximum(out[:, s:], x[:, :-s] * on)
        out[:, :-s] = torch.maximum(out[:, :-s], x[:, s:] * on)
    return out


def _proposal_mass(rays_o: Tensor, rays_d: Tensor, coarse: Tensor, occupancy: "OccupancyGrid",
                   uniform_share: float, dilate: float) -> tuple[Tensor, Tensor]:
    """Steps 1-2 of :func:`weighted_samples` on the bins ``coarse`` [R,M+1]: the mass of each bin [R,M]
    (sums to 1 per ray) and the occupied (dilated) length of each bin [R,M] in ray parameter."""
    M = coarse.shape[1] - 1
    mids = 0.5 * (coarse[:, :-1] + coarse[:, 1:])
    widths = coarse[:, 1:] - coarse[:, :-1]
    cells = widths * rays_d.float().norm(dim=-1, keepdim=True) / occupancy.cell_size  # bin length in cells
    reach = torch.where(cells[:, :1] > 0, torch.ceil(float(dilate) / cells[:, :1].clamp_min(1e-6)), 0.0)
    reach = reach.clamp(max=M // 4).long()  # [R,1]: the dilation in bins
    cells_hit = occupancy.ray_cells(rays_o, rays_d, mids)
    occ = _dilate(occupancy.at(cells_hit).float(), reach)
    score = occupancy.at(cells_hit, "score").float().clamp(0.0, 1.0 - 1e-6)
    log_clear = torch.log1p(-score) * cells  # log(1 - a_i)
    # T_i^(1/4) a_i: the scores overrate opacity (the most opaque point of a cell), so the plain T_i ends
    # rays early (grazing rays through a rim, seen in tests); the tempered T keeps samples along them
    w = torch.exp(0.25 * (torch.cumsum(log_clear, -1) - log_clear)) * -torch.expm1(log_clear)
    w = _dilate(w, reach) * occ
    occ_len = occ * widths
    L_occ = occ_len.sum(-1, keepdim=True)
    total = w.sum(-1, keepdim=True)
    share = torch.where(total > 1e-8, torch.full_like(total, float(uniform_share)), torch.ones_like(total))
    mass = (1.0 - share) * w / total.clamp_min(1e-12) + share * occ_len / L_occ.clamp_min(1e-12)
    return torch.where(L_occ > 0, mass, widths / widths.sum(-1, keepdim=True).clamp_min(1e-12)), occ_len


def _sections(coarse: Tensor, mass: Tensor, occ_len: Tensor, u: Tensor) -> Tensor:
    """Step 3 of :func:`weighted_samples`: the sections [R,K,2] between the inverse-CDF points of the
    sorted ``u`` [R,K+1] (``u_0 = 0``, ``u_K = 1``) of the bins' ``mass``, each shrunk about its
    inverse-CDF midpoint to the occupied length ``occ_len`` it covers."""
    cdf = torch.cat([torch.zeros_like(mass[:, :1]), torch.cumsum(mass, -1)], -1)
    cdf = (cdf / cdf[:, -1:].clamp_min(1e-12)).clamp(max=1.0)
    cdf[:, -1] = 1.0
    edges = torch.cummax(_invert_cdf(coarse, cdf, u), -1).values  # [R,K+1]
    centre = _invert_cdf(coarse, cdf, 0.5 * (u[:, :-1] + u[:, 1:])).clamp(edges[:, :-1], edges[:, 1:])
    occ_cum = torch.cat([torch.zeros_like(occ_len[:, :1]), torch.cumsum(occ_len, -1)], -1)
    length = torch.diff(_interp(edges, coarse, occ_cum), dim=-1).clamp_min(0.0)  # occupied length covered
    shrink = (length / (edges[:, 1:] - edges[:, :-1]).clamp_min(1e-12)).clamp(max=1.0)
    lo = centre - shrink * (centre - edges[:, :-1])
    hi = centre + shrink * (edges[:, 1:] - centre)
    return torch.stack([lo, hi], dim=-1)


@torch.no_grad()
def weighted_samples(
    rays_o: Tensor,
    rays_d: Tensor,
    near: Tensor,
    far: Tensor,
    occupancy: "OccupancyGrid",
    num_samples: int,
    num_coarse: int = 256,
    perturb: bool = False,
    generator: Optional[torch.Generator] = None,
    uniform_share: float = 0.2,
    dilate: float = 2.0,
) -> Tensor:
    """Proposal sections: K sections per ray, dense where the grid says the ray ends, sparse elsewhere,
    none in empty space.

    The occupancy grid of a density field keeps, per cell, a recent upper bound of the opacity of one
    cell side (``score``); read along a ray it is a cheap proposal of the field, as the proposal
    networks of mip-NeRF 360 / nerfstudio, with no network to train:

    1. ``num_coarse`` uniform bins between near and far. Bin i's opacity is
       ``a_i = 1 - (1 - s_i)^(len_i / cell)`` (``s_i``: the score of the cell at its centre, ``len_i``:
       its length in world units) and its weight ``w_i = T_i^(1/4) a_i`` (``T_i``: the transmittance
       before it, tempered because the scores overrate opacity), so what lies well behind the first
       surface gets none. Weights are widened by a max over ``dilate`` cells on each side (a cell's
       score is its most opaque point, so the proposal runs ahead of the surface) and kept only in
       occupied bins (dilated as much).
    2. pdf = ``(1 - uniform_share) w / sum(w) + uniform_share`` x uniform over the occupied bins: every
       occupied part of the ray keeps some samples, so a surface the proposal underrates still gets
       gradient. Rays with no weight: uniform over their occupied bins (as :func:`occupancy_samples`).
    3. Section k spans the inverse CDF between stratified ``u_k`` and ``u_{k+1}`` (jittered when
       ``perturb``), shrunk about its inverse-CDF midpoint to the *occupied* length it covers: the
       sections are sorted and disjoint, their lengths sum to the ray's occupied length, and empty gaps
       are skipped. Rays that miss every occupied cell get zero-length (transparent) sections.

    Returns:
        t_samples [R,K,2] float32, no gradient.
    """
    R = rays_o.shape[0]
    coarse = stratified_edges(near, far, int(num_coarse), perturb=False)  # [R,M+1]
    mass, occ_len = _proposal_mass(rays_o, rays_d, coarse, occupancy, uniform_share, dilate)
    u = stratified_edges(torch.zeros(R, device=rays_o.device), torch.ones(R, device=rays_o.device),
                         num_samples, perturb, generator)  # [R,K+1]
    return _sections(coarse, mass, occ_len, u)


_COMPILED_SECTIONS: Optional[Any] = None


def _compiled_sections() -> Any:
    """:func:`_occupied_sections` through ``torch.compile`` (dynamic shapes), made once: the sampler's share of a
    compiled render (``compile``; the occupancy grid's ``compiled`` flag selects it)."""
    global _COMPILED_SECTIONS
    if _COMPILED_SECTIONS is None:
        _COMPILED_SECTIONS = torch.compile(_occupied_sections, dynamic=True)
    return _COMPILED_SECTIONS
