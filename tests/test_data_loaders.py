"""Loaders on the real data in ../shared/data (small resolutions) and the shipped default scene."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfart_plugin.config import registry
from nerfart_plugin.data import load_scene
from nerfart_plugin.data.datamodule import default_scene_path
from nerfart_plugin.data.llff import read_poses_bounds
from nerfart_plugin.data.normalize import detect_capture
from nerfart_plugin.errors import DataError


def _angle_to_origin_deg(c2w: torch.Tensor) -> np.ndarray:
    c = c2w[:, :, 3]
    cos = (-c / c.norm(dim=-1, keepdim=True) * c2w[:, :, 2]).sum(-1).clamp(-1, 1)
    return np.degrees(np.arccos(cos.numpy()))


def _check_rotations(c2w: torch.Tensor) -> None:
    R = c2w[:, :, :3].double()
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3, dtype=R.dtype).expand_as(R), atol=1e-4)
    assert torch.allclose(torch.det(R), torch.ones(len(R), dtype=R.dtype), atol=1e-4)


def test_registry_names():
    assert {"h3ds", "llff", "selfie", "nerfstudio"} <= set(registry.names("data"))


@pytest.mark.slow
def test_every_loader_declares_its_settings_and_refuses_unknown_options():
    """Each loader's typed Config is its settings (what the schema checks and --help lists); an unknown or
    mistyped option, from Python or from the command line, is one ConfigError with the closest valid name."""
    from nerfart_plugin.config.components import config_of
    from nerfart_plugin.config.sections import check_section
    from nerfart_plugin.errors import ConfigError

    for kind in registry.names("data"):
        fields = config_of(registry.get("data", kind)).model_fields
        assert {"resolution", "holdout_every", "use_masks"} <= set(fields), kind
        assert all(info.description for info in fields.values()), f"{kind}: a setting without a meaning"
    with pytest.raises(ConfigError, match=r"data.resolutoin=64: unknown setting; did you mean data.resolution\?"):
        load_scene("h3ds", default_scene_path(), resolutoin=64)
    _, issues = check_section("data", {"name": "llff", "path": "x", "factr": 4})
    assert [str(i) for i in issues] == [i for i in map(str, issues) if "did you mean data.factor?" in i] and issues


def test_girl_h3ds(shared_data):
    s = load_scene("h3ds", shared_data / "girl", resolution=64)
    assert s.images.shape == (31, 64, 64, 3) and s.masks.shape == (31, 64, 64)
    assert s.capture == "object" and s.c2w.shape == (31, 3, 4) and s.K.shape == (31, 3, 3)
    assert 0 <= s.images.min() and s.images.max() <= 1
    _check_rotations(s.c2w)
    # every camera looks at the unit-sphere centre (OpenCV: z forward)
    assert _angle_to_origin_deg(s.c2w).max() < 8.0
    assert (s.c2w[:, :, 3].norm(dim=-1) > 1.0).all()  # cameras outside the unit sphere
    # images are upright: camera y (down) points against the mean "up"
    assert (s.c2w[:, :, 1] @ s.c2w[:, :, 1].mean(0) > 0.5).all()
    assert s.val_ids == list(range(0, 31, 8)) and sorted(s.train_ids + s.val_ids) == list(range(31))
    assert (s.near < s.far).all() and torch.allclose(s.far - s.near, torch.full((31,), 2.0), atol=1e-4)
    assert len(s.content_hash) == 64
    # normalization maps camera centres of the original frame into the normalized one
    assert s.normalization.shape == (4, 4)


@pytest.mark.slow
def test_girl_intrinsics_scale_with_resolution(shared_data):
    a = load_scene("h3ds", shared_data / "girl", resolution=128)
    b = load_scene("h3ds", shared_data / "girl", resolution=32)
    full = load_scene("h3ds", shared_data / "girl", resolution=None, holdout_every=0)
    assert full.images.shape[1:3] == (512, 512) and full.val_ids == []
    assert torch.allclose(a.K[:, :2], full.K[:, :2] / 4, rtol=1e-5, atol=1e-4)
    assert torch.allclose(b.K[:, :2], full.K[:, :2] / 16, rtol=1e-5, atol=1e-4)
    assert torch.allclose(a.c2w, b.c2w) and a.content_hash != b.content_hash
    # the mask centroid projects near the image location of the sphere centre
    K, c2w = a.K[3].double(), a.c2w[3].double()
    x = c2w[:, :3].T @ (torch.zeros(3, dtype=torch.float64) - c2w[:, 3])
    uv = (K @ x)[:2] / x[2]
    m = a.masks[3].double()
    vv, uu = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
    cu, cv = (m * (uu + 0.5)).sum() / m.sum(), (m * (vv + 0.5)).sum() / m.sum()
    assert abs(float(uv[0] - cu)) < 20 and abs(float(uv[1] - cv)) < 30


@pytest.mark.slow
def test_cameras_sphere_npz(shared_data):
    s = load_scene("h3ds", shared_data / "girl", resolution=32, cameras_file="cameras_sphere.npz")
    assert s.capture == "object" and _angle_to_origin_deg(s.c2w).max() < 15.0


@pytest.mark.slow
def test_fangzhou_ignores_colmap_output(shared_data):
    s = load_scene("h3ds", shared_data / "fangzhou_nature", resolution=48)
    assert s.num_images == 100 and s.images.shape[1:3] == (48, 27)
    assert "colmap_output.txt" not in s.image_names
    assert any("colmap_output.txt" in n for n in s.notes)
    assert _angle_to_origin_deg(s.c2w).max() < 10.0


@pytest.mark.slow
def test_yanan_93_images_100_mattes(shared_data):
    s = load_scene("h3ds", shared_data / "yanan_nature", resolution=48)
    assert s.num_images == 93 and s.masks.shape[0] == 93
    assert any("100 mattes for 93 images" in n and "000094.png" in n for n in s.notes)
    # without masks the capture is detected from the cameras instead
    s2 = load_scene("h3ds", shared_data / "yanan_nature", resolution=24, use_masks=False)
    assert s2.masks is None and s2.capture in ("forward_facing", "unbounded")


def test_llff_fern(shared_data):
    s = load_scene("llff", shared_data / "llff_fern", factor=8)
    assert s.images.shape == (20, 378, 504, 3) and s.capture == "forward_facing" and s.masks is None
    pb = read_poses_bounds(shared_data / "llff_fern" / "poses_bounds.npy")
    assert torch.allclose(s.K[:, 0, 0], torch.tensor(pb.hwf[:, 2] / 8, dtype=torch.float32), rtol=1e-5)
    assert torch.allclose(s.K[0, :2, 2], torch.tensor([252.0, 189.0]))
    _check_rotations(s.c2w)
    # all cameras face the same way: along -z of the recentred LLFF frame
    z = s.c2w[:, :, 2]
    assert (z @ torch.tensor([0.0, 0.0, -1.0]) > math.cos(math.radians(15))).all()
    # bd_factor scaling: the smallest near bound is 1/0.75
    assert abs(float(s.near.min()) - 1 / 0.75) < 1e-4
    assert any("ndc" in n.lower() for n in s.notes)
    small = load_scene("llff", shared_data / "llff_fern", factor=8, resolution=126)
    assert small.images.shape[1:3] == (95, 126) or small.images.shape[1:3] == (94, 126)
    assert torch.allclose(small.K[0, 0, 0], s.K[0, 0, 0] * 126 / 504, rtol=1e-4)


def test_llff_pose_convention_matches_reference(shared_data):
    """LLFF [down, right, back] -> OpenCV [right, down, forward]."""
    raw = np.load(shared_data / "llff_fern" / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    pb = read_poses_bounds(shared_data / "llff_fern" / "poses_bounds.npy")
    np.testing.assert_allclose(pb.c2w[:, :3, 0], raw[:, :, 1])
    np.testing.assert_allclose(pb.c2w[:, :3, 1], raw[:, :, 0])
    np.testing.assert_allclose(pb.c2w[:, :3, 2], -raw[:, :, 2])
    np.testing.assert_allclose(pb.c2w[:, :3, 3], raw[:, :, 3])


def test_beer_poses_not_forward_facing(shared_data):
    pb = read_poses_bounds(shared_data / "video_beer" / "poses_bounds.npy")
    assert pb.c2w.shape == (71, 4, 4) and pb.bounds.shape == (71, 2)
    assert tuple(pb.hwf[0]) == pytest.approx((1280.0, 720.0, pb.hwf[0, 2]))
    capture, reason = detect_capture(pb.c2w, None)
    assert capture == "unbounded", reason
    fern = read_poses_bounds(shared_data / "llff_fern" / "poses_bounds.npy")
    assert detect_capture(fern.c2w, None)[0] == "forward_facing"


@pytest.mark.slow
def test_selfie_loader_uses_existing_colmap_model(shared_data):
    s = load_scene("selfie", shared_data / "yanan_nature", resolution=48)
    assert s.num_images == 93 and s.capture == "object"
    assert any("existing COLMAP model" in n for n in s.notes)
    _check_rotations(s.c2w)
    assert _angle_to_origin_deg(s.c2w).max() < 25.0


def test_default_scene_asset():
    root = default_scene_path()
    total = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert total < 1.5e6, total
    assert (root / "SOURCE.md").is_file()
    s = load_scene("h3ds", root)
    assert s.images.shape == (31, 256, 256, 3) and s.capture == "object"
    assert _angle_to_origin_deg(s.c2w).max() < 8.0


def test_default_scene_matches_source(shared_data):
    a = load_scene("h3ds", default_scene_path())
    b = load_scene("h3ds", shared_data / "girl", resolution=256)
    assert torch.allclose(a.K, b.K, atol=1e-3) and torch.allclose(a.c2w, b.c2w, atol=1e-4)
    assert (a.images - b.images).abs().mean() < 0.02


def test_neus_idr_dtu_layout(shared_data, tmp_path):
    """image/ + mask/ + cameras_sphere.npz (NeuS's DTU release), DTU-style names: 000000.png vs 000.png."""
    girl = shared_data / "girl"
    root = tmp_path / "dtu_like"
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    for i, p in enumerate(sorted((girl / "images").iterdir())):
        (root / "image" / f"{i:06d}{p.suffix}").symlink_to(p)
    for i, p in enumerate(sorted((girl / "matte").iterdir())):
        (root / "mask" / f"{i:03d}.png").symlink_to(p)
    (root / "cameras_sphere.npz").symlink_to(girl / "cameras_sphere.npz")
    s = load_scene("h3ds", root, resolution=48)
    ref = load_scene("h3ds", girl, resolution=48, cameras_file="cameras_sphere.npz")
    assert s.image_names[:2] == ["000000.jpg", "000001.jpg"] and s.capture == "object"
    for a, b in ((s.images, ref.images), (s.masks, ref.masks), (s.c2w, ref.c2w), (s.K, ref.K)):
        assert torch.equal(a, b)
    assert any("views from image/, mattes from mask/" in n and "cameras_sphere.npz" in n for n in s.notes)
    # an empty-handed folder names both layouts
    (root / "image").rename(root / "photos")
    with pytest.raises(DataError, match=r"looked for images/ or image/ \(found mask/, photos/\)"):
        load_scene("h3ds", root)
