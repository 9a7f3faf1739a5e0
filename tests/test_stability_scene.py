"""Numerical stability at the extremes: scene scale, a camera at the origin, degenerate ray weights,
and the first stylization step (stylized == source)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfart_plugin.data import load_scene
from nerfart_plugin.objectives.losses import directional_clip_loss, weight_regularization


def _llff_copy(src: Path, dst: Path, scale: float, origin_camera: bool) -> Path:
    shutil.copytree(src / "images_8", dst / "images_8")
    pb = np.load(src / "poses_bounds.npy").copy()
    poses = pb[:, :15].reshape(-1, 3, 5)
    if origin_camera:
        poses[:, :, 3] -= poses[0, :, 3]
    poses[:, :, 3] *= scale
    pb[:, :15] = poses.reshape(-1, 15)
    pb[:, 15:] *= scale
    np.save(dst / "poses_bounds.npy", pb)
    return dst


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_llff_scene_scale_does_not_change_the_normalized_scene(tmp_path: Path, shared_data: Path, scale: float) -> None:
    ref = load_scene("llff", shared_data / "llff_fern", factor=8, resolution=64)
    scene = load_scene("llff", _llff_copy(shared_data / "llff_fern", tmp_path / "s", scale, False), factor=8,
                       resolution=64)
    for t in (scene.c2w, scene.K, scene.near, scene.far, scene.normalization):
        assert torch.isfinite(t).all()
    torch.testing.assert_close(scene.c2w, ref.c2w, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(scene.near / scene.far, ref.near / ref.far, rtol=1e-4, atol=1e-5)
    assert scene.capture == ref.capture == "forward_facing"


def test_llff_camera_at_the_origin(tmp_path: Path, shared_data: Path) -> None:
    scene = load_scene("llff", _llff_copy(shared_data / "llff_fern", tmp_path / "o", 1.0, True), factor=8,
                       resolution=64)
    assert torch.isfinite(scene.c2w).all() and torch.isfinite(scene.normalization).all()
    assert (scene.far > scene.near).all()


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_h3ds_scene_scale(tmp_path: Path, shared_data: Path, scale: float) -> None:
    """World scaled by s: P' = K[R | s t], scale_mat' = diag(s,s,s,1) scale_mat -> same normalized scene."""
    src = shared_data / "girl"
    dst = tmp_path / "girl"
    shutil.copytree(src / "images", dst / "images")
    shutil.copytree(src / "matte", dst / "matte")
    cams = dict(np.load(src / "cameras.npz"))
    S = np.diag([scale, scale, scale, 1.0])
    for k in list(cams):
        if k.startswith("world_mat_"):
            P = cams[k].astype(np.float64)
            # P = K [R|t]; world points X' = s X  =>  P' = P @ diag(1/s,1/s,1/s,1)
            cams[k] = P @ np.linalg.inv(S)
        elif k.startswith("scale_mat_"):
            cams[k] = S @ cams[k].astype(np.float64)
    np.savez(dst / "cameras.npz", **cams)
    ref = load_scene("h3ds", src, resolution=32)
    scene = load_scene("h3ds", dst, resolution=32)
    assert torch.isfinite(scene.c2w).all()
    torch.testing.assert_close(scene.c2w, ref.c2w, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(scene.K, ref.K, rtol=1e-4, atol=1e-3)


@settings(max_examples=40, deadline=None)
@given(k=st.integers(2, 64), hot=st.integers(0, 63), scale=st.sampled_from([1e-6, 1.0, 1e4]))
def test_weight_regularization_one_hot_and_uniform(k: int, hot: int, scale: float) -> None:
    depths = (torch.linspace(0.1, 2.0, k, dtype=torch.float64) * scale)[None].repeat(2, 1)
    one_hot = torch.zeros(1, k, dtype=torch.float64)
    one_hot[0, hot % k] = 1.0
    uniform = torch.full((1, k), 1.0 / k, dtype=torch.float64)
    w = torch.cat([one_hot, uniform]).requires_grad_(True)
    per_ray = torch.stack([weight_regularization(w[i : i + 1], depths[i : i + 1]) for i in range(2)])
    per_ray.sum().backward()
    assert torch.isfinite(per_ray).all() and torch.isfinite(w.grad).all()
    assert float(per_ray[0]) == pytest.approx(0.0, abs=1e-12)  # a single spike has no spread
    d = depths[1]
    brute = float((uniform[0][:, None] * uniform[0][None] * (d[:, None] - d[None]).abs()).sum())
    assert float(per_ray[1]) == pytest.approx(brute, rel=1e-9)


def test_first_stylization_step_has_a_finite_useful_gradient() -> None:
    """At step 0 the stylized render equals the source: the image direction is zero (Eq. 4)."""
    torch.manual_seed(0)
    src = torch.randn(1, 32)
    img = src.clone().requires_grad_(True)
    tgt, src_txt = torch.randn(32), torch.randn(32)
    loss = directional_clip_loss(img, src, tgt, src_txt)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(img.grad).all()
    assert float(img.grad.norm()) > 0
    with torch.no_grad():  # one gradient step moves the image toward the text direction
        stepped = img - 1e-3 * img.grad / img.grad.norm()
    assert float(directional_clip_loss(stepped, src, tgt, src_txt)) < float(loss)
