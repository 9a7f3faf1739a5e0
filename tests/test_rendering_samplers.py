"""Stratified / inverse-CDF / occupancy-guided sampling and t_samples reuse."""

from __future__ import annotations

import torch

from nerfart_plugin.fields import OccupancyGrid, build_field
from nerfart_plugin.rendering import VolumeRenderer, occupancy_samples, ray_aabb, stratified_samples


def _rays(R: int = 64, seed: int = 0, spread: float = 0.15) -> dict:
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, -3.0]) + 0.05 * torch.randn(R, 3, generator=g)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + spread * torch.randn(R, 3, generator=g), dim=-1)
    return {"rays_o": o, "rays_d": d, "near": torch.full((R,), 1.0), "far": torch.full((R,), 5.0)}


def _check_intervals(ts: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> None:
    start, end = ts[..., 0], ts[..., 1]
    assert (end >= start).all()
    assert (start[:, 1:] >= end[:, :-1] - 1e-6).all(), "sections must be sorted and disjoint"
    assert (start >= near[:, None] - 1e-6).all() and (end <= far[:, None] + 1e-6).all()


def test_stratified_sorted_within_bounds_and_deterministic() -> None:
    near, far = torch.rand(32), torch.rand(32) + 1.0
    ts0 = stratified_samples(near, far, 16, perturb=False)
    _check_intervals(ts0, near, far)
    torch.testing.assert_close(ts0[:, 0, 0], near)
    torch.testing.assert_close(ts0[:, -1, 1], far)
    a = stratified_samples(near, far, 16, True, torch.Generator().manual_seed(3))
    b = stratified_samples(near, far, 16, True, torch.Generator().manual_seed(3))
    c = stratified_samples(near, far, 16, True, torch.Generator().manual_seed(4))
    _check_intervals(a, near, far)
    assert torch.equal(a, b) and not torch.equal(a, c)
    # contiguous sections cover [near, far] exactly
    torch.testing.assert_close((a[..., 1] - a[..., 0]).sum(-1), far - near)


def test_ray_aabb() -> None:
    t0, t1 = ray_aabb(torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]), 1.0)
    torch.testing.assert_close(t0[0], torch.tensor(2.0))
    torch.testing.assert_close(t1[0], torch.tensor(4.0))
    assert t0[1] > t1[1]  # misses


def test_occupancy_samples_skip_empty_space() -> None:
    grid = OccupancyGrid(resolution=16, bound=1.0)
    grid.occupied.zero_()
    # occupy the cells of the slab z in [-0.25, 0.25]
    r = grid.resolution
    idx = torch.arange(r**3)
    k = idx % r
    zc = (k.float() + 0.5) * grid.cell_size - 1.0
    grid.occupied[(zc.abs() < 0.25)] = True
    batch = _rays(32, spread=0.05)  # all pass through the slab inside the box
    batch["rays_o"][-4:] += torch.tensor([5.0, 0.0, 0.0])  # these miss the box entirely
    ts = occupancy_samples(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"], grid, 16, 256,
                           perturb=True, generator=torch.Generator().manual_seed(1), dilate=0)
    _check_intervals(ts, batch["near"], batch["far"])
    mid = 0.5 * (ts[..., 0] + ts[..., 1])
    pts = batch["rays_o"][:, None] + batch["rays_d"][:, None] * mid[..., None]
    hit = (ts[..., 1] - ts[..., 0]).sum(-1) > 0
    assert hit[:-4].all() and not hit[-4:].any()
    occ = grid.query(pts[hit].reshape(-1, 3))
    assert occ.float().mean() > 0.95
    # occupied length along a ray through the slab is ~0.5 / cos(angle)
    lengths = (ts[..., 1] - ts[..., 0]).sum(-1)[hit]
    cos = batch["rays_d"][hit, 2].abs()
    torch.testing.assert_close(lengths * cos, torch.full_like(lengths, 0.5), atol=0.06, rtol=0)


def test_renderer_t_samples_reuse_identical() -> None:
    field = build_field({"name": "nerf", "hidden_dim": 16, "color_hidden_dim": 16}, {"name": "frequency", "n_freqs": 4})
    for occ in (None, OccupancyGrid(16, 1.0)):
        r = VolumeRenderer(field, num_samples=24, occupancy=occ)
        batch = _rays(16)
        out1 = r(batch, perturb=True, generator=torch.Generator().manual_seed(0))
        out2 = r(batch, perturb=True, t_samples=out1["t_samples"])
        out3 = r(batch, perturb=True, generator=torch.Generator().manual_seed(0))
        for k in ("rgb", "depth", "opacity", "weights", "t", "deltas"):
            assert torch.equal(out1[k], out2[k]), k
            assert torch.equal(out1[k], out3[k]), k
        out4 = r(batch, perturb=True, generator=torch.Generator().manual_seed(1))
        assert not torch.equal(out1["t"], out4["t"])
