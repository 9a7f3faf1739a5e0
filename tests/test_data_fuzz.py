"""Fuzz: malformed cameras.npz, poses_bounds.npy, COLMAP model folders and transforms.json give
project errors (DataError, ConfigError) only."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from nerfart_plugin.data.colmap import read_colmap_model
from nerfart_plugin.data.h3ds import read_cameras_npz
from nerfart_plugin.data.llff import read_poses_bounds
from nerfart_plugin.errors import DataError

SETTINGS = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
floats = st.floats(allow_nan=True, allow_infinity=True, width=32)
shapes = st.sampled_from([(4, 4), (3, 4), (4, 4), (3, 3), (4,), (0, 4), (4, 4, 1), ()])


def _npz_entries():
    key = st.sampled_from(["world_mat_0", "world_mat_1", "world_mat_3", "scale_mat_0", "scale_mat_1", "camera_mat_0", "x"])
    arr = shapes.flatmap(lambda s: arrays(np.float64, s, elements=floats))
    return st.dictionaries(key, arr, max_size=5)


@pytest.mark.slow
@SETTINGS
@given(entries=_npz_entries(), garbage=st.binary(max_size=64), mode=st.sampled_from(["npz", "bytes", "truncated"]))
def test_fuzz_cameras_npz(entries, garbage, mode):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "cameras.npz"
        if mode == "bytes":
            p.write_bytes(garbage)
        else:
            np.savez(p, **entries)
            if mode == "truncated":
                p.write_bytes(p.read_bytes()[: max(1, len(p.read_bytes()) // 2)])
        try:
            K, c2w, S = read_cameras_npz(p)
        except DataError:
            return
        assert np.isfinite(K).all() and np.isfinite(c2w).all() and len(K) == len(c2w) >= 1


@pytest.mark.slow
@SETTINGS
@given(
    arr=st.one_of(
        arrays(np.float64, st.sampled_from([(1, 17), (3, 17), (5, 17), (3, 15), (17,), (2, 3, 17)]), elements=floats),
        arrays(np.int64, st.sampled_from([(3, 17)]), elements=st.integers(-5, 5)),
        arrays(np.bool_, (2, 17)),
    ),
    garbage=st.binary(max_size=64),
    mode=st.sampled_from(["npy", "bytes", "truncated"]),
)
def test_fuzz_poses_bounds(arr, garbage, mode):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "poses_bounds.npy"
        if mode == "bytes":
            p.write_bytes(garbage)
        else:
            np.save(p, arr)
            if mode == "truncated":
                p.write_bytes(p.read_bytes()[: max(1, len(p.read_bytes()) - 7)])
        try:
            pb = read_poses_bounds(p)
        except DataError:
            return
        assert np.isfinite(pb.c2w).all() and (pb.bounds[:, 1] > pb.bounds[:, 0]).all()


@pytest.mark.slow
@SETTINGS
@given(
    files=st.dictionaries(
        st.sampled_from(["cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt"]),
        st.binary(max_size=200),
        max_size=6,
    )
)
def test_fuzz_colmap_model(files):
    with tempfile.TemporaryDirectory() as d:
        for name, data in files.items():
            (Path(d) / name).write_bytes(data)
        try:
            read_colmap_model(d)
        except DataError:
            return


# --------------------------------------------------------------------------- transforms.json
_json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-(10**400), 10**400), st.text(max_size=4),
                          st.floats(allow_nan=True, allow_infinity=True))
_json_any = st.recursive(_json_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=4), c,
                                                                                           max_size=3), max_leaves=8)
_num = st.one_of(st.sampled_from([0, 1, 6, 8, 300.0, 0.7, 3.2, 1e308, -1.0, 1e-300]), _json_scalars)
_R = np.array([[1.0, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, 3.0], [0, 0, 0, 1]])
_valid = st.sampled_from([_R.tolist(), _R[:3].tolist(), (_R @ np.diag([1, -1, -1, 1])).tolist(), np.eye(4).tolist()])
_matrix = st.one_of(  # valid matrices weighted up so that some files load
    _valid, _valid, _valid,
    arrays(np.float64, st.sampled_from([(4, 4), (3, 4), (4, 3), (4,)]), elements=floats).map(lambda a: a.tolist()),
    _json_any,
)
_cam_keys = {k: _num for k in ("fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                                "k1", "k2", "k3", "k4", "p1", "p2")}
_model = st.sampled_from(["OPENCV", "OPENCV_FISHEYE", "PINHOLE", "EQUIRECTANGULAR", "x", 5, None])
_frame = st.fixed_dictionaries(
    {"file_path": st.sampled_from(["a.png", "a", "rgba", "./rgba.png", "a.png", "rgba", "b.png", "missing.png", "",
                                   3, None]),
     "transform_matrix": _matrix},
    optional={"mask_path": st.sampled_from(["m.png", "m", "a.png", "nope.png", 1]), "camera_model": _model,
              **{k: _num for k in ("fl_x", "w", "h", "cx", "k1")}},
)
_names = st.lists(st.sampled_from(["a.png", "rgba.png", "b.png", "zz.png", 4]), max_size=3)
_transforms = st.fixed_dictionaries(
    {"frames": st.one_of(st.lists(_frame, min_size=1, max_size=4), st.lists(_frame, min_size=1, max_size=4), _json_any),
     "fl_x": st.one_of(st.just(300.0), st.just(7.5), _num)},
    optional={**_cam_keys, "camera_model": _model, "aabb": st.one_of(st.just([[-1, -1, -1], [1, 1, 1]]), _json_any),
              "aabb_scale": _num, "scale": _num, "offset": _json_any, "train_filenames": _names,
              "val_filenames": st.one_of(_names, _json_any)},
)


def _tiny_images(d: Path) -> None:
    from PIL import Image

    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)).save(d / "a.png")
    Image.fromarray(rng.integers(0, 255, (6, 8, 4), dtype=np.uint8)).save(d / "rgba.png")
    Image.fromarray(rng.integers(0, 255, (6, 6, 3), dtype=np.uint8)).save(d / "b.png")
    Image.fromarray(rng.integers(0, 255, (6, 8), dtype=np.uint8)).save(d / "m.png")


@pytest.mark.slow
@SETTINGS
@given(meta=_transforms, garbage=st.binary(max_size=64), mode=st.sampled_from(["json", "json", "bytes", "truncated"]))
def test_fuzz_transforms_json(meta, garbage, mode):
    from nerfart_plugin.data import load_scene
    from nerfart_plugin.errors import ConfigError

    with tempfile.TemporaryDirectory() as d:
        _tiny_images(Path(d))
        p = Path(d) / "transforms.json"
        if mode == "bytes":
            p.write_bytes(garbage)
        else:
            text = json.dumps(meta)
            p.write_text(text if mode == "json" else text[: max(1, len(text) // 2)])
        try:
            s = load_scene("nerfstudio", d, resolution=None)
        except (DataError, ConfigError):
            return
        # every frame of one size (a scene of the 6x6 b.png alone is fine; mixed sizes are refused)
        assert s.num_images >= 1 and s.images.shape[1:] in ((6, 8, 3), (6, 6, 3))
        for t in (s.images, s.c2w, s.K, s.near, s.far, s.normalization):
            assert torch.isfinite(t).all()
