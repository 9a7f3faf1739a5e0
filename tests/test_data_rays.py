"""Rays, NDC warp, camera paths and intrinsics scaling (synthetic cameras + the default scene)."""

from __future__ import annotations

import math

import pytest
import torch

from nerfart_plugin.cameras.capture import scale_intrinsics
from nerfart_plugin.cameras.orbits import orbit_path
from nerfart_plugin.data import load_scene
from nerfart_plugin.data.datamodule import default_scene_path
from nerfart_plugin.data.rays import ndc_rays, pixel_rays, rays_for_views


@pytest.fixture(scope="module")
def default_scene():
    return load_scene("h3ds", default_scene_path(), resolution=64)


@pytest.fixture(scope="module")
def fern_scene(shared_data):
    return load_scene("llff", shared_data / "llff_fern", factor=8, resolution=96)


def _K(f=50.0, W=64, H=48):
    return torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])


def _rot(axis, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    if axis == "y":
        return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]])


def test_pixel_rays_opencv_and_unit():
    K = _K()
    c2w = torch.cat([torch.eye(3), torch.tensor([[1.0], [2.0], [3.0]])], 1)
    o, d = pixel_rays(K, c2w, 48, 64)
    assert o.shape == (48, 64, 3) and d.shape == (48, 64, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(48, 64), atol=1e-6)
    assert torch.allclose(o[5, 7], torch.tensor([1.0, 2.0, 3.0]))
    # pixel centres: the four central pixels straddle the principal point symmetrically
    assert torch.allclose(d[23, 31, :2], -d[24, 32, :2], atol=1e-6)
    # x grows to the right, y grows downwards, z forward (OpenCV)
    assert d[0, -1, 0] > 0 and d[0, 0, 0] < 0 and d[-1, 0, 1] > 0 and (d[..., 2] > 0).all()


def test_pixel_rays_reproject_to_pixel_centres():
    K = _K(40.0, 32, 24)
    R = _rot("y", 30) @ _rot("x", -10)
    c2w = torch.cat([R, torch.tensor([[0.5], [-0.2], [1.0]])], 1).double()
    o, d = pixel_rays(K, c2w, 24, 32)
    X = o + 2.7 * d  # points along the rays
    w2c_R = c2w[:3, :3].T
    Xc = (X - c2w[:3, 3]) @ w2c_R.T
    uv = Xc @ K.double().T
    uv = uv[..., :2] / uv[..., 2:]
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    assert torch.allclose(uv[..., 0], u.double() + 0.5, atol=1e-6)
    assert torch.allclose(uv[..., 1], v.double() + 0.5, atol=1e-6)


def test_ndc_rays_range_and_projection():
    # forward-facing frame: camera at origin looking along -z (OpenCV c2w = diag(1,-1,-1))
    K = _K(60.0, 64, 48)
    c2w = torch.cat([torch.diag(torch.tensor([1.0, -1.0, -1.0])), torch.zeros(3, 1)], 1).double()
    o, d = pixel_rays(K, c2w, 48, 64)
    on, dn = ndc_rays(o.reshape(-1, 3), d.reshape(-1, 3), K.double(), near_plane=1.0)
    assert torch.allclose(on[:, 2], -torch.ones_like(on[:, 2]))  # t = 0 on the near plane
    far = on + dn  # t = 1 -> infinity
    assert torch.allclose(far[:, 2], torch.ones_like(far[:, 2]), atol=1e-6)
    assert on[:, :2].abs().max() <= 1.0 + 1e-6  # the image maps into [-1,1]^2
    assert not torch.allclose(dn.norm(dim=-1), torch.ones(dn.shape[0], dtype=dn.dtype))
    # a world point at depth z maps to NDC z = 1 + 2 near / z (z negative)
    z = -3.0
    t_world = z / d.reshape(-1, 3)[:, 2]
    p = o.reshape(-1, 3) + t_world[:, None] * d.reshape(-1, 3)
    expect_ndc_z = 1 + 2 * 1.0 / z
    t_ndc = (expect_ndc_z - on[:, 2]) / dn[:, 2]
    pn = on + t_ndc[:, None] * dn
    assert torch.allclose(pn[:, 0], -2 * 60.0 / 64 * p[:, 0] / p[:, 2], atol=1e-6)
    assert ((t_ndc >= 0) & (t_ndc <= 1)).all()


