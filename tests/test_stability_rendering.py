"""Property tests: extreme inputs give finite values AND finite gradients."""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from render_helpers import check_sharp_surface_under_autocast

from nerfart_plugin.fields import build_field
from nerfart_plugin.fields.field import Field
from nerfart_plugin.fields.opacity import neus_alpha, volsdf_density
from nerfart_plugin.rendering import VolumeRenderer, volume_weights, weights_from_alpha

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
sigma_st = st.one_of(st.just(0.0), st.just(1e8), st.floats(0.0, 1e8, allow_nan=False))
delta_st = st.one_of(st.just(0.0), st.floats(0.0, 10.0, allow_nan=False))
sdf_st = st.one_of(st.just(0.0), st.just(1e4), st.just(-1e4), st.floats(-1e4, 1e4, allow_nan=False))


def _finite(*ts: torch.Tensor) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in ts)


@SETTINGS
@given(st.lists(st.tuples(sigma_st, delta_st), min_size=1, max_size=6))
def test_volume_weights_extremes(pairs: list) -> None:
    sigma = torch.tensor([[p[0] for p in pairs]], dtype=torch.float32, requires_grad=True)
    deltas = torch.tensor([[p[1] for p in pairs]], dtype=torch.float32, requires_grad=True)
    w, T = volume_weights(sigma, deltas)
    assert _finite(w, T)
    assert (w >= 0).all() and w.sum() <= 1 + 1e-5 and (T <= 1).all()
    (w.sum() + T.sum()).backward()
    assert _finite(sigma.grad, deltas.grad)


@SETTINGS
@given(st.lists(st.one_of(st.just(0.0), st.just(1.0), st.floats(0.0, 1.0)), min_size=1, max_size=8))
def test_weights_from_alpha_extremes(alphas: list) -> None:
    a = torch.tensor([alphas], dtype=torch.float32, requires_grad=True)
    w, T = weights_from_alpha(a)
    assert _finite(w, T) and w.sum() <= 1 + 1e-5
    (w.sum() + (w * torch.arange(len(alphas))).sum()).backward()
    assert _finite(a.grad)


@SETTINGS
@given(sdf_st, st.one_of(st.just(1e-6), st.just(10.0), st.floats(1e-6, 10.0)))
def test_volsdf_density_extremes(d: float, beta: float) -> None:
    sdf = torch.tensor([d], requires_grad=True)
    b = torch.tensor(beta, requires_grad=True)
    sigma = volsdf_density(sdf, b)
    assert _finite(sigma) and (sigma >= 0).all() and (sigma <= 1.0 / beta * (1 + 1e-5)).all()
    alpha = -torch.expm1(-sigma * 0.01)
    (sigma.sum() + alpha.sum()).backward()
    assert _finite(sdf.grad, b.grad)


@SETTINGS
@given(sdf_st, st.floats(-1.0, 1.0), delta_st,
       st.one_of(st.just(1.0), st.just(1e5), st.floats(1.0, 1e5)), st.floats(0.0, 1.0))
def test_neus_alpha_extremes(d: float, cos: float, delta: float, inv_s: float, r: float) -> None:
    sdf = torch.tensor([[d]], requires_grad=True)
    c = torch.tensor([[cos]], requires_grad=True)
    dl = torch.tensor([[delta]], requires_grad=True)
    s = torch.tensor(inv_s, requires_grad=True)
    a = neus_alpha(sdf, c, dl, s, r)
    assert _finite(a) and ((a >= 0) & (a <= 1)).all()
    w, _ = weights_from_alpha(a)
    (a.sum() + w.sum()).backward()
    assert _finite(sdf.grad, c.grad, dl.grad, s.grad)


