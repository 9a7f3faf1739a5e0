"""Eq. 1 volume rendering, VolSDF density and NeuS alpha against hand-computed / direct values."""

from __future__ import annotations

import math

import pytest
import torch

from nerfart_plugin.fields.field import Field
from nerfart_plugin.fields.opacity import neus_alpha, volsdf_density
from nerfart_plugin.rendering import VolumeRenderer, volume_weights, weights_from_alpha

LN2, LN4 = math.log(2.0), math.log(4.0)


def test_volume_weights_hand_computed() -> None:
    # optical depths tau = sigma*delta = [ln2, ln2, ln4]  ->  alpha = 1 - exp(-tau) = [1/2, 1/2, 3/4]
    # T = [1, 1/2, 1/4]  ->  w = T*alpha = [1/2, 1/4, 3/16], sum = 15/16
    sigma = torch.tensor([[LN2, 2 * LN2, LN4]])
    deltas = torch.tensor([[1.0, 0.5, 1.0]])
    w, T = volume_weights(sigma, deltas)
    torch.testing.assert_close(T, torch.tensor([[1.0, 0.5, 0.25]]))
    torch.testing.assert_close(w, torch.tensor([[0.5, 0.25, 3 / 16]]))
    w2, T2 = weights_from_alpha(torch.tensor([[0.5, 0.5, 0.75]]))
    torch.testing.assert_close(w2, w)
    torch.testing.assert_close(T2, T)


def test_weights_from_alpha_opaque_sample() -> None:
    # alpha = [1, 0.5]: first sample takes everything, T_1 = max(0, 1e-10) ~ 0
    w, T = weights_from_alpha(torch.tensor([[1.0, 0.5]], requires_grad=True))
    assert w[0, 0].item() == 1.0 and w[0, 1].item() < 1e-9 and T[0, 1].item() <= 1.001e-10


