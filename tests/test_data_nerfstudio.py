"""data=nerfstudio: transforms.json (nerfstudio / instant-ngp / Blender) against data=h3ds on the shipped head.

The head's cameras are written as a transforms.json in their original (un-normalized)
world frame with OpenGL axes; both loaders must then give the same images, masks and
rays from the same pixels (compared in that world frame: each loader normalizes on its own).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from camera_helpers import interior_error, look_at, pattern_seen_by, pinhole_pattern
from PIL import Image

from nerfart_plugin.data import load_scene
from nerfart_plugin.data.datamodule import default_scene_path
from nerfart_plugin.data.h3ds import read_cameras_npz
from nerfart_plugin.data.loader import LoaderContext
from nerfart_plugin.data.rays import pixel_rays, rays_for_views
from nerfart_plugin.errors import DataError

GL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV <-> OpenGL camera axes (its own inverse)


@pytest.fixture(scope="module")
def head():
    """(h3ds scene, K [N,3,3], OpenCV c2w [N,4,4] in the original world frame, scale_mat [4,4])."""
    root = default_scene_path()
    K, c2w_norm, S = read_cameras_npz(root / "cameras.npz")
    c2w = S[0] @ c2w_norm
    c2w[:, :3, :3] /= np.cbrt(np.linalg.det(S[0][:3, :3]))
    return load_scene("h3ds", root), K, c2w, S[0]


def _frames(K, c2w, image, mask=None, per_frame=False):
    frames = []
    for i in range(len(c2w)):
        f = {"file_path": image(i), "transform_matrix": (c2w[i] @ GL).tolist()}
        if mask is not None:
            f["mask_path"] = mask(i)
        if per_frame:
            f.update(fl_x=K[i, 0, 0], fl_y=K[i, 1, 1], cx=K[i, 0, 2], cy=K[i, 1, 2])
        frames.append(f)
    return frames


def write_head_transforms(dst: Path, K, c2w, S, per_frame: bool = False) -> Path:
    """transforms.json for the head: images/ and matte/ linked in, file_path without extension, aabb from scale_mat."""
    dst.mkdir(parents=True, exist_ok=True)
    for sub in ("images", "matte"):
        (dst / sub).symlink_to(default_scene_path() / sub)
    c, s = S[:3, 3], S[0, 0]
    meta = {"w": 256, "h": 256, "aabb": [(c - s).tolist(), (c + s).tolist()],
            "frames": _frames(K, c2w, lambda i: f"images/{i:04d}", lambda i: f"matte/{i:04d}.png", per_frame)}
    if not per_frame:
        meta.update(fl_x=K[0, 0, 0], fl_y=K[0, 1, 1], cx=K[0, 0, 2], cy=K[0, 1, 2])
    else:
        meta["camera_angle_x"] = 1.0  # a default every frame overrides
    (dst / "transforms.json").write_text(json.dumps(meta))
    return dst


def _world_rays(scene, i):
    """Rays of view i mapped back to the capture's world frame with the scene's normalization."""
    o, d = pixel_rays(scene.K[i].double(), scene.c2w[i].double(), scene.height, scene.width)
    Tinv = torch.linalg.inv(scene.normalization.double())
    R = Tinv[:3, :3] / torch.linalg.det(Tinv[:3, :3]).pow(1 / 3)
    return o @ Tinv[:3, :3].T + Tinv[:3, 3], d @ R.T


def _assert_same_rays(a, b, views, atol=1e-4):
    for i in views:
        (oa, da), (ob, db) = _world_rays(a, i), _world_rays(b, i)
        torch.testing.assert_close(oa, ob, atol=atol, rtol=0)
        torch.testing.assert_close(da, db, atol=atol, rtol=0)


def test_head_as_transforms_json_agrees_with_h3ds(tmp_path, head):
    ref, K, c2w, S = head
    s = load_scene("nerfstudio", write_head_transforms(tmp_path / "ns", K, c2w, S))
    assert s.capture == ref.capture == "object" and s.images.shape == ref.images.shape == (31, 256, 256, 3)
    assert torch.equal(s.images, ref.images) and torch.equal(s.masks, ref.masks)
    assert s.image_names[:2] == ["images/0000.jpg", "images/0001.jpg"]
    assert s.train_ids == ref.train_ids and s.val_ids == ref.val_ids
    _assert_same_rays(s, ref, [0, 7, 19, 30])
    # the aabb (scale_mat's cube) -> its circumscribed sphere: same centre, radius sqrt(3) x scale_mat's
    Tn, Th = torch.linalg.inv(s.normalization.double()), torch.linalg.inv(ref.normalization.double())
    torch.testing.assert_close(Tn[:3, 3], Th[:3, 3], atol=1e-4, rtol=0)
    torch.testing.assert_close(Tn[:3, :3], Th[:3, :3] * math.sqrt(3), atol=1e-4, rtol=0)
    assert (s.c2w[:, :, 3].norm(dim=-1) > 1.0).all() and any("aabb" in n for n in s.notes)


def test_per_frame_intrinsics(tmp_path, head):
    ref, K, c2w, S = head
    root = write_head_transforms(tmp_path / "pf", K, c2w, S, per_frame=True)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][5].update(w=512, h=512, fl_x=2 * K[5, 0, 0], fl_y=2 * K[5, 1, 1], cx=2 * K[5, 0, 2],
                             cy=2 * K[5, 1, 2])  # intrinsics of a 2x larger original: scaled to the image
    meta["frames"][9]["fl_x"] = 1.1 * K[9, 0, 0]
    (root / "transforms.json").write_text(json.dumps(meta))
    s = load_scene("nerfstudio", root)
    keep = [i for i in range(31) if i != 9]
    torch.testing.assert_close(s.K[keep], ref.K[keep], atol=1e-4, rtol=0)
    assert float(s.K[9, 0, 0]) == pytest.approx(1.1 * K[9, 0, 0], rel=1e-6)
    _assert_same_rays(s, ref, [0, 5, 30])
    (_, da), (_, db) = _world_rays(s, 9), _world_rays(ref, 9)
    assert (da - db).abs().max() > 1e-2  # the changed focal changes that view's rays
    # mixed native sizes are refused, naming the files
    big = root / "big.png"
    Image.open(default_scene_path() / "images" / "0003.jpg").resize((300, 300)).save(big)
    meta["frames"][3]["file_path"] = "big.png"
    meta["frames"][3].update(w=300, h=300)
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"Mixed image sizes: .*0000.jpg is 256x256 but .*big.png is 300x300"):
        load_scene("nerfstudio", root)


def _blender_scene(dst: Path, K, c2w, splits=(("train", range(0, 24)), ("val", range(24, 28)),
                                                ("test", range(28, 31)))) -> Path:
    """Blender layout: transforms_{split}.json, RGBA PNGs (alpha = the head's matte), camera_angle_x only."""
    head = default_scene_path()
    for split, ids in splits:
        (dst / split).mkdir(parents=True)
        for j, i in enumerate(ids):
            rgb = np.asarray(Image.open(head / "images" / f"{i:04d}.jpg").convert("RGB"))
            a = np.asarray(Image.open(head / "matte" / f"{i:04d}.png").convert("L"))
            Image.fromarray(np.dstack([rgb, a])).save(dst / split / f"r_{j}.png")
        frames = _frames(K[list(ids)], c2w[list(ids)], lambda j, s=split: f"./{s}/r_{j}")
        meta = {"camera_angle_x": 2 * math.atan(128 / K[0, 0, 0]), "frames": frames}
        (dst / f"transforms_{split}.json").write_text(json.dumps(meta))
    return dst


@pytest.mark.slow
def test_blender_rgba_scene(tmp_path, head):
    ref, K, c2w, S = head
    root = _blender_scene(tmp_path / "lego_like", K, c2w)
    s = load_scene("nerfstudio", root)
    assert s.num_images == 28 and s.train_ids == list(range(24)) and s.val_ids == [24, 25, 26, 27]
    assert s.image_names[0] == "train/r_0.png" and s.image_names[24] == "val/r_0.png"
    assert s.capture == "object" and any("alpha is the mask" in n for n in s.notes)
    torch.testing.assert_close(s.masks, ref.masks[:28], atol=1e-6, rtol=0)
    f = 128 / math.tan(math.atan(128 / K[0, 0, 0]))
    torch.testing.assert_close(s.K[0].double(), torch.tensor([[f, 0, 128], [0, f, 128], [0, 0, 1.0]],
                                                             dtype=torch.float64), atol=1e-3, rtol=0)
    # OpenGL -> OpenCV: every camera looks at the object in the unit sphere
    c = s.c2w[:, :, 3]
    cos = (-c / c.norm(dim=-1, keepdim=True) * s.c2w[:, :, 2]).sum(-1)
    assert (cos > math.cos(math.radians(10))).all()
    # training targets: straight RGBA colours composited once = h3ds's photo composited with its matte
    for bg in ([1.0, 1.0, 1.0], [0.0, 0.0, 0.0]):
        for i in (0, 25):
            a = rays_for_views(s, [i], background=bg)["rgb"]
            b = rays_for_views(ref, [i], background=bg)["rgb"]
            assert (a - b).abs().max() < 1.5 / 255
    assert (s.images[0][s.masks[0] == 0] == 1.0).all()  # fully transparent pixels show the background
    every = load_scene("nerfstudio", root, splits=["train", "val", "test"])
    assert every.num_images == 31 and every.val_ids == list(range(24, 31))
    flat = load_scene("nerfstudio", root, context=LoaderContext(background=(0.0, 0.0, 0.0)), use_masks=False)
    assert flat.masks is None
    torch.testing.assert_close(flat.images[3], rays_for_views(ref, [3], background=[0, 0, 0])["rgb"].reshape(
        256, 256, 3), atol=1.5 / 255, rtol=0)
    small = load_scene("nerfstudio", root, resolution=64)
    ref64 = load_scene("h3ds", default_scene_path(), resolution=64)
    assert small.images.shape[1:3] == (64, 64) and (small.masks - ref64.masks[:28]).abs().mean() < 0.01


def test_background_colour_comes_from_the_config(tmp_path, head):
    from pipeline_helpers import tiny_cfg

    from nerfart_plugin.run.pipeline import Pipeline

    _, K, c2w, _ = head
    root = _blender_scene(tmp_path / "b", K, c2w, splits=(("train", range(0, 8)),))
    pipe = Pipeline(tiny_cfg(tmp_path / "out", root, "data=nerfstudio", "render.background_color=[0,0,0]",
                             "stage=reconstruct"))
    pipe.load_data()
    s = pipe.scene
    assert s.images.shape == (8, 24, 24, 3) and s.masks is not None
    assert (s.images[s.masks == 0] == 0.0).all()


@pytest.mark.parametrize("model,params", [
    ("OPENCV", {"k1": -0.16, "k2": 0.05, "p1": 0.004, "p2": -0.003}),
    ("OPENCV", {"k1": -0.2, "k2": 0.06, "k3": 0.01, "p1": 0.003, "p2": -0.002}),
    ("OPENCV_FISHEYE", {"k1": 0.06, "k2": -0.02, "k3": 0.004, "k4": -0.001}),
])
def test_distorted_cameras_are_undistorted(tmp_path, model, params):
    """Images made through the lens (pycolmap's model of it) load as the pinhole view of the same rays."""
    from nerfart_plugin.data.undistort import colmap_camera

    W, H, fx, fy, cx, cy = 160, 120, 110.0, 112.0, 81.3, 58.6
    k = params.get
    colmap_params = ([fx, fy, cx, cy, k("k1", 0), k("k2", 0), k("k3", 0), k("k4", 0)] if model == "OPENCV_FISHEYE"
                     else [fx, fy, cx, cy, k("k1", 0), k("k2", 0), k("p1", 0), k("p2", 0), k("k3", 0), 0, 0, 0])
    cam = colmap_camera("OPENCV_FISHEYE" if model == "OPENCV_FISHEYE" else "FULL_OPENCV", W, H, colmap_params)
    img = pattern_seen_by(cam, W, H)
    frames = []
    for i in range(6):
        a = 2 * np.pi * i / 6
        Image.fromarray(img).save(tmp_path / f"{i}.png")
        frames.append({"file_path": f"{i}.png",
                       "transform_matrix": (look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.5])) @ GL).tolist()})
    meta = {"camera_model": model, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": W, "h": H, **params,
            "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    s = load_scene("nerfstudio", tmp_path, resolution=None)
    assert s.images.shape == (6, H, W, 3) and any(f"removed {model} lens distortion" in n for n in s.notes)
    K = s.K[0].double().numpy()
    np.testing.assert_allclose(K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rtol=1e-6)
    expected = pinhole_pattern(K, W, H)
    err, inside = interior_error(s.images[2].numpy(), expected)
    raw_err = np.abs(img / 255.0 - expected)[inside].mean()
    assert inside.mean() > 0.6 and err < 0.01 and raw_err > 3 * err, (err, raw_err)
    assert s.capture == "unbounded"  # no masks, cameras all around


# --------------------------------------------------------------------------- malformed files
@pytest.fixture()
def tiny(tmp_path, head):
    """A valid 4-frame transforms.json in tmp_path and a function to rewrite it."""
    _, K, c2w, _ = head
    for i in range(4):
        shutil.copy(default_scene_path() / "images" / f"{i:04d}.jpg", tmp_path / f"{i}.jpg")
    meta = {"fl_x": 300.0, "frames": _frames(K[:4], c2w[:4], lambda i: f"{i}.jpg")}

    def write(m=None, text=None):
        (tmp_path / "transforms.json").write_text(text if text is not None else json.dumps(m))
        return tmp_path

    write(meta)
    return meta, write


def test_valid_tiny_file_loads(tiny):
    meta, write = tiny
    s = load_scene("nerfstudio", write(meta), resolution=32)
    assert s.num_images == 4 and s.masks is None
    # forward-facing cameras without a scene box cannot be bounded for NDC: unbounded, with a note
    assert s.capture == "unbounded" and any("add \"aabb\"" in n for n in s.notes)


@pytest.mark.parametrize("edit,message", [
    (lambda m: m.pop("frames"), r"transforms.json has no 'frames' list"),
    (lambda m: m["frames"][1].pop("file_path"), r"transforms.json frames\[1\]: file_path is missing"),
    (lambda m: m["frames"][2].update(file_path="nope/7"), r"frames\[2\]: file_path 'nope/7' not found \(looked for"),
    (lambda m: m.pop("fl_x"), r"frames\[0\]: no valid focal length: give fl_x \(pixels\) or camera_angle_x"),
    (lambda m: m["frames"][3].update(transform_matrix=[[1, 0], [0, 1]]), r"frames\[3\]: transform_matrix must be a 4x4"),
    (lambda m: m["frames"][0].update(transform_matrix=(2 * np.eye(4)).tolist()), r"not orthonormal"),
    (lambda m: m.update(fl_x="300"), r"fl_x=300 is not a finite number"),
    (lambda m: m.update(w=512, h=256), r"intrinsics are for 512x256 images but .*0.jpg is 256x256"),
    (lambda m: m.update(camera_model="EQUIRECTANGULAR"), r"camera_model 'EQUIRECTANGULAR' is not supported"),
    (lambda m: m["frames"][0].update(mask_path="0.jpg"), r"frames \[1, 2, 3\] have no mask_path but others have one"),
    (lambda m: m.update(aabb=[[0, 0, 0], [1, 1]]), r"aabb must be \[\[xmin, ymin, zmin\], \[xmax, ymax, zmax\]\]"),
    (lambda m: m.update(aabb_scale=-4), r"aabb_scale=-4 must be positive"),
    (lambda m: m.update(train_filenames=["0.jpg", "9.jpg"]), r"train_filenames names \['9.jpg'\]"),
    (lambda m: m["frames"][2].update(file_path="../../../../etc/passwd"),
     r"frames\[2\]: file_path '../../../../etc/passwd' leads outside the capture's folder"),
])
def test_malformed_files_name_the_file_and_the_fix(tiny, edit, message):
    meta, write = tiny
    m = json.loads(json.dumps(meta))
    edit(m)
    with pytest.raises(DataError, match=message):
        load_scene("nerfstudio", write(m))


def test_invalid_json_names_line_and_column(tiny):
    _, write = tiny
    with pytest.raises(DataError, match=r"transforms.json is not valid JSON \(line 1, column 13"):
        load_scene("nerfstudio", write(text='{"frames": ['))


def test_missing_transforms_and_splits(tmp_path):
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(DataError, match=r"No transforms.json \(nerfstudio / instant-ngp\) or transforms_train.json"):
        load_scene("nerfstudio", tmp_path)
    with pytest.raises(DataError, match="data.splits has"):
        load_scene("nerfstudio", tmp_path, splits=["training"])


def test_nerfstudio_split_lists_and_ngp_box(tiny):
    meta, write = tiny
    m = dict(meta, train_filenames=["0.jpg", "./2.jpg", "3.jpg"], val_filenames=["1.jpg"], aabb_scale=16)
    ff = load_scene("nerfstudio", write(m), resolution=32)
    assert ff.train_ids == [0, 2, 3] and ff.val_ids == [1]
    # 4 neighbouring views without masks are forward-facing: LLFF normalization, depths from the box
    assert ff.capture == "forward_facing" and any("depth bounds from the scene box" in n for n in ff.notes)
    assert float(ff.near.min()) == pytest.approx(1 / 0.75, rel=1e-4)
    s = load_scene("nerfstudio", write(m), resolution=32, capture="unbounded")
    # instant-ngp: unit cube of p * 0.33 + 0.5 -> file-frame box [-1.52, 1.52]^3, its circumscribed sphere
    T = s.normalization.double()
    assert float(torch.linalg.det(T[:3, :3]).pow(1 / 3)) == pytest.approx(0.33 / (math.sqrt(3) / 2), rel=1e-5)
    torch.testing.assert_close(T[:3, 3], torch.zeros(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert any("aabb_scale=16: the content out to that box is background" in n for n in s.notes)


def test_rgba_frames_whose_alpha_is_zero_everywhere_are_refused(tiny):
    """Alpha is the mask; an alpha of 0 everywhere would train on empty masks."""
    meta, write = tiny
    folder = write(meta)
    for i in range(4):
        rgb = np.asarray(Image.open(folder / f"{i}.jpg").convert("RGB"))
        Image.fromarray(np.dstack([rgb, np.zeros(rgb.shape[:2], np.uint8)])).save(folder / f"{i}.png")
    m = json.loads(json.dumps(meta))
    for i, fr in enumerate(m["frames"]):
        fr["file_path"] = f"{i}.png"
    with pytest.raises(DataError, match="every mask is empty"):
        load_scene("nerfstudio", write(m), resolution=32)
