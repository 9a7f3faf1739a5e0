"""Tiny fit: ~100 steps on rays of a synthetic coloured sphere lower the photometric loss."""

from __future__ import annotations

import pytest
import torch

from nerfart_plugin.fields import OccupancyGrid, build_field
from nerfart_plugin.rendering import VolumeRenderer


def _sphere_rays(R: int, gen: torch.Generator, radius: float = 0.5) -> dict:
    """Rays from random cameras on a sphere of radius 2.5 looking near the origin; GT colour = 0.5 + 0.5 * normal at
    the hit on a sphere of ``radius`` (white where it misses)."""
    cam = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen), dim=-1) * 2.5
    target = (torch.rand(R, 3, generator=gen) - 0.5) * 1.0
    d = torch.nn.functional.normalize(target - cam, dim=-1)
    b = (cam * d).sum(-1)
    c = cam.square().sum(-1) - radius**2
    disc = b * b - c
    hit = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    n = torch.nn.functional.normalize(cam + t[:, None] * d, dim=-1)
    rgb = torch.where(hit[:, None], 0.5 + 0.5 * n, torch.ones(R, 3))
    return {"rays_o": cam, "rays_d": d, "near": torch.full((R,), 1.0), "far": torch.full((R,), 4.0), "rgb": rgb}


@pytest.mark.slow
@pytest.mark.parametrize(
    "backbone,encoding,occupancy,factor",
    [("nerf", {"name": "grid", "resolution": 32, "n_components": 8, "out_features": 16}, True, 0.5),
     # NeuS starts from the right sphere (geometric init), only colour and sharpness are learnt: smaller drop
     ("neus", {"name": "frequency", "n_freqs": 4}, False, 0.8)],
)
def test_tiny_fit_lowers_loss(backbone: str, encoding: dict, occupancy: bool, factor: float) -> None:
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    field = build_field({"name": backbone, "hidden_dim": 32, "color_hidden_dim": 32}, encoding)
    grid = OccupancyGrid(resolution=16, bound=1.0, update_every=20, warmup_steps=1000) if occupancy else None
    r = VolumeRenderer(field, num_samples=16, occupancy=grid, num_coarse=64)
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    val = _sphere_rays(256, torch.Generator().manual_seed(123))

    def val_loss() -> float:
        with torch.no_grad():
            return float((r.render_chunked(val, chunk=256)["rgb"] - val["rgb"]).square().mean())

    before = val_loss()
    for step in range(100):
        if grid is not None and step > 0:
            grid.update(field, step, generator=gen)
        batch = _sphere_rays(128, gen)
        out = r(batch, perturb=True, generator=gen)
        loss = (out["rgb"] - batch["rgb"]).square().mean() + 0.1 * sum(out["regularizers"].values(), torch.zeros(()))
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = val_loss()
    assert after < factor * before, (before, after)
