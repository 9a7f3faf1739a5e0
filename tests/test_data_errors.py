"""Clear DataErrors (naming the file and the fix) for broken inputs, raised before long work."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nerfart_plugin.data import load_scene
from nerfart_plugin.data.colmap import read_colmap_model
from nerfart_plugin.data.datamodule import default_scene_path
from nerfart_plugin.data.llff import read_poses_bounds
from nerfart_plugin.data.selfie import extract_frames
from nerfart_plugin.errors import ConfigError, DataError


@pytest.fixture()
def head_copy(tmp_path) -> Path:
    dst = tmp_path / "head"
    shutil.copytree(default_scene_path(), dst)
    return dst


def test_missing_and_empty_folder(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        load_scene("h3ds", tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="is empty"):
        load_scene("llff", tmp_path / "empty")
    with pytest.raises(ConfigError, match="Valid data names"):
        load_scene("nosuchkind", tmp_path)


def test_no_cameras_file(head_copy):
    (head_copy / "cameras.npz").unlink()
    with pytest.raises(DataError, match="No cameras.npz"):
        load_scene("h3ds", head_copy)


def test_count_mismatch_names_both(head_copy):
    (head_copy / "images" / "0005.jpg").unlink()
    with pytest.raises(DataError, match=r"31 cameras but .* 30 images"):
        load_scene("h3ds", head_copy)


def test_extra_mattes_matched_by_name(head_copy):
    shutil.copy(head_copy / "matte" / "0000.png", head_copy / "matte" / "0099.png")
    s = load_scene("h3ds", head_copy, resolution=32)
    assert s.masks.shape[0] == 31 and any("0099.png" in n for n in s.notes)
    (head_copy / "matte" / "0003.png").unlink()
    (head_copy / "matte" / "0099.png").rename(head_copy / "matte" / "x.png")
    (head_copy / "matte" / "y.png").write_bytes((head_copy / "matte" / "x.png").read_bytes())
    with pytest.raises(DataError, match="mattes cannot be matched"):
        load_scene("h3ds", head_copy)


def test_truncated_image_named(head_copy):
    p = head_copy / "images" / "0007.jpg"
    p.write_bytes(p.read_bytes()[:300])
    with pytest.raises(DataError, match="0007.jpg"):
        load_scene("h3ds", head_copy)


def test_zero_length_image_named(head_copy):
    (head_copy / "images" / "0002.jpg").write_bytes(b"")
    with pytest.raises(DataError, match="0002.jpg"):
        load_scene("h3ds", head_copy)


def test_mixed_sizes(head_copy):
    p = head_copy / "images" / "0004.jpg"
    Image.open(p).resize((200, 200)).save(p)
    with pytest.raises(DataError, match="Mixed image sizes.*0004.jpg"):
        load_scene("h3ds", head_copy)


def test_cameras_npz_nan_and_missing_key(head_copy):
    cams = dict(np.load(head_copy / "cameras.npz"))
    bad = dict(cams)
    bad["world_mat_3"] = bad["world_mat_3"].copy()
    bad["world_mat_3"][0, 0] = np.nan
    np.savez(head_copy / "cameras.npz", **bad)
    with pytest.raises(DataError, match="world_mat_3.*NaN"):
        load_scene("h3ds", head_copy)
    bad = {k: v for k, v in cams.items() if k != "world_mat_10"}
    np.savez(head_copy / "cameras.npz", **bad)
    with pytest.raises(DataError, match="missing \\[10\\]"):
        load_scene("h3ds", head_copy)


def test_poses_bounds_errors(tmp_path):
    p = tmp_path / "poses_bounds.npy"
    np.save(p, np.zeros((4, 15)))
    with pytest.raises(DataError, match=r"shape \(4, 15\)"):
        read_poses_bounds(p)
    with pytest.raises(DataError, match="not found"):
        read_poses_bounds(tmp_path / "missing.npy")


def test_llff_count_mismatch(tmp_path, shared_data):
    root = tmp_path / "fern"
    shutil.copytree(shared_data / "llff_fern", root)
    (root / "images_8" / "image003.png").unlink()
    with pytest.raises(DataError, match="20 poses but .* 19 images"):
        load_scene("llff", root)
    with pytest.raises(DataError, match="images_4"):
        load_scene("llff", root, factor=4)


def test_bad_videos(tmp_path):
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(DataError, match="empty"):
        load_scene("selfie", empty, cache_dir=tmp_path / "c")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 100)
    with pytest.raises(DataError, match="junk.mp4"):
        extract_frames(junk, tmp_path / "frames")
    with pytest.raises(DataError, match="not a video"):
        txt = tmp_path / "notes.txt"
        txt.write_text("x")
        load_scene("selfie", txt)


def test_colmap_model_errors(tmp_path, shared_data):
    with pytest.raises(DataError, match="not a COLMAP sparse model"):
        read_colmap_model(tmp_path)
    m = tmp_path / "m"
    shutil.copytree(shared_data / "girl" / "sparse" / "0", m)
    (m / "images.bin").write_bytes((m / "images.bin").read_bytes()[:100])
    with pytest.raises(DataError, match="Cannot read COLMAP model"):
        read_colmap_model(m)


def test_selfie_model_not_matching_images(shared_data):
    # girl/sparse/0 names views (img_0059...) absent from girl/images: refuse, do not guess
    with pytest.raises(DataError, match="missing from"):
        load_scene("selfie", shared_data / "girl")


def test_colmap_lists_longer_than_their_files_are_refused_before_pycolmap_reads_them(tmp_path):
    """A corrupt list length made pycolmap read past the end for 2^31 entries (a hang found by the fuzzer):
    the model's binary files are walked first, and such a file is a DataError naming it."""
    import struct

    point = struct.pack("<Q3d3Bd", 1, 0.0, 0.0, 0.0, 0, 0, 0, 0.0)
    image = struct.pack("<I4d3dI", 1, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1) + b"a.png\0"
    cases = {"points3D.bin": (struct.pack("<Q", 0), struct.pack("<QQ", 1, 1) + point[8:] + struct.pack("<Q", 2**31)),
             "images.bin": (struct.pack("<Q", 1) + image + struct.pack("<Q", 2**40), struct.pack("<Q", 0))}
    for bad, (images, points) in cases.items():
        folder = tmp_path / bad
        folder.mkdir()
        (folder / "cameras.bin").write_bytes(struct.pack("<Q", 0))
        (folder / "images.bin").write_bytes(images)
        (folder / "points3D.bin").write_bytes(points)
        with pytest.raises(DataError, match=rf"{bad}: record 0 declares \d+ entries, more than the file holds"):
            read_colmap_model(folder)
    (tmp_path / "short").mkdir()
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (tmp_path / "short" / name).write_bytes(struct.pack("<Q", 5))
    with pytest.raises(DataError, match="declares 5 records but ends inside record 0"):
        read_colmap_model(tmp_path / "short")