def test_scale_intrinsics_exact_under_resize():
    K = _K(50.0, 64, 48)
    K2 = scale_intrinsics(K, 0.5, 0.25)
    assert torch.allclose(K2, torch.tensor([[25.0, 0, 16], [0, 12.5, 6], [0, 0, 1]]))
    # pixel centre of the resized image <-> same ray as the corresponding continuous point
    c2w = torch.cat([torch.eye(3), torch.zeros(3, 1)], 1)
    _, d = pixel_rays(K2, c2w, 12, 32)
    _, dfull = pixel_rays(K, c2w, 48, 64)
    # resized pixel (0,0) centre (0.5,0.5) corresponds to full-res point (1.0, 2.0), between pixels
    ray = torch.tensor([(1.0 - 32) / 50.0, (2.0 - 24) / 50.0, 1.0])
    assert torch.allclose(d[0, 0], ray / ray.norm(), atol=1e-6)


def test_rays_for_views_batch(default_scene):
    b = rays_for_views(default_scene, [1], background=(1.0, 1.0, 1.0))
    n = default_scene.height * default_scene.width
    assert b["rays_o"].shape == (n, 3) and b["rays_d"].shape == (n, 3) and b["rgb"].shape == (n, 3)
    assert b["mask"].shape == (n,) and b["view_id"].dtype == torch.long and (b["view_id"] == 1).all()
    assert b["H"] == default_scene.height and b["W"] == default_scene.width
    assert (b["far"] > b["near"]).all()
    bg = b["mask"] < 0.01
    assert bg.any() and torch.allclose(b["rgb"][bg], torch.ones_like(b["rgb"][bg]), atol=0.02)
    b2 = rays_for_views(default_scene, [0, 2])
    assert b2["rays_o"].shape == (2 * n, 3) and "H" not in b2


def test_orbit_path_object(default_scene):
    P = orbit_path(default_scene, 40)
    assert P.shape == (40, 3, 4)
    R = P[:, :, :3]
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3).expand(40, 3, 3), atol=1e-5)
    assert torch.allclose(torch.det(R), torch.ones(40), atol=1e-5)
    dist = default_scene.c2w[:, :, 3].norm(dim=-1).mean()
    assert torch.allclose(P[:, :, 3].norm(dim=-1), dist.expand(40), rtol=0.15)
    # cameras look at the centre (z axis toward the sphere centre)
    cos = (-P[:, :, 3] / P[:, :, 3].norm(dim=-1, keepdim=True) * P[:, :, 2]).sum(-1)
    assert (cos > math.cos(math.radians(10))).all()
    # image "up" agrees with the training cameras
    assert (P[:, :, 1] @ default_scene.c2w[:, :, 1].mean(0) > 0.8).all()
    # smooth: small steps
    step = (P[1:, :, 3] - P[:-1, :, 3]).norm(dim=-1)
    assert step.max() < 0.5 * dist


def test_orbit_path_forward_facing_spiral(fern_scene):
    P = orbit_path(fern_scene, 30)
    assert P.shape == (30, 3, 4)
    mean_z = fern_scene.c2w[:, :, 2].mean(0)
    assert (P[:, :, 2] @ mean_z > math.cos(math.radians(20))).all()
    spread = fern_scene.c2w[:, :, 3].std(0).norm()
    assert (P[:, :, 3].norm(dim=-1) < 5 * spread + 1e-3).all()


def test_pixel_rays_are_float32_under_bfloat16_autocast() -> None:
    """Rays made inside a step run under trainer.precision=bf16-mixed (validation views): a bfloat16 rotation
    tilted them by ~1 pixel (a trained selfie's view then read 34.9 dB against float32's)."""
    K = torch.tensor([[500.0, 0.0, 270.0], [0.0, 500.0, 480.0], [0.0, 0.0, 1.0]])
    c2w = torch.tensor([[0.36, 0.48, -0.8, 0.1], [-0.8, 0.6, 0.0, 0.2], [0.48, 0.64, 0.6, -2.5]])
    _, ref = pixel_rays(K, c2w, 96, 54)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        _, low = pixel_rays(K, c2w, 96, 54)
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, ref, rtol=0.0, atol=1e-6)