class _ConstField(Field):
    """Constant density ``sigma`` everywhere (leaf parameter so gradients can be checked)."""

    bound = 1.0

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = torch.nn.Parameter(torch.tensor(float(sigma)))

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> dict:
        return {"rgb": torch.full_like(x, 0.25), "sigma": self.sigma.expand(x.shape[0])}

    def alpha(self, out: dict, deltas: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return -torch.expm1(-out["sigma"].reshape(deltas.shape).float() * deltas)


@SETTINGS
@given(sigma_st, st.floats(1.0, 3.0), st.floats(0.0, 2.0), st.booleans())
def test_renderer_extremes(sigma: float, near: float, length: float, miss: bool) -> None:
    field = _ConstField(sigma)
    r = VolumeRenderer(field, num_samples=8, background_color=(0.0, 1.0, 0.0))
    o = torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, -2.0]])
    if miss:
        o = o + torch.tensor([5.0, 0.0, 0.0])  # rays that hit nothing (outside the box)
    batch = {"rays_o": o, "rays_d": torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]),
             "near": torch.full((2,), near), "far": torch.full((2,), near + length)}  # length 0: near == far
    out = r(batch, perturb=True, generator=torch.Generator().manual_seed(0))
    assert _finite(out["rgb"], out["depth"], out["opacity"], out["weights"])
    if miss or sigma == 0.0 or length == 0.0:
        assert (out["weights"] == 0).all()
        torch.testing.assert_close(out["rgb"], torch.tensor([[0.0, 1.0, 0.0]]).expand(2, 3))
    (out["rgb"].sum() + out["depth"].sum()).backward()
    assert field.sigma.grad is None or _finite(field.sigma.grad)


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_autocast_forward_finite(backbone: str, dtype: torch.dtype) -> None:
    field = build_field({"name": backbone, "hidden_dim": 16, "color_hidden_dim": 16},
                        {"name": "grid", "resolution": 16, "n_components": 4, "out_features": 8})
    r = VolumeRenderer(field, num_samples=16)
    g = torch.Generator().manual_seed(0)
    R = 16
    batch = {"rays_o": torch.tensor([0.0, 0.0, -2.5]).expand(R, 3).contiguous(),
             "rays_d": torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.2 * torch.randn(R, 3, generator=g), dim=-1),
             "near": torch.full((R,), 1.0), "far": torch.full((R,), 4.0)}
    with torch.autocast("cpu", dtype=dtype):
        out = r(batch)
        out_ng = r.render_chunked(batch, chunk=8)
    for k in ("rgb", "depth", "opacity"):
        assert _finite(out[k]) and _finite(out_ng[k]), k
    if field.is_sdf:
        assert _finite(out["normal"], out["regularizers"]["eikonal"])


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
def test_sdf_fields_far_points_finite(backbone: str) -> None:
    field = build_field({"name": backbone, "hidden_dim": 16, "color_hidden_dim": 16}, {"name": "frequency", "n_freqs": 4})
    x = torch.tensor([[1e4, 0.0, 0.0], [-1e4, 1e4, 0.0], [0.0, 0.0, 0.0]], requires_grad=True)
    d = torch.nn.functional.normalize(torch.ones(3, 3), dim=-1)
    out = field(x, d)
    deltas = torch.full((1, 3), 0.1)
    a = field.alpha(out, deltas, d[None])
    assert _finite(out["sdf"], out["gradient"], a)
    (a.sum() + out["rgb"].sum() + field.regularizers(out)["eikonal"]).backward()
    assert all(_finite(p.grad) for p in field.parameters() if p.grad is not None)


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
def test_bfloat16_autocast_keeps_a_sharp_surface_where_float32_puts_it(backbone: str) -> None:
    """trainer.precision=bf16-mixed on a CPU (render_helpers.check_sharp_surface_under_autocast)."""
    check_sharp_surface_under_autocast(backbone, torch.device("cpu"), torch.bfloat16)


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
@pytest.mark.parametrize("training", [False, True])
def test_analytic_sdf_gradient_stays_float32_under_bfloat16_autocast(backbone: str, training: bool) -> None:
    """The geometry net runs in float32 under trainer.precision=*-mixed, and so does the backward that
    gives its analytic gradient (normals, eikonal): inside the autocast those backward matmuls ran in
    bfloat16 and moved it by up to 1.1% of its length (a scratch measurement: 64-wide frequency-encoded net, 4096 points)."""
    torch.manual_seed(0)
    field = build_field({"name": backbone, "hidden_dim": 64, "color_hidden_dim": 16, "grad_type": "analytic"},
                        {"name": "frequency", "n_freqs": 6})
    x = torch.rand(2048, 3) - 0.5
    d = torch.nn.functional.normalize(torch.randn(2048, 3), dim=-1)
    with torch.set_grad_enabled(training):
        ref = field(x, d)["gradient"]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = field(x, d)["gradient"]
            sub = field._gradient(x[:256]) if training else ref[:256]  # the grad_samples subset (training only)
    assert low.dtype == sub.dtype == torch.float32
    torch.testing.assert_close(low, ref, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(sub, ref[:256], rtol=1e-6, atol=1e-7)
