"""Meshes in the capture's world frame by default, with the frame written into the file."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from nerfart_plugin.data.rays import ndc_rays
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.export.mesh import export_mesh
from nerfart_plugin.export.world_frame import frame_metadata, to_frame
from nerfart_plugin.cameras.capture import ndc_to_normalized


def similarity(scale: float, angle: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = scale * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    T[:3, 3] = t
    return T


def test_world_frame_undoes_the_normalization() -> None:
    T = similarity(0.25, 0.3, (0.1, -0.2, 0.3))  # x_norm = T x_world
    world_pts = np.random.default_rng(0).normal(size=(50, 3)) * 2
    norm_pts = world_pts @ T[:3, :3].T + T[:3, 3]
    mesh = trimesh.Trimesh(vertices=norm_pts, faces=np.array([[0, 1, 2]]), process=False)
    np.testing.assert_allclose(to_frame(mesh, "world", T).vertices, world_pts, atol=1e-9)
    np.testing.assert_allclose(to_frame(mesh, "normalized", T).vertices, norm_pts)
    meta = frame_metadata("world", T)
    assert meta["frame"] == "world" and abs(meta["world_units_per_normalized_unit"] - 4.0) < 1e-9
    with pytest.raises(ConfigError, match="export.frame"):
        to_frame(mesh, "camera", T)


def test_ndc_points_map_back_to_the_scene() -> None:
    """NDC -> normalized inverts ndc_rays: a scene point's NDC image maps back to it; the far plane is dropped."""
    K = torch.tensor([[400.0, 0, 252], [0, 400.0, 189], [0, 0, 1]])
    pts = torch.tensor([[0.3, -0.2, -2.0], [1.0, 0.5, -7.5], [-0.4, 0.1, -1.2]], dtype=torch.float64)
    o, d = ndc_rays(torch.zeros_like(pts), pts, K.double(), 1.0, H=378, W=504)
    # the NDC ray through the point, at the point's NDC depth z_ndc = 1 + 2 near / z
    z_ndc = 1.0 + 2.0 / pts[:, 2]
    t = (z_ndc - o[:, 2]) / d[:, 2]
    ndc_pts = (o + t[:, None] * d).numpy()
    back, finite = ndc_to_normalized(ndc_pts, 400.0, 400.0, 504, 378, 1.0)
    np.testing.assert_allclose(back, pts.numpy(), rtol=1e-6, atol=1e-6)
    assert finite.all()
    _, far = ndc_to_normalized(np.array([[0.0, 0.0, 0.9999]]), 400.0, 400.0, 504, 378)
    assert not far.any()


def test_files_say_which_frame(tmp_path) -> None:
    mesh = trimesh.creation.icosphere(subdivisions=1)
    meta = frame_metadata("world", similarity(0.5, 0.0, (0, 0, 0)))
    for fmt in ("ply", "obj", "glb"):
        path = export_mesh(mesh, tmp_path / f"m.{fmt}", meta=meta)
        loaded = trimesh.load(path, process=False)
        geom = next(iter(loaded.geometry.values())) if isinstance(loaded, trimesh.Scene) else loaded
        assert len(geom.vertices) >= len(mesh.vertices) // 2, fmt
        raw = path.read_bytes()
        if fmt == "glb":
            assert b'"nerfart"' in raw and b'"frame":"world"' in raw
        else:
            head = raw[:2000].decode(errors="ignore")
            line = next(l for l in head.splitlines() if "nerfart {" in l)
            assert json.loads(line.split("nerfart ", 1)[1])["frame"] == "world"
