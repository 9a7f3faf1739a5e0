"""Textured mesh export: xatlas UV atlas + texture baked from the field, OBJ+MTL+PNG and GLB."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

pytest.importorskip("xatlas")

from nerfart_plugin.export import MeshExtractor  # noqa: E402
from nerfart_plugin.export.texture import bake_texture, export_textured, rasterize_atlas  # noqa: E402
from nerfart_plugin.fields.analytic import SphereSDF  # noqa: E402


@pytest.fixture(scope="module")
def sphere_and_mesh():
    field = SphereSDF(radius=0.5)
    mesh = MeshExtractor(resolution=40, bound=1.0).extract(field)
    return field, mesh


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    col = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    row = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)
    return image[row, col, :3].astype(np.float64) / 255.0


def test_baked_texture_holds_the_field_colour(sphere_and_mesh) -> None:
    field, mesh = sphere_and_mesh
    tex = bake_texture(mesh, field, size=512)
    image = np.asarray(tex.visual.material.image.convert("RGB"))
    assert image.shape == (512, 512, 3) and len(tex.visual.uv) == len(tex.vertices)
    # the texture at each face centre's UV is the field's colour at that face centre
    centres = tex.triangles_center
    uv_c = tex.visual.uv[tex.faces].mean(1)
    with torch.no_grad():
        d = torch.nn.functional.normalize(-torch.as_tensor(centres, dtype=torch.float32), dim=-1)
        want = field(torch.as_tensor(centres, dtype=torch.float32), d)["rgb"].numpy()
    err = np.abs(sample_texture(image, uv_c) - want).mean()
    assert err < 0.03, err
    # vertex colours of the untextured mesh agree with the texture within a texel's worth of variation
    assert np.isfinite(tex.vertices).all() and np.allclose(np.linalg.norm(tex.vertices, axis=1), 0.5, atol=0.05)


def test_rasterizer_covers_each_triangle_once() -> None:
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]])
    index = rasterize_atlas(faces, uv, 64)
    covered = index >= 0
    assert 0.55 < covered.mean() < 0.7  # the square [0.1, 0.9]^2 is 64% of the atlas
    assert set(np.unique(index[covered])) == {0, 1}
    assert index[0, 0] == -1 and index[32, 32] in (0, 1)


def test_export_obj_mtl_png_and_glb(sphere_and_mesh, tmp_path) -> None:
    field, mesh = sphere_and_mesh
    tex = bake_texture(mesh, field, size=128)
    paths = export_textured(tex, tmp_path / "stylized_textured")
    names = sorted(p.name for p in paths)
    assert names == ["stylized_textured.glb", "stylized_textured.mtl", "stylized_textured.obj", "stylized_textured.png"]
    assert "map_Kd stylized_textured.png" in (tmp_path / "stylized_textured.mtl").read_text()
    assert "mtllib stylized_textured.mtl" in (tmp_path / "stylized_textured.obj").read_text()
    obj = trimesh.load(tmp_path / "stylized_textured.obj", process=False)
    assert isinstance(obj.visual, trimesh.visual.TextureVisuals) and obj.visual.material.image.size == (128, 128)
    glb = trimesh.load(tmp_path / "stylized_textured.glb")
    geom = next(iter(glb.geometry.values())) if isinstance(glb, trimesh.Scene) else glb
    assert geom.visual.material.baseColorTexture.size == (128, 128)
    assert len(geom.faces) == len(tex.faces)


def test_the_textured_copy_is_decimated_to_the_face_budget_and_stays_on_the_surface(sphere_and_mesh) -> None:
    field, mesh = sphere_and_mesh
    budget = len(mesh.faces) // 4
    tex = bake_texture(mesh, field, size=256, faces=budget)
    assert 0.8 * budget <= len(tex.faces) <= budget + 2
    radius = np.linalg.norm(tex.vertices, axis=1)  # the sphere of radius 0.5, kept by the decimation
    assert np.abs(radius - 0.5).max() < 0.02
    assert len(bake_texture(mesh, field, size=64, faces=0).faces) == len(mesh.faces)  # 0: every triangle
    assert len(bake_texture(mesh, field, size=64, faces=10**6).faces) == len(mesh.faces)
