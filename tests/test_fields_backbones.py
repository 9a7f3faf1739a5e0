"""Every backbone x encoding builds, renders with the right shapes and has finite gradients."""

from __future__ import annotations

import copy
import logging

import pytest
import torch

from nerfart_plugin.config import registry
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields import EnvironmentMap, OccupancyGrid, build_background, build_field
from nerfart_plugin.fields.encodings import FrequencyEncoding, SHEncoding, TensorVMGridEncoding, level_sides
from nerfart_plugin.rendering import VolumeRenderer

SMALL = {"hidden_dim": 16, "color_hidden_dim": 16, "feature_dim": 7}
ENCODINGS = {
    "frequency": {"name": "frequency", "n_freqs": 4},
    "grid": {"name": "grid", "resolution": 16, "n_components": 4, "out_features": 8},
    "grid_multires": {"name": "grid", "resolution": [8, 16], "n_components": 2, "out_features": None},
}


def _batch(R: int = 32) -> dict:
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([0.0, 0.0, -2.5]) + 0.05 * torch.randn(R, 3, generator=g)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.2 * torch.randn(R, 3, generator=g), dim=-1)
    return {"rays_o": o, "rays_d": d, "near": torch.full((R,), 1.0), "far": torch.full((R,), 4.0)}


def test_registry_names() -> None:
    assert {"nerf", "volsdf", "neus"} <= set(registry.names("backbone"))
    assert {"frequency", "grid", "sh"} <= set(registry.names("encoding"))


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
@pytest.mark.parametrize("enc", list(ENCODINGS))
def test_backbone_renders_with_finite_grads(backbone: str, enc: str) -> None:
    field = build_field({"name": backbone, **SMALL}, ENCODINGS[enc], bound=1.0)
    r = VolumeRenderer(field, num_samples=16)
    R, K = 32, 16
    out = r(_batch(R), perturb=True, generator=torch.Generator().manual_seed(0))
    assert out["rgb"].shape == (R, 3) and out["depth"].shape == (R,) and out["opacity"].shape == (R,)
    assert out["weights"].shape == (R, K) and out["t"].shape == (R, K) and out["deltas"].shape == (R, K)
    assert out["t_samples"].shape == (R, K, 2)
    assert ((out["rgb"] >= 0) & (out["rgb"] <= 1 + 1e-5)).all()
    assert ((out["opacity"] >= 0) & (out["opacity"] <= 1 + 1e-5)).all()
    loss = (out["rgb"] - 0.3).square().mean()
    if field.is_sdf:
        assert out["normal"].shape == (R, 3) and out["regularizers"]["eikonal"].dim() == 0
        loss = loss + 0.1 * out["regularizers"]["eikonal"]
    loss.backward()
    grads = [p.grad for p in field.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in (p.grad for p in field.geometry_parameters()) if g is not None)
    # no-grad full-view rendering: same keys, no regularizers, no graph
    full = r.render_chunked({**_batch(R), "H": 4, "W": 8}, chunk=10)
    assert full["rgb"].shape == (R, 3) and not full["rgb"].requires_grad and full["H"] == 4
    assert ("normal" in full) == field.is_sdf
    # early ray termination: within the renderer's stop_transmittance of the dense render
    torch.testing.assert_close(full["rgb"], r(_batch(R))["rgb"].detach(), atol=r.stop_transmittance + 1e-5, rtol=0)


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
def test_field_contract(backbone: str) -> None:
    field = build_field({"name": backbone, **SMALL}, ENCODINGS["frequency"])
    x = torch.rand(10, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    with torch.no_grad():
        out = field(x, d)
    assert out["rgb"].shape == (10, 3)
    assert field.geometry(x).shape == (10,)
    if field.is_sdf:
        assert out["sdf"].shape == (10,) and out["gradient"].shape == (10, 3)  # gradient even under no_grad
        assert field.mesh_level == 0.0 and field.mesh_inside_is_below
    else:
        assert (out["sigma"] >= 0).all() and not field.mesh_inside_is_below
    geo = {id(p) for p in field.geometry_parameters()}
    col = {id(p) for p in field.color_parameters()}
    assert geo and col and not (geo & col) and geo | col == {id(p) for p in field.parameters()}


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
@pytest.mark.parametrize("enc", ["frequency", "grid"])
def test_sdf_geometric_init_is_sphere(backbone: str, enc: str) -> None:
    field = build_field({"name": backbone, "radius": 0.5}, ENCODINGS[enc])
    dirs = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    with torch.no_grad():
        on = field.geometry(0.5 * dirs)
        out = field.geometry(0.9 * dirs)
        inside = field.geometry(0.2 * dirs)
    assert on.abs().max() < 0.08
    assert (out > 0.25).all() and (inside < -0.15).all()
    g = field(0.5 * dirs, dirs)["gradient"]
    cos = torch.nn.functional.cosine_similarity(g, dirs, dim=-1)
    assert cos.mean() > 0.95 and (g.norm(dim=-1) - 1).abs().mean() < 0.2


def test_sdf_analytic_and_finite_difference_gradients_agree() -> None:
    a = build_field({"name": "neus", **SMALL, "grad_type": "analytic"}, ENCODINGS["grid"])
    f = build_field({"name": "neus", **SMALL, "grad_type": "finite_difference"}, ENCODINGS["grid"])
    f.load_state_dict(a.state_dict())
    x = torch.rand(50, 3) * 1.6 - 0.8
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    ga, gf = a(x, d)["gradient"], f(x, d)["gradient"]
    assert torch.nn.functional.cosine_similarity(ga, gf, dim=-1).mean() > 0.99


def test_neus_cos_anneal_and_volsdf_beta() -> None:
    neus = build_field({"name": "neus", **SMALL, "anneal_steps": 100}, ENCODINGS["frequency"])
    assert neus.cos_anneal_ratio == 0.0
    neus.update_step(50, 1000)
    assert neus.cos_anneal_ratio == 0.5
    neus.update_step(500, 1000)
    assert neus.cos_anneal_ratio == 1.0
    # checkpointed: a loaded, annealed field renders with ratio 1, and a stylization restarting its
    # step count at 0 does not restart the anneal
    fresh = build_field({"name": "neus", **SMALL, "anneal_steps": 100}, ENCODINGS["frequency"])
    fresh.load_state_dict(neus.state_dict())
    assert fresh.cos_anneal_ratio == 1.0
    fresh.update_step(0, 100)
    assert fresh.cos_anneal_ratio == 1.0
    old = {k: v for k, v in neus.state_dict().items() if k != "cos_anneal"}  # a checkpoint from before
    fresh2 = build_field({"name": "neus", **SMALL, "anneal_steps": 100}, ENCODINGS["frequency"])
    fresh2.load_state_dict(old)
    assert fresh2.cos_anneal_ratio == 1.0
    assert 15 < float(neus.inv_s.detach()) < 25  # exp(10 * 0.3)
    vol = build_field({"name": "volsdf", **SMALL, "beta_init": 0.05, "beta_min": 1e-3}, ENCODINGS["frequency"])
    torch.testing.assert_close(vol.beta, torch.tensor(0.05))
    with torch.no_grad():
        vol.beta_param.fill_(-1e-9)
    assert float(vol.beta.detach()) >= 1e-3


def test_encodings_shapes() -> None:
    x = torch.rand(20, 3) * 4 - 2
    fe = FrequencyEncoding(bound=2.0, n_freqs=3)
    assert fe(x).shape == (20, 3 * 7) and fe.n_output_dims == 21
    ge = TensorVMGridEncoding(bound=2.0, resolution=[4, 8], n_components=3, out_features=5)
    assert ge(x).shape == (20, 5)
    assert TensorVMGridEncoding(resolution=8, n_components=3, out_features=None).n_output_dims == 9
    sh = SHEncoding(degree=4)
    d = torch.nn.functional.normalize(torch.randn(20, 3), dim=-1)
    assert sh(d).shape == (20, 16)
    tv = TensorVMGridEncoding(resolution=8, n_components=2, tv_weight=1.0).regularizers()["grid_tv"]
    assert tv > 0


def test_grid_levels_halve_the_side_down_from_the_finest() -> None:
    """encoding.levels: one side (an int, or auto as the scene setup resolves it) becomes the finest of
    that many levels, each coarser one half the side; a list of sides that disagrees with levels is refused."""
    assert level_sides(128, 3) == [32, 64, 128] and level_sides(256, 1) == [256] and level_sides(4, 3) == [2, 2, 4]
    ge = TensorVMGridEncoding(resolution=16, levels=3, n_components=2, out_features=None)
    assert ge.resolutions == [4, 8, 16] and ge.n_output_dims == 3 * 2 * 3
    assert [p.shape[-1] for p in ge.planes] == [4, 8, 16]
    assert TensorVMGridEncoding(resolution=[8, 16], levels=2).resolutions == [8, 16]
    with pytest.raises(ConfigError, match="encoding.levels"):
        TensorVMGridEncoding(resolution=[8, 16], levels=3)


def test_bad_configs_raise_config_error() -> None:
    with pytest.raises(ConfigError, match="backbone.name=.nope.: one of nerf, neus, volsdf"):
        build_field({"name": "nope"}, ENCODINGS["frequency"])
    with pytest.raises(ConfigError, match=r"backbone.hiden_dim=3: unknown setting; did you mean backbone.hidden_dim\?"):
        build_field({"name": "nerf", "hiden_dim": 3}, ENCODINGS["frequency"])
    with pytest.raises(ConfigError, match="grad_type"):
        build_field({"name": "neus", "grad_type": "magic"}, ENCODINGS["frequency"])
    with pytest.raises(ConfigError):
        build_field({"name": "nerf"}, {"name": "grid", "resolution": 1})


def test_background_model_fills_remaining_transmittance() -> None:
    field = build_field({"name": "nerf", **SMALL, "density_bias": -30.0}, ENCODINGS["frequency"])  # empty scene
    bg = build_background({"name": "envmap", "hidden_dim": 8})
    assert isinstance(bg, EnvironmentMap) and build_background(None) is None
    r = VolumeRenderer(field, num_samples=8, background=bg)
    batch = _batch(8)
    out = r(batch)
    torch.testing.assert_close(out["rgb"], bg(batch["rays_d"]), atol=1e-5, rtol=0)
    out["rgb"].sum().backward()
    assert all(p.grad is not None for p in bg.parameters())


def test_occupancy_grid_never_empties_a_lost_surface(caplog: pytest.LogCaptureFixture) -> None:
    """An SDF without a zero crossing in the box (its surface lost mid-training) must not empty the
    grid for good: the grid falls back to all cells, warns once, and prunes again once a surface is back."""
    field = build_field({"name": "volsdf", "radius": 0.5}, ENCODINGS["frequency"])
    grid = OccupancyGrid(resolution=16, bound=1.0, ema_decay=0.0)
    with torch.no_grad():
        field.geo_net.out.bias[0] += 10.0  # sdf > 0 everywhere: no surface
    with caplog.at_level(logging.WARNING, logger="nerfart_plugin.fields.occupancy"):
        grid.update(field, 0, force=True)
        grid.update(field, 1, force=True)
    assert grid.occupied_fraction == 1.0
    assert sum("no cell occupied" in r.getMessage() for r in caplog.records) == 1
    with torch.no_grad():
        field.geo_net.out.bias[0] -= 10.0  # the surface is back
    grid.update(field, 2, force=True)
    assert 0.0 < grid.occupied_fraction < 0.5


def test_occupancy_grid_update_and_query() -> None:
    field = build_field({"name": "neus", "radius": 0.5}, ENCODINGS["frequency"])  # default width: good sphere init
    grid = OccupancyGrid(resolution=16, bound=1.0, update_every=4)
    assert grid.occupied.all()
    assert not grid.update(field, step=3)
    assert grid.update(field, step=4, generator=torch.Generator().manual_seed(0))
    dirs = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    assert grid.query(0.5 * dirs).float().mean() > 0.95  # surface band occupied
    assert not grid.query(torch.zeros(1, 3)).any()  # deep inside skipped
    assert not grid.query(torch.tensor([[0.95, 0.95, 0.95]])).any()  # far outside skipped
    assert not grid.query(torch.tensor([[3.0, 0.0, 0.0]])).any()  # outside the box
    nerf = build_field({"name": "nerf", **SMALL, "density_bias": -30.0}, ENCODINGS["frequency"])
    g2 = OccupancyGrid(resolution=8, bound=1.0, ema_decay=0.0)
    g2.update(nerf, 0, force=True)
    # nothing occupied would be absorbing (no samples, no gradient, no recovery): sample everywhere
    assert g2.occupied_fraction == 1.0
    g2.occupied.zero_()
    # empty grid (e.g. loaded): rays still get valid samples and render the background exactly
    r = VolumeRenderer(nerf, num_samples=8, occupancy=g2, background_color=(0.2, 0.4, 0.6))
    out = r(_batch(4))
    assert torch.isfinite(out["t"]).all() and (out["weights"] == 0).all()
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.2, 0.4, 0.6]]).expand(4, 3))


