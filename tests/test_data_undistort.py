"""Lens undistortion for every COLMAP camera model (pycolmap) and nerfstudio's OpenCV models.

Checks map points, not code paths: a "coordinate image" (each pixel holds its own
pixel-centre coordinates) is undistorted; at the pinhole projection ``K X`` of a 3D
point it must then hold the point's projection through the distorted lens model.
For the OpenCV family the distorted projection comes from ``cv2.projectPoints``, an
implementation independent of pycolmap's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from camera_helpers import interior_error, look_at, pattern_seen_by, pinhole_pattern
from PIL import Image

from nerfart_plugin.data import load_scene
from nerfart_plugin.data.colmap import project, read_colmap_model, reprojection_errors
from nerfart_plugin.data.undistort import colmap_camera, colmap_maps, opencv_maps, remap
from nerfart_plugin.errors import DataError

W, H = 160, 120
FX, FY, CX, CY = 110.0, 112.0, 81.3, 58.6

#: realistic, clearly non-zero lens parameters per model (after the focal/principal point ones)
MODELS = {
    "SIMPLE_PINHOLE": [FX, CX, CY],
    "PINHOLE": [FX, FY, CX, CY],
    "SIMPLE_RADIAL": [FX, CX, CY, -0.18],
    "RADIAL": [FX, CX, CY, -0.15, 0.04],
    "OPENCV": [FX, FY, CX, CY, -0.16, 0.05, 0.004, -0.003],
    "FULL_OPENCV": [FX, FY, CX, CY, -0.2, 0.06, 0.003, -0.002, 0.01, 0.05, -0.01, 0.005],
    "OPENCV_FISHEYE": [FX, FY, CX, CY, 0.06, -0.02, 0.004, -0.001],
    "SIMPLE_RADIAL_FISHEYE": [FX, CX, CY, 0.05],
    "RADIAL_FISHEYE": [FX, CX, CY, 0.05, -0.01],
    "FOV": [FX, FY, CX, CY, 0.9],
    "THIN_PRISM_FISHEYE": [FX, FY, CX, CY, 0.05, -0.01, 0.002, -0.001, 0.003, -0.001, 0.002, 0.001],
    "RAD_TAN_THIN_PRISM_FISHEYE": [FX, FY, CX, CY, 0.04, -0.01, 0.002, 0.0, 0.0, 0.0, 0.001, -0.001,
                                   0.001, 0.0, -0.001, 0.0],
    "SIMPLE_DIVISION": [FX, CX, CY, -0.12],
    "DIVISION": [FX, FY, CX, CY, -0.12],
    "SIMPLE_FISHEYE": [FX, CX, CY],
    "FISHEYE": [FX, FY, CX, CY],
    "EUCM": [FX, FY, CX, CY, 0.55, 1.1],
}
#: models with an independent OpenCV implementation: name -> (fisheye, OpenCV distortion vector)
OPENCV_EQUIVALENT = {
    "SIMPLE_RADIAL": (False, lambda p: [p[3], 0, 0, 0]),
    "RADIAL": (False, lambda p: [p[3], p[4], 0, 0]),
    "OPENCV": (False, lambda p: p[4:8]),
    "FULL_OPENCV": (False, lambda p: p[4:12]),
    "OPENCV_FISHEYE": (True, lambda p: p[4:8]),
}


def _coordinate_image() -> np.ndarray:
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    return np.stack([u, v], -1).astype(np.float32)


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear sample of [H,W,C] at pixel coordinates uv [P,2] (pixel centres at +0.5)."""
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    a, b = img[y0, x0], img[y0, x0 + 1]
    c, d = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _points_in_view(K: np.ndarray, n: int = 300, margin: float = 6.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """3D points [n,3] in the camera frame whose pinhole projections [n,2] lie inside the image."""
    rng = np.random.default_rng(seed)
    q = np.stack([rng.uniform(margin, W - margin, n), rng.uniform(margin, H - margin, n)], -1)
    z = rng.uniform(0.5, 4.0, n)[:, None]
    X = np.concatenate([(q - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones((n, 1))], 1) * z
    return X, q


def _check_maps(maps, X, q, expected, tol=0.02):
    """The undistorted coordinate image at q must hold the distorted projection."""
    und = remap(_coordinate_image(), maps)
    got = _sample(und, q)
    ok = (got > 0).all(-1)  # samples inside the source image
    assert ok.mean() > 0.5
    err = np.linalg.norm(got[ok] - expected[ok], axis=-1)
    assert err.max() < tol, (err.max(), np.median(err))


@pytest.mark.parametrize("model", sorted(MODELS))
def test_colmap_maps_every_model(model: str) -> None:
    cam = colmap_camera(model, W, H, MODELS[model])
    maps = colmap_maps(cam, "test")
    np.testing.assert_allclose(maps.K, cam.calibration_matrix())
    X, q = _points_in_view(maps.K)
    distorted = np.asarray(cam.img_from_cam(X))
    moved = np.linalg.norm(distorted - q, axis=-1).max()
    if model.endswith("PINHOLE"):
        assert maps.identity and moved < 1e-9
    else:  # the lens really distorts, so an identity table would fail below
        assert not maps.identity and moved > 1.0, moved
    _check_maps(maps, X, q, distorted)


@pytest.mark.parametrize("model", sorted(OPENCV_EQUIVALENT))
def test_colmap_maps_agree_with_opencv_projection(model: str) -> None:
    import cv2

    params = MODELS[model]
    cam = colmap_camera(model, W, H, params)
    fisheye, to_cv = OPENCV_EQUIVALENT[model]
    D = np.asarray(to_cv(params), dtype=np.float64)
    K = np.asarray(cam.calibration_matrix())
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5  # OpenCV pixel centres at integers
    X, q = _points_in_view(K, seed=1)
    if fisheye:
        uv, _ = cv2.fisheye.projectPoints(X[:, None], np.zeros(3), np.zeros(3), K_cv, D.reshape(4, 1))
    else:
        uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K_cv, D)
    expected = uv.reshape(-1, 2) + 0.5
    _check_maps(colmap_maps(cam, "test"), X, q, expected)
    # nerfstudio's path (OpenCV tables) is the same undistortion
    _check_maps(opencv_maps(K, D, W, H, fisheye=fisheye), X, q, expected)


def test_spherical_and_malformed_models_are_refused() -> None:
    with pytest.raises(DataError, match="EQUIRECTANGULAR.*no pinhole view"):
        colmap_maps(colmap_camera("EQUIRECTANGULAR", W, H, [W, H]), "pano")
    with pytest.raises(DataError, match="unknown camera model 'KANNALA'"):
        colmap_camera("KANNALA", W, H, [FX])
    with pytest.raises(DataError, match=r"OPENCV needs parameters \(fx, fy, cx, cy, k1, k2, p1, p2\)"):
        colmap_camera("OPENCV", W, H, [FX, FY])
    with pytest.raises(DataError, match="do not describe this lens"):
        colmap_maps(colmap_camera("SIMPLE_RADIAL", W, H, [FX, CX, CY, 40.0]), "wild")


# --------------------------------------------------------------------------- a COLMAP scene per model
def write_colmap_scene(root: Path, model: str, params: list, n_views: int = 8) -> tuple[Path, list[np.ndarray]]:
    """``root/images`` (pattern images seen through the lens) + ``root/sparse/0`` (pycolmap-written)."""
    import pycolmap

    cam = colmap_camera(model, W, H, params)
    cam.camera_id = 1
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    pts = np.random.default_rng(0).uniform(-0.9, 0.9, (60, 3))
    (root / "images").mkdir(parents=True)
    img = pattern_seen_by(cam, W, H)
    c2ws = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        c2w = look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.4]))
        c2ws.append(c2w)
        w2c = np.linalg.inv(c2w)
        uv = cam.img_from_cam(pts @ w2c[:3, :3].T + w2c[:3, 3])
        name = f"{i:03d}.png"
        Image.fromarray(img).save(root / "images" / name)  # the pattern is fixed to the camera frame
        im = pycolmap.Image(name=name, keypoints=uv, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
    for j, p in enumerate(pts):
        track = pycolmap.Track()
        for i in range(n_views):
            track.add_element(i + 1, j)
        pid = rec.add_point3D(p, track)
        for i in range(n_views):
            rec.image(i + 1).points2D[j].point3D_id = pid
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(str(root / "sparse" / "0"))
    return root, c2ws


@pytest.mark.parametrize("model", ["OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE",
                                   "SIMPLE_DIVISION", "EUCM"])
def test_colmap_scene_of_any_model_loads_undistorted(tmp_path: Path, model: str) -> None:
    root, _ = write_colmap_scene(tmp_path / model, model, MODELS[model])
    m = read_colmap_model(root / "sparse" / "0")
    assert m.camera_models == [model] * 8 and np.allclose(m.params[0], MODELS[model])
    # observations were made through the lens: reprojection through the model is exact, pinhole is not
    assert np.median(reprojection_errors(m)) < 1e-6
    xy, idx = m.observations[0]
    assert np.linalg.norm(project(m.points[idx], m.K[0], m.c2w[0]) - xy, axis=-1).max() > 1.0
    s = load_scene("selfie", root, resolution=None, use_masks=False)
    assert s.images.shape == (8, H, W, 3) and any(f"removed {model} lens distortion" in n for n in s.notes)
    K = s.K[0].double().numpy()
    np.testing.assert_allclose(K, m.K[0], rtol=1e-6)
    expected = pinhole_pattern(K, W, H)
    img = s.images[3].numpy()
    err, inside = interior_error(img, expected)
    assert inside.mean() > 0.5
    raw = np.asarray(Image.open(root / "images" / "003.png"), dtype=np.float64) / 255
    assert err < 0.01, err
    assert np.abs(raw - expected)[inside].mean() > 3 * err  # the loader's output is not the raw image


def test_colmap_scene_with_spherical_camera_is_refused(tmp_path: Path) -> None:
    root, _ = write_colmap_scene(tmp_path / "pano", "SIMPLE_RADIAL", MODELS["SIMPLE_RADIAL"])
    import pycolmap

    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    rec.cameras[1].model = pycolmap.CameraModelId.EQUIRECTANGULAR
    rec.cameras[1].params = [W, H]
    rec.write(str(root / "sparse" / "0"))
    with pytest.raises(DataError, match="EQUIRECTANGULAR"):
        load_scene("selfie", root, use_masks=False)


def test_sfm_camera_model_is_checked_before_any_work(tmp_path: Path) -> None:
    from nerfart_plugin.errors import ConfigError

    (tmp_path / "frames").mkdir()
    with pytest.raises(ConfigError, match="data.camera_model='EQUIRECTANGULAR'.*OPENCV_FISHEYE"):
        load_scene("selfie", tmp_path / "frames", camera_model="EQUIRECTANGULAR")
    assert not any((tmp_path / "frames").iterdir())
