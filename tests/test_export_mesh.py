"""MeshExtractor on analytic stand-in fields (sphere/torus SDF, density blob)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.export.compare import chamfer_to_analytic
from nerfart_plugin.export.mesh import EmptyLevelSetError, MeshExtractor, export_mesh, view_directions
from nerfart_plugin.fields.analytic import DensityFromSDF, SphereSDF, TorusSDF, UnionSDF


def extractor(**kw) -> MeshExtractor:
    kw.setdefault("resolution", 48)
    kw.setdefault("show_progress", False)
    return MeshExtractor(**kw)


def test_sphere_sdf_radius_watertight_outward_coloured():
    mesh = extractor(resolution=64).extract(SphereSDF(0.5))
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(r.mean() - 0.5) < 2e-3 and r.std() < 2e-3
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 0.125, rel=0.02)  # > 0: outward normals
    # Normals point away from the centre.
    assert (np.einsum("ij,ij->i", mesh.vertex_normals, mesh.vertices) > 0).mean() > 0.99
    cols = mesh.visual.vertex_colors
    assert cols.shape == (len(mesh.vertices), 4) and cols[:, :3].std() > 5
    # Colour matches the field's rgb at the vertex looking along -normal.
    f = SphereSDF(0.5)
    x = torch.tensor(mesh.vertices[:5], dtype=torch.float32)
    d = -torch.tensor(mesh.vertex_normals[:5], dtype=torch.float32)
    ref = (f(x, d)["rgb"] * 255).round().numpy()
    assert np.abs(cols[:5, :3] - ref).max() <= 1
    assert mesh.metadata["extraction"]["level"] == 0.0


def test_world_coordinates_off_centre_and_bound():
    mesh = extractor(resolution=48, bound=2.0, color=False).extract(SphereSDF(0.6, center=(0.8, -0.5, 0.3)))
    assert np.allclose(mesh.center_mass, [0.8, -0.5, 0.3], atol=5e-3)
    assert abs(np.linalg.norm(mesh.vertices - [0.8, -0.5, 0.3], axis=1).mean() - 0.6) < 5e-3
    assert mesh.visual.kind is None or mesh.visual.kind != "vertex"


def test_density_field_inside_is_above_level():
    field = DensityFromSDF(SphereSDF(0.5))
    assert field.mesh_inside_is_below is False
    mesh = extractor(resolution=64).extract(field)
    assert mesh.is_watertight and mesh.volume > 0  # outward normals for the density convention too
    assert abs(np.linalg.norm(mesh.vertices, axis=1).mean() - 0.5) < 3e-3
    # A lower density threshold encloses more of the soft blob: a larger surface.
    bigger = extractor(resolution=64, level=field.mesh_level / 10, color=False).extract(field)
    assert np.linalg.norm(bigger.vertices, axis=1).mean() > 0.5 + 0.02


def test_chunk_size_does_not_change_result():
    field = TorusSDF()
    a = extractor(chunk=997).extract(field)
    b = extractor(chunk=10_000_000).extract(field)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.visual.vertex_colors, b.visual.vertex_colors)


def test_floater_removal_drops_small_blob():
    field = UnionSDF(SphereSDF(0.5), SphereSDF(0.08, center=(0.75, 0.75, 0.0)))
    kept = extractor(resolution=64, color=False).extract(field)
    assert len(kept.split(only_watertight=False)) == 2
    clean = extractor(resolution=64, color=False, remove_floaters=True, min_component_fraction=0.1).extract(field)
    assert len(clean.split(only_watertight=False)) == 1
    assert np.abs(np.linalg.norm(clean.vertices, axis=1) - 0.5).max() < 0.01
    assert clean.is_watertight
    # Fraction 0 keeps everything.
    same = extractor(resolution=64, color=False, remove_floaters=True, min_component_fraction=0.0).extract(field)
    assert len(same.faces) == len(kept.faces)


def test_empty_level_set_error_names_range_and_setting():
    with pytest.raises(EmptyLevelSetError, match=r"level.*range over \[") as exc:
        extractor(level=5.0).extract(SphereSDF(0.5))
    assert "export.level" in str(exc.value)
    with pytest.raises(ConfigError, match="bound"):  # whole box inside the object
        extractor().extract(SphereSDF(3.0))


def test_non_finite_values_are_treated_as_outside():
    class Holey(SphereSDF):
        def sdf(self, x):
            v = super().sdf(x)
            return torch.where(x[:, 0] > 0.9, torch.full_like(v, float("nan")), v)

    mesh = extractor(color=False).extract(Holey(0.5))
    assert mesh.is_watertight and abs(np.linalg.norm(mesh.vertices, axis=1).mean() - 0.5) < 5e-3


def test_bad_settings_raise_config_error():
    for kw in ({"resolution": 2}, {"bound": 0}, {"chunk": 0}, {"min_component_fraction": 2}):
        with pytest.raises(ConfigError):
            MeshExtractor(**kw)


def test_field_with_parameters_and_multi_view_colour():
    class Learned(torch.nn.Module):
        mesh_level, mesh_inside_is_below = 0.0, True

        def __init__(self):
            super().__init__()
            self.r = torch.nn.Parameter(torch.tensor(0.4))

        def geometry(self, x):
            return x.norm(dim=-1) - self.r

        def forward(self, x, d):
            return {"rgb": (d * 0.5 + 0.5).clamp(0, 1), "sdf": self.geometry(x)}

    mesh = extractor(color_views=5).extract(Learned())
    # rgb depends only on view dir; averaged around -normal it stays close to (-n/2 + 1/2).
    expect = (-mesh.vertex_normals * 0.5 + 0.5) * 255
    assert np.abs(mesh.visual.vertex_colors[:, :3] - expect).mean() < 15
    dirs = view_directions(torch.randn(10, 3), 5)
    assert dirs.shape == (10, 5, 3) and torch.allclose(dirs.norm(dim=-1), torch.ones(10, 5), atol=1e-5)


@pytest.mark.parametrize("suffix", ["ply", "obj", "glb"])
def test_export_round_trip(tmp_path, suffix):
    mesh = extractor(resolution=32).extract(SphereSDF(0.5))
    path = export_mesh(mesh, tmp_path / f"mesh.{suffix}")
    assert path.exists() and [p.name for p in tmp_path.iterdir()] == [f"mesh.{suffix}"]  # no temp left
    back = trimesh.load(path, force="mesh")
    assert len(back.faces) == len(mesh.faces)
    assert len(back.vertices) == len(mesh.vertices)
    assert np.allclose(np.sort(back.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-5)
    cols = back.visual.to_color().vertex_colors if back.visual.kind == "texture" else back.visual.vertex_colors
    assert cols[:, :3].std() > 5  # colours survived


def test_export_unknown_suffix(tmp_path):
    mesh = extractor(resolution=16, color=False).extract(SphereSDF(0.5))
    with pytest.raises(ConfigError, match=r"\.ply"):
        MeshExtractor().export(mesh, tmp_path / "mesh.stl")


@pytest.mark.slow
def test_chamfer_to_true_surface_falls_with_resolution():
    field = TorusSDF(0.5, 0.2)
    coarse = chamfer_to_analytic(extractor(resolution=32, color=False).extract(field), field, n_samples=20_000)
    fine = chamfer_to_analytic(extractor(resolution=96, color=False).extract(field), field, n_samples=20_000)
    assert fine["chamfer"] < coarse["chamfer"] / 4  # ~ cell^2 convergence: (95/31)^2 ~ 9
    assert coarse["chamfer"] < 0.01


def test_extract_to_writes_file(tmp_path):
    mesh = extractor(resolution=24).extract_to(SphereSDF(0.5), tmp_path / "sub" / "m.ply")
    assert (tmp_path / "sub" / "m.ply").exists() and len(mesh.faces) > 0


def test_a_stylization_copies_its_sources_mesh_instead_of_extracting_it_again(tmp_path, monkeypatch):
    """The source mesh is keyed by the field's tensors, the scene and the export settings: the same key copies
    the reconstruction's files (no marching cubes, no texture bake); another field or setting extracts anew."""
    from types import SimpleNamespace

    import nerfart_plugin.export.mesh as mesh_module
    from nerfart_plugin.config.schema import ExportConfig
    from nerfart_plugin.export.run_meshes import export_source_mesh

    def scene(**export) -> SimpleNamespace:
        cfg = SimpleNamespace(export=ExportConfig(resolution=24, formats=["ply", "obj"], frame="normalized",
                                                  texture_size=64, **export))
        cams = SimpleNamespace(ndc=False, normalization=np.eye(4).tolist())
        return SimpleNamespace(cfg=cfg, scene=SimpleNamespace(content_hash="head"), cameras=cams)

    calls = []
    real = mesh_module.MeshExtractor.extract
    monkeypatch.setattr(mesh_module.MeshExtractor, "extract", lambda self, f: calls.append(1) or real(self, f))
    field = SphereSDF(0.5)
    recon, style = tmp_path / "recon" / "mesh" / "source", tmp_path / "style" / "mesh" / "source"
    made = export_source_mesh(scene(), field, recon)
    assert len(calls) == 1
    got = export_source_mesh(scene(), field, style, shared=recon)
    assert len(calls) == 1, "the same field and settings must not be extracted again"
    names = ["source.ply", "source.obj", "source_textured.obj", "source_textured.mtl", "source_textured.png",
             "source_textured.glb"]
    for name in names:
        assert (style.parent / name).read_bytes() == (recon.parent / name).read_bytes(), name
    np.testing.assert_array_equal(got.vertices, made.vertices)
    np.testing.assert_array_equal(got.faces, made.faces)
    np.testing.assert_array_equal(got.visual.vertex_colors, made.visual.vertex_colors)
    # another export setting, another field, or a damaged source folder: extracted anew
    export_source_mesh(scene(level=0.05), field, tmp_path / "a" / "source", shared=recon)
    changed = SphereSDF(0.5)
    changed.register_buffer("trained", torch.ones(1))  # other tensors: another field
    export_source_mesh(scene(), changed, tmp_path / "b" / "source", shared=recon)
    (recon.parent / "source_textured.png").unlink()
    export_source_mesh(scene(), field, tmp_path / "c" / "source", shared=recon)
    assert len(calls) == 4


def test_tensors_hash_reads_every_kind_of_tensor_and_changes_with_any_value():
    from nerfart_plugin.export.run_meshes import tensors_hash

    m = torch.nn.Linear(2, 2)
    for name, t in (("scalar", torch.tensor(1.5)), ("mask", torch.zeros(4, dtype=torch.bool)), ("empty", torch.zeros(0)),
                    ("halves", torch.ones(3, dtype=torch.float16))):
        m.register_buffer(name, t)
    before = tensors_hash(m)
    assert tensors_hash(m) == before
    m.scalar.fill_(2.5)
    assert tensors_hash(m) != before