def test_encoding_mlp_lr_scale_sets_the_mlp_learning_rate() -> None:
    """Frequency-encoded MLPs train at encoding.mlp_lr_scale x the MLP rate; grids keep their own rate."""
    from nerfart_plugin.systems.base import param_groups

    freq = VolumeRenderer(build_field({"name": "neus", **SMALL}, {**ENCODINGS["frequency"], "mlp_lr_scale": 0.25}))
    groups = {g["name"]: g["lr"] for g in param_groups(freq, 1e-2, 4e-3)}
    assert groups == {"mlp": pytest.approx(1e-3)}
    grid = VolumeRenderer(build_field({"name": "neus", **SMALL}, ENCODINGS["grid"]))
    groups = {g["name"]: g["lr"] for g in param_groups(grid, 1e-2, 4e-3)}
    assert groups == {"grid": pytest.approx(1e-2), "mlp": pytest.approx(4e-3)}
    with pytest.raises(ConfigError, match="mlp_lr_scale"):
        build_field({"name": "neus"}, {**ENCODINGS["frequency"], "mlp_lr_scale": 0})


def test_systems_adam_is_fused_on_cpu_and_steps_like_plain_adam() -> None:
    """Both stages' optimizer (systems.base.adam) takes torch's fused kernel on a CPU and moves the
    parameters as the plain Adam with the same groups does, step after step (rates per group kept)."""
    from nerfart_plugin.systems.base import adam, param_groups

    torch.manual_seed(0)
    a = VolumeRenderer(build_field({"name": "nerf", **SMALL}, ENCODINGS["grid"]))
    b = copy.deepcopy(a)
    opt_a = adam(param_groups(a, 1e-2, 4e-3))
    opt_b = torch.optim.Adam(param_groups(b, 1e-2, 4e-3), betas=(0.9, 0.99), eps=1e-15)
    assert opt_a.defaults["fused"] and not opt_b.defaults["fused"]
    x = torch.rand(256, 3) * 2 - 1
    for _ in range(5):
        for r, opt in ((a, opt_a), (b, opt_b)):
            opt.zero_grad()
            out = r.field(x, torch.nn.functional.normalize(x, dim=-1))
            (out["sigma"].square().mean() + out["rgb"].mean()).backward()
            opt.step()
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.allclose(pa, pb, atol=1e-6, rtol=1e-5)
    assert [g["lr"] for g in opt_a.param_groups] == [g["lr"] for g in opt_b.param_groups]


def test_sharp_softplus_is_softplus_with_its_gradients_at_the_extremes() -> None:
    """The geometry nets' fast softplus equals F.softplus(beta=100) from deep negative to huge inputs, in
    float32 and bfloat16, and its first and second derivatives are softplus' (the analytic eikonal)."""
    from nerfart_plugin.fields.mlp import SharpSoftplus

    act = SharpSoftplus(100.0)
    x = torch.cat([torch.linspace(-1.0, 1.0, 200001), torch.tensor([-1e30, -50.0, 0.0, 50.0, 1e30])])
    ref = torch.nn.functional.softplus(x.double(), beta=100.0, threshold=30.0)
    assert torch.isfinite(act(x)).all()
    assert (act(x).double() - ref).abs().max() < 1e-7
    assert (act(x.bfloat16()).double() - ref).abs().max() < 1e-2 * (1 + ref.abs()).max()
    assert torch.isnan(act(torch.tensor([float("nan")]))).all()
    xd = (0.03 * torch.randn(64, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(act, (xd,))
    assert torch.autograd.gradgradcheck(act, (xd,))
    xg = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(act(xg).sum(), xg)
    assert torch.allclose(grad.double(), torch.sigmoid(100.0 * x.double()), atol=1e-6)
