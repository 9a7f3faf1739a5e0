"""Fast SDF training path: gradient on a sample subset, NeuS Eq. 13 section alpha, compaction, adaptive band."""

from __future__ import annotations

import pytest
import torch

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields import OccupancyGrid, build_field
from nerfart_plugin.fields.opacity import neus_alpha, neus_alpha_sections
from nerfart_plugin.rendering import VolumeRenderer

GRID = {"name": "grid", "resolution": 16, "n_components": 4, "out_features": 8}
FAST = {"color_normal": False, "grad_samples": 0.25, "hidden_dim": 32, "radius": 0.5}


def _batch(R: int = 16) -> dict:
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.1 * torch.randn(R, 3, generator=g), dim=-1)
    return {"rays_o": torch.tensor([0.0, 0.0, -2.5]).expand(R, 3).clone(), "rays_d": d,
            "near": torch.full((R,), 1.0), "far": torch.full((R,), 4.0)}


@pytest.mark.parametrize("backbone,extra", [("volsdf", {}), ("neus", {"alpha_mode": "sections"})])
def test_gradient_subset_training_forward(backbone: str, extra: dict) -> None:
    field = build_field({"name": backbone, **FAST, **extra}, GRID)
    x = torch.rand(200, 3) * 1.6 - 0.8
    d = torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    out = field(x, d)
    assert int(out["gradient_mask"].sum()) == 50
    assert (out["gradient"][~out["gradient_mask"]] == 0).all()
    # the computed rows are the true gradients (same as the full no-grad path)
    with torch.no_grad():
        full = field(x, d)
    m = out["gradient_mask"]
    torch.testing.assert_close(out["gradient"][m].detach(), full["gradient"][m], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out["sdf"].detach(), full["sdf"], atol=2e-3, rtol=0)  # FD mean vs point value
    assert "gradient_mask" not in full and full["gradient"].norm(dim=-1).min() > 0
    r = VolumeRenderer(field, num_samples=16)
    res = r(_batch(), perturb=True)
    eik = res["regularizers"]["eikonal"]
    assert eik.dim() == 0 and torch.isfinite(eik)
    (res["rgb"].sum() + eik).backward()
    assert all(torch.isfinite(p.grad).all() for p in field.parameters() if p.grad is not None)


def test_neus_gradient_alpha_rejects_nothing_but_needs_all_gradients() -> None:
    f = build_field({"name": "neus", **FAST, "alpha_mode": "gradient"}, GRID)
    out = f(torch.rand(20, 3) - 0.5, torch.nn.functional.normalize(torch.randn(20, 3), dim=-1))
    assert "gradient_mask" not in out  # gradient alpha: every gradient is computed
    with pytest.raises(ConfigError, match="alpha_mode"):
        build_field({"name": "neus", "alpha_mode": "nope"}, GRID)
    with pytest.raises(ConfigError, match="grad_samples"):
        build_field({"name": "volsdf", "grad_samples": 0.0}, GRID)


def test_neus_section_alpha_matches_gradient_alpha_on_a_plane() -> None:
    # planar SDF crossed head-on by a ray: f(t) = 1 - t; both estimates must agree away from the ends
    t = torch.linspace(0.0, 2.0, 201)[None]
    deltas = torch.full_like(t, 0.01)
    sdf = 1.0 - t
    a_sec = neus_alpha_sections(sdf, deltas, 50.0)
    # section k spans samples k..k+1, i.e. it is centred half a step further than the mid-point section k
    a_mid = neus_alpha(sdf - 0.005, -torch.ones_like(t), deltas, 50.0)
    torch.testing.assert_close(a_sec[:, 10:-10], a_mid[:, 10:-10], atol=2e-3, rtol=0)
    w = a_sec * torch.exp(torch.cumsum(torch.log1p(-a_sec.clamp(max=1 - 1e-7)), -1) - torch.log1p(-a_sec.clamp(max=1 - 1e-7)))
    assert abs(float((w * t).sum() / w.sum()) - 1.0) < 0.02  # unbiased: the depth is the zero crossing
    assert (neus_alpha_sections(sdf, torch.zeros_like(t), 50.0) == 0).all()


def test_compaction_does_not_change_renders() -> None:
    torch.manual_seed(0)
    field = build_field({"name": "volsdf", "hidden_dim": 32, "radius": 0.5}, GRID)
    occ = OccupancyGrid(resolution=16, bound=1.0)
    occ.update(field, 0, force=True)
    batch = _batch(32)
    batch["rays_o"][:8] += torch.tensor([0.0, 5.0, 0.0])  # these rays miss everything
    on = VolumeRenderer(field, num_samples=16, occupancy=occ, compact=True)
    off = VolumeRenderer(field, num_samples=16, occupancy=occ, compact=False)
    with torch.no_grad():
        a, b = on(batch), off(batch)
    for k in ("rgb", "opacity", "depth", "weights"):
        torch.testing.assert_close(a[k], b[k], atol=1e-6, rtol=0)


def test_occupancy_band_follows_surface_width() -> None:
    field = build_field({"name": "volsdf", "radius": 0.5, "beta_init": 0.1}, {"name": "frequency", "n_freqs": 2})
    grid = OccupancyGrid(resolution=32, bound=1.0, band_widths=3.0)
    assert grid.band(field) == pytest.approx(0.3, rel=1e-3)
    grid.update(field, 0, force=True)
    dirs = torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    assert grid.query(0.75 * dirs).float().mean() > 0.9  # 0.25 from the surface: inside the widened band
    with torch.no_grad():
        field.beta_param.fill_(-30.0)
    assert grid.band(field) == pytest.approx(grid.sdf_band)  # sharp surface: one cell diagonal


@pytest.mark.parametrize("backbone,extra,skips", [
    ("volsdf", {}, True),
    ("neus", {"alpha_mode": "sections"}, True),
    ("neus", {"alpha_mode": "gradient"}, False),  # alpha reads the gradient: must keep it
    ("volsdf", {"color_normal": True}, False),  # colour reads the normal: must keep it
    ("nerf", {}, True),
])
def test_colour_only_render_skips_normals_and_matches(backbone: str, extra: dict, skips: bool) -> None:
    """Pass 1 of stylization renders colour only: SDF fields skip the 4 gradient taps where nothing
    reads them, and the image equals the full render (sdf at x vs the mean of the taps: O(h^2))."""
    torch.manual_seed(0)
    base = {"hidden_dim": 32} if backbone == "nerf" else FAST
    field = build_field({"name": backbone, **base, **extra}, GRID)
    r = VolumeRenderer(field, num_samples=16)
    batch = _batch(24)
    calls = []
    hook = field.encoding.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    with torch.no_grad():
        full = r(batch)
        n_full = sum(calls)
        calls.clear()
        fast = r(batch, with_normals=False)
        n_fast = sum(calls)
    hook.remove()
    for k in ("rgb", "opacity", "depth"):
        torch.testing.assert_close(fast[k], full[k], atol=1e-4, rtol=0)
    if backbone == "nerf":
        assert n_fast == n_full and "normal" not in fast
    elif skips:
        assert "normal" not in fast and n_fast * 4 == n_full  # one geometry evaluation per sample instead of 4
    else:
        assert "normal" in fast and n_fast == n_full
    with torch.enable_grad():  # with grad the training path is unchanged (eikonal needs the gradient)
        out = r(batch, with_normals=False)
    assert "eikonal" in out["regularizers"] or backbone == "nerf"
