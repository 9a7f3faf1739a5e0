"""compare_meshes / vertex_distances / displacement_mesh on spheres with known offsets."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.export.compare import SurfaceDistance, compare_meshes, displacement_mesh, vertex_distances
from nerfart_plugin.export.mesh import MeshExtractor, export_mesh
from nerfart_plugin.fields.analytic import DensityFromSDF, SphereSDF

N = 20_000


@pytest.fixture(scope="module")
def spheres() -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    ex = MeshExtractor(resolution=64, color=False, show_progress=False)
    return ex.extract(SphereSDF(0.5)), ex.extract(SphereSDF(0.55))


def test_sphere_vs_scaled_sphere_known_distance(spheres):
    source, stylized = spheres
    m = compare_meshes(stylized, source, n_samples=N, source_sdf=SphereSDF(0.5))
    assert m["chamfer"] == pytest.approx(0.05, abs=2e-3)
    assert m["hausdorff"] == pytest.approx(0.05, abs=3e-3)
    assert m["chamfer_l2"] == pytest.approx(0.05**2, rel=0.1)
    assert m["vertex_mean_signed"] == pytest.approx(0.05, abs=2e-3)  # positive: outward
    assert m["vertex_fraction_outward"] == 1.0
    assert m["signed"] is True and "chamfer" in m["convention"]
    import json

    json.dumps(m)  # metrics.json-ready


def test_sign_is_negative_inward_and_symmetric(spheres):
    source, stylized = spheres
    d = vertex_distances(source, stylized, source_sdf=SphereSDF(0.55), n_samples=N)
    assert np.all(d < 0) and d.mean() == pytest.approx(-0.05, abs=2e-3)
    d_n = vertex_distances(source, stylized, sign_from_normals=True, n_samples=N)
    assert np.allclose(d, d_n, atol=1e-6)
    d_u = vertex_distances(source, stylized, n_samples=N)
    assert np.allclose(np.abs(d), d_u)


def test_identical_meshes_distance_zero(spheres):
    source, _ = spheres
    m = compare_meshes(source, source, n_samples=N)
    assert m["chamfer"] < 1e-4 and m["vertex_max_abs"] < 1e-6 and "vertex_mean_signed" not in m


def test_surface_distance_matches_analytic_off_surface(spheres):
    source, _ = spheres
    pts = SphereSDF(0.8).sample_surface(2000, seed=3)
    d = SurfaceDistance(source, n_samples=N).query(pts)
    assert np.allclose(d, 0.3, atol=3e-3)  # 0.3 minus the mesh's chord sag


def test_density_field_rejected_as_sdf(spheres):
    source, stylized = spheres
    with pytest.raises(ConfigError, match="density"):
        vertex_distances(stylized, source, source_sdf=DensityFromSDF(SphereSDF(0.5)), n_samples=N)


def test_displacement_mesh_has_colours_and_roundtrips(tmp_path, spheres):
    source, stylized = spheres
    d = vertex_distances(stylized, source, source_sdf=SphereSDF(0.5), n_samples=N)
    d[: len(d) // 2] *= -1  # both signs -> both ends of the diverging map
    dm = displacement_mesh(stylized, d)
    path = export_mesh(dm, tmp_path / "displacement.ply")
    back = trimesh.load(path, force="mesh")
    cols = back.visual.vertex_colors[:, :3].astype(int)
    assert len(back.vertices) == len(stylized.vertices)
    # coolwarm: positive -> red-ish, negative -> blue-ish.
    pos, neg = d > 0, d < 0
    assert (cols[pos, 0] > cols[pos, 2]).all() and (cols[neg, 2] > cols[neg, 0]).all()
    with pytest.raises(DataError, match="distances"):
        displacement_mesh(stylized, d[:-1])


def test_empty_mesh_rejected(spheres):
    with pytest.raises(DataError, match="empty"):
        compare_meshes(trimesh.Trimesh(), spheres[0], n_samples=100)
