"""COLMAP model reading: reprojection check on girl/sparse/0."""

from __future__ import annotations

import numpy as np

from nerfart_plugin.data.colmap import project, read_colmap_model, reprojection_errors


def test_girl_colmap_reprojection(shared_data):
    m = read_colmap_model(shared_data / "girl" / "sparse" / "0")
    assert len(m.names) == 31 and m.c2w.shape == (31, 4, 4) and m.K.shape == (31, 3, 3)
    assert m.points.shape[1] == 3 and len(m.points) > 500
    R = m.c2w[:, :3, :3]
    np.testing.assert_allclose(np.transpose(R, (0, 2, 1)) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    err = reprojection_errors(m)
    assert len(err) > 1000
    assert np.median(err) < 2.0, np.median(err)
    # points lie in front of the cameras that observe them (OpenCV z forward)
    xy, idx = m.observations[0]
    w2c = np.linalg.inv(m.c2w[0])
    z = m.points[idx] @ w2c[2, :3] + w2c[2, 3]
    assert (z > 0).all()


def test_project_pinhole_identity():
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    uv = project(np.array([[0.0, 0.0, 2.0], [0.2, -0.4, 2.0]]), K, np.eye(4))
    np.testing.assert_allclose(uv, [[50, 40], [60, 20]])