class _StubField(Field):
    """Density field by depth z: sigma = ln2 for z < 2 else ln4; colour red / green / blue by z bin."""

    bound = 100.0

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> dict:
        z = x[:, 2]
        sigma = torch.where(z < 2.0, torch.full_like(z, LN2), torch.full_like(z, LN4))
        rgb = torch.nn.functional.one_hot(z.floor().long().clamp(0, 2), 3).float()
        return {"rgb": rgb, "sigma": sigma}

    def alpha(self, out: dict, deltas: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return 1.0 - torch.exp(-out["sigma"].reshape(deltas.shape) * deltas)


@pytest.mark.parametrize("dir_scale", [1.0, 2.0])
def test_renderer_hand_computed(dir_scale: float) -> None:
    # Ray from 0 along +z, K=3 unperturbed sections of unit *metric* length centred at z = 0.5, 1.5, 2.5.
    # tau = [ln2, ln2, ln4] -> w = [1/2, 1/4, 3/16]; colours red, green, blue; white background gets T_final = 1/16:
    # rgb = (1/2 + 1/16, 1/4 + 1/16, 3/16 + 1/16) = (9/16, 5/16, 1/4); opacity = 15/16.
    # depth = (1/2*t1 + 1/4*t2 + 3/16*t3) / (15/16) with t = z/dir_scale -> 7/6 / dir_scale.
    # dir_scale = 2 mimics NDC (non-unit dirs): t in [0, 1.5], deltas = dt * |d| = 1 still.
    r = VolumeRenderer(_StubField(), num_samples=3, background_color=(1, 1, 1), clip_to_bound=False)
    batch = {
        "rays_o": torch.zeros(1, 3),
        "rays_d": torch.tensor([[0.0, 0.0, dir_scale]]),
        "near": torch.zeros(1),
        "far": torch.full((1,), 3.0 / dir_scale),
    }
    out = r(batch, perturb=False)
    torch.testing.assert_close(out["deltas"], torch.ones(1, 3))
    torch.testing.assert_close(out["weights"], torch.tensor([[0.5, 0.25, 3 / 16]]))
    torch.testing.assert_close(out["rgb"], torch.tensor([[9 / 16, 5 / 16, 1 / 4]]))
    torch.testing.assert_close(out["opacity"], torch.tensor([15 / 16]))
    torch.testing.assert_close(out["depth"], torch.tensor([7 / 6 / dir_scale]))
    # no compositing: rgb = sum w c only; black constant background = same numbers
    r_none = VolumeRenderer(_StubField(), num_samples=3, background_color=None, clip_to_bound=False)
    torch.testing.assert_close(r_none(batch)["rgb"], torch.tensor([[0.5, 0.25, 3 / 16]]))
    # per-batch background override
    out_bg = r({**batch, "bg_color": torch.tensor([0.0, 0.0, 1.0])})
    torch.testing.assert_close(out_bg["rgb"], torch.tensor([[0.5, 0.25, 3 / 16 + 1 / 16]]))


def test_volsdf_density_formula() -> None:
    beta = 0.1
    sdf = torch.tensor([0.0, 0.2, -0.2, 1.0])
    # outside: 0.5 exp(-d/beta)/beta ; inside: (1 - 0.5 exp(d/beta))/beta
    expected = torch.tensor([0.5 / beta, 0.5 * math.exp(-2) / beta, (1 - 0.5 * math.exp(-2)) / beta, 0.5 * math.exp(-10) / beta])
    torch.testing.assert_close(volsdf_density(sdf, beta), expected)
    torch.testing.assert_close(volsdf_density(sdf, torch.tensor(beta)), expected)
    # density is continuous and decreasing in d, with the right slope at 0 from both sides (-0.5/beta^2)
    d = torch.tensor([-1e-4, 0.0, 1e-4], requires_grad=True)
    s = volsdf_density(d, beta)
    (g,) = torch.autograd.grad(s.sum(), d)
    torch.testing.assert_close(g, torch.full((3,), -0.5 / beta**2), rtol=1e-2, atol=0)


def _neus_alpha_direct(sdf, cos, deltas, inv_s, r):
    iter_cos = -(torch.relu(-cos * 0.5 + 0.5) * (1 - r) + torch.relu(-cos) * r)
    nxt = sdf + iter_cos * deltas * 0.5
    prv = sdf - iter_cos * deltas * 0.5
    phi = lambda v: 1.0 / (1.0 + torch.exp(-v * inv_s))  # noqa: E731
    p, c = phi(prv) - phi(nxt), phi(prv)
    return ((p + 1e-5) / (c + 1e-5)).clip(0.0, 1.0)


@pytest.mark.parametrize("r", [1.0, 0.3])
def test_neus_alpha_matches_direct(r: float) -> None:
    g = torch.Generator().manual_seed(0)
    sdf = (torch.rand(8, 16, generator=g) - 0.5) * 0.4
    cos = torch.rand(8, 16, generator=g) * 2 - 1
    deltas = torch.rand(8, 16, generator=g) * 0.05 + 1e-3
    for inv_s in (5.0, 64.0):
        torch.testing.assert_close(neus_alpha(sdf, cos, deltas, inv_s, r), _neus_alpha_direct(sdf, cos, deltas, inv_s, r))


def test_neus_alpha_surface_crossing() -> None:
    # a ray crossing the surface head-on (cos = -1) across a thin section at sdf = 0 is nearly opaque for sharp inv_s
    a = neus_alpha(torch.zeros(1, 1), -torch.ones(1, 1), torch.full((1, 1), 0.1), 1e4)
    assert a.item() > 0.99
    # far in front of the surface: transparent; zero-length section: transparent
    assert neus_alpha(torch.ones(1, 1), -torch.ones(1, 1), torch.full((1, 1), 0.1), 100.0).item() < 1e-3
    assert neus_alpha(-torch.ones(1, 1), -torch.ones(1, 1), torch.zeros(1, 1), 100.0).item() == 0.0


def test_a_custom_field_with_the_plain_forward_contract_renders() -> None:
    """A Field subclass with only forward(x, d) / alpha / geometry: the base class answers the rest
    (query without with_normal, density occupancy, no regularizers, no surface width)."""
    from nerfart_plugin.fields import OccupancyGrid

    r = VolumeRenderer(_StubField(), num_samples=3, clip_to_bound=False)
    batch = {"rays_o": torch.zeros(2, 3), "rays_d": torch.tensor([[0.0, 0.0, 1.0]] * 2),
             "near": torch.zeros(2), "far": torch.full((2,), 3.0)}
    colour_only = r.render_chunked(batch, with_normals=False)
    torch.testing.assert_close(colour_only["rgb"], r.render_chunked(batch)["rgb"])
    with torch.enable_grad():
        assert r(batch)["regularizers"] == {}
    field = _StubField()
    field.geometry = lambda x: torch.full((x.shape[0],), 50.0)
    grid = OccupancyGrid(resolution=4, bound=1.0)
    assert grid.update(field, 0, force=True) and grid.occupied_fraction == 1.0