def test_the_scene_contract_refuses_captures_that_cannot_be_reconstructed():
    """The family of degenerate captures, checked in one place (Scene.validate, every loader): tiny images, one
    view, empty masks, no baseline, cameras looking away; each named with its fix."""
    import dataclasses

    import torch

    from nerfart_plugin.data.scene import MIN_IMAGE_SIDE, RECONSTRUCTABLE

    s = load_scene("h3ds", default_scene_path(), resolution=32)
    assert s.validate() is s and len(RECONSTRUCTABLE) >= 5
    n = s.num_images
    small = dataclasses.replace(s, images=s.images[:, :8, :8], masks=s.masks[:, :8, :8])
    cases = {
        f"at least {MIN_IMAGE_SIDE} px a side": small,
        "at least 2 views": dataclasses.replace(s, train_ids=[]),
        "every mask is empty": dataclasses.replace(s, masks=torch.zeros_like(s.masks)),
        "every camera sits at the same place": dataclasses.replace(
            s, c2w=torch.cat([s.c2w[:, :, :3], s.c2w[:1, :, 3:].expand(n, 3, 1)], -1)),
        "face the scene's centre": dataclasses.replace(
            s, c2w=torch.cat([s.c2w[:, :, :1], -s.c2w[:, :, 1:3], s.c2w[:, :, 3:]], -1)),
    }
    for message, scene in cases.items():
        with pytest.raises(DataError, match=f"Invalid scene from .*{message}"):
            scene.validate()
