"""Fuzz: malformed cameras.npz, poses_bounds.npy and COLMAP model folders give DataError only."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
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
