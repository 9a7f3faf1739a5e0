"""Gaussian splats: the rasterizer against a brute-force reference, the .ply layout and its round trip, a fit that
reproduces a field, and real splat clients reading the export (splat-transform in Node, Spark in Chromium)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData

from nerfart_plugin.errors import DataError
from nerfart_plugin.export.splats import (PLY_PROPERTIES, SplatFit, Views, fit_splats, initial_splats, read_ply,
                                          splat_quality, to_world, write_ply)
from nerfart_plugin.fields.analytic import DensityFromSDF, SphereSDF
from nerfart_plugin.rendering.splats import (C0, Splats, project, quat_to_rotmat, rasterize, rasterize_gsplat,
                                             rotmat_to_quat)

CAM = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.5]])
K = torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])


def random_splats(n: int = 60, seed: int = 0, grad: bool = False) -> Splats:
    g = torch.Generator().manual_seed(seed)
    s = Splats(torch.randn(n, 3, generator=g) * 0.3, torch.randn(n, 4, generator=g),
               torch.log(torch.rand(n, 3, generator=g) * 0.08 + 0.02), torch.randn(n, generator=g),
               torch.randn(n, 3, generator=g))
    return Splats(*(t.requires_grad_(grad) for t in s.parameters()))


def brute_force(splats: Splats, H: int, W: int) -> torch.Tensor:
    """Every Gaussian at every pixel, sorted by depth: the reference the tiled rasterizer must match."""
    proj = project(splats, CAM, K, H, W)
    order = torch.argsort(proj.depth.detach())
    order = order[proj.visible[order]]
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    dx = u.reshape(-1, 1) - proj.xy[order, 0][None]
    dy = v.reshape(-1, 1) - proj.xy[order, 1][None]
    a, b, c = proj.conic[order].unbind(-1)
    power = (-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy).clamp(max=0.0)
    alpha = (torch.sigmoid(splats.opacities[order]) * torch.exp(power)).clamp(max=0.99)
    alpha = alpha * (alpha >= 1 / 255)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    w = alpha * trans
    rgb = w @ splats.rgb()[order] + (1 - w.sum(1, keepdim=True))
    return rgb.reshape(H, W, 3)


def test_the_tiled_rasterizer_matches_the_brute_force_reference_and_its_gradients():
    splats = random_splats(grad=True)
    ours = rasterize(splats, CAM, K, 24, 32, tile=8, max_per_tile=1000)["rgb"]
    ref = brute_force(splats, 24, 32)
    torch.testing.assert_close(ours, ref, atol=1e-5, rtol=1e-5)
    g_ours = torch.autograd.grad(ours.square().sum(), splats.parameters())
    g_ref = torch.autograd.grad(brute_force(splats, 24, 32).square().sum(), splats.parameters())
    for a, b in zip(g_ours, g_ref):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3)


def test_one_gaussian_draws_its_colour_and_opacity_at_its_centre():
    s = Splats(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), math.log(0.2)),
               torch.tensor([math.log(0.5 / 0.5)]), torch.tensor([[(1.0 - 0.5) / C0, -0.5 / C0, -0.5 / C0]]))
    out = rasterize(s, CAM, K, 24, 32)
    centre = out["rgb"][12, 16]  # the pixel whose centre is the projection (16, 12) + 0.5 away
    assert 0.45 < float(out["alpha"][12, 16]) < 0.5 and centre[0] > 0.99 and centre[1] < 0.55
    assert float(out["alpha"][0, 0]) < 1e-3


def test_quaternions_round_trip():
    q = torch.nn.functional.normalize(torch.randn(100, 4), dim=-1)
    back = rotmat_to_quat(quat_to_rotmat(q))
    torch.testing.assert_close(quat_to_rotmat(back), quat_to_rotmat(q), atol=1e-5, rtol=0)
    assert (back[:, 0] >= 0).all()


def test_the_ply_is_the_3dgs_layout_and_round_trips(tmp_path):
    splats = random_splats(100)
    path = write_ply(splats, tmp_path / "s.ply")
    ply = PlyData.read(str(path))
    assert [p.name for p in ply["vertex"].properties] == PLY_PROPERTIES and len(PLY_PROPERTIES) == 62
    assert all(p.val_dtype in ("f4", "float32") for p in ply["vertex"].properties)
    assert ply.byte_order == "<" and not ply.text and not ply.comments and not ply.obj_info
    back = read_ply(path)
    torch.testing.assert_close(back.means, splats.means)
    torch.testing.assert_close(back.quats, torch.nn.functional.normalize(splats.quats, dim=-1))
    torch.testing.assert_close(back.log_scales, splats.log_scales)
    torch.testing.assert_close(back.opacities, splats.opacities)
    torch.testing.assert_close(back.colours, splats.colours)
    assert np.all(np.asarray(ply["vertex"]["f_rest_7"]) == 0)
    bad = random_splats(3)
    bad.means[0, 0] = float("nan")
    with pytest.raises(DataError, match="non-finite"):
        write_ply(bad, tmp_path / "bad.ply")
    assert not (tmp_path / "bad.ply").exists()
    (tmp_path / "no.ply").write_text("ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(DataError, match="not a 3DGS splat"):
        read_ply(tmp_path / "no.ply")


def test_the_world_frame_is_the_normalization_undone():
    T = np.diag([2.0, 2.0, 2.0, 1.0])
    T[:3, :3] = T[:3, :3] @ quat_to_rotmat(torch.tensor([[0.9, 0.1, -0.3, 0.2]]))[0].double().numpy()
    T[:3, 3] = [0.5, -1.0, 2.0]
    s = random_splats(20)
    w = to_world(s, T)
    back = to_world(w, np.linalg.inv(T))
    torch.testing.assert_close(back.means, s.means, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.log_scales, s.log_scales, atol=1e-5, rtol=0)
    torch.testing.assert_close(quat_to_rotmat(back.quats), quat_to_rotmat(s.quats), atol=1e-5, rtol=0)
    torch.testing.assert_close(w.log_scales, s.log_scales - math.log(2.0), atol=1e-5, rtol=0)


def test_a_fit_reproduces_a_field_better_than_its_initialization():
    """A coloured sphere: splats initialized on its surface, then fitted to its renders, read closer to them."""
    from nerfart_plugin.rendering import VolumeRenderer

    field = SphereSDF(0.5)
    renderer = VolumeRenderer(DensityFromSDF(field, scale=200.0, width=0.01), num_samples=48)
    cams = [_look_from(torch.tensor(p)) for p in ([0.0, 0, -2.5], [2.5, 0, 0], [0, -2.5, 0.1], [-1.8, 0, -1.8])]
    Kv = torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]])
    from nerfart_plugin.data.rays import camera_batch

    images = []
    with torch.no_grad():
        for c in cams:
            images.append(renderer.render_chunked(camera_batch(Kv, c, 32, 32, 1.0, 4.0, False))["rgb"].reshape(32, 32, 3))
    views = Views(torch.stack(cams), Kv.expand(len(cams), 3, 3), 32, 32, torch.stack(images))
    start = initial_splats(renderer.field, 600, mesh_resolution=48)
    fitted, curve = fit_splats(start, views, SplatFit(count=600, steps=120, tile_share=1.0), torch.ones(3))
    before, after = splat_quality(start, views, torch.ones(3)), splat_quality(fitted, views, torch.ones(3))
    assert after["psnr"] > before["psnr"] + 1.0 and after["psnr"] > 25, (before, after)
    assert curve[-1] < curve[0]


def _look_from(eye: torch.Tensor) -> torch.Tensor:
    """c2w [3,4] (OpenCV) of a camera at ``eye`` looking at the origin."""
    z = -eye / eye.norm()
    up = torch.tensor([0.0, -1.0, 0.0]) if abs(float(z[1])) < 0.9 else torch.tensor([0.0, 0.0, 1.0])
    x = torch.nn.functional.normalize(torch.cross(up, z, dim=0), dim=0)
    y = torch.cross(z, x, dim=0)
    return torch.cat([torch.stack([x, y, z], 1), eye[:, None]], 1)


@pytest.mark.cuda
def test_gsplat_and_the_pytorch_rasterizer_agree():
    """Where CUDA and gsplat exist: the same splats, the same image (gsplat has no cap per tile)."""
    pytest.importorskip("gsplat")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    s = Splats(*(t.cuda() for t in random_splats().parameters()))
    ours = rasterize(s, CAM.cuda(), K.cuda(), 24, 32, max_per_tile=1000)["rgb"]
    theirs = rasterize_gsplat(s, CAM.cuda(), K.cuda(), 24, 32)["rgb"]
    assert float((ours - theirs).abs().mean()) < 2e-3


# ---------------------------------------------------------------------- real clients
@pytest.fixture(scope="session")
def splat_clients() -> Path:
    """The npm clients (benchmarks/splat_clients.py), installed once; skipped where Node and npm are absent
    (unless the browser tests are required, as in CI)."""
    from benchmarks.splat_clients import install_clients, missing_node

    if missing_node():
        if os.environ.get("NERFART_REQUIRE_BROWSER"):
            pytest.fail("npm and node are required for the splat client tests (NERFART_REQUIRE_BROWSER is set)")
        pytest.skip(missing_node())
    return install_clients()


@pytest.fixture(scope="module")
def exported(tmp_path_factory, shared_runs) -> dict:
    """A small splat export of a tiny reconstruction of the shipped head (world frame)."""
    from pipeline_helpers import TINY, composed

    from nerfart_plugin.api import open_run
    from nerfart_plugin.export.splats import export_splats
    from nerfart_plugin.run.pipeline import run

    out = run(composed(f"output_root={shared_runs}", *TINY, "stage=reconstruct", "reconstruct.steps=300"))
    recon = open_run(out["reconstruction"]["dir"], device="cpu")
    folder = tmp_path_factory.mktemp("splats")
    report = export_splats(recon, folder / "head.ply", SplatFit(count=3000, steps=80, resolution=64, orbit_views=4))
    return {"run": recon, "report": report, "path": folder / "head.ply", "folder": folder}


@pytest.mark.slow
def test_splat_transform_reads_the_export_and_counts_what_we_wrote(splat_clients, exported):
    """PlayCanvas' splat-transform (Node) reads the .ply: the same count and bounds as ours, and it converts it
    to SuperSplat's compressed .ply."""
    from benchmarks.splat_clients import splat_transform

    out = splat_transform(splat_clients, str(exported["path"]), "--stats", "json", "null")
    assert out.returncode == 0, out.stderr[-2000:]
    stats = json.loads(out.stdout[out.stdout.index("{"):])
    ours = read_ply(exported["path"])
    assert stats["numGaussians"] == len(ours) == exported["report"]["gaussians"]
    columns, data = stats["stats"][0]["columns"], stats["stats"][0]["data"]
    for i, axis in enumerate("xyz"):
        j = columns.index(axis)
        assert data["min"][j] == pytest.approx(float(ours.means[:, i].min()), rel=1e-4, abs=1e-5)
        assert data["max"][j] == pytest.approx(float(ours.means[:, i].max()), rel=1e-4, abs=1e-5)
    assert sum(data["nanCount"]) == 0 and sum(data["infCount"]) == 0
    converted = exported["folder"] / "head.compressed.ply"
    done = splat_transform(splat_clients, str(exported["path"]), str(converted))
    assert done.returncode == 0 and converted.stat().st_size > 0, done.stderr[-2000:]


@pytest.mark.slow
def test_spark_in_chromium_draws_the_export_as_our_rasterizer_does(splat_clients, exported):
    """Spark (three.js, from npm) in the headless Chromium of the viewer tests draws the exported .ply from the
    capture's first training camera: its picture's silhouette matches our rasterizer's (IoU >= 0.9) and its
    colours too (PSNR >= 20 dB)."""
    from benchmarks.splat_clients import spark_screenshot

    from nerfart_plugin.viewer.browser import missing_browser

    if missing_browser():
        pytest.skip(missing_browser())
    cams, W, H = exported["run"].cameras, 96, 96
    i = cams.train_ids[0]
    c2w = cams.to_world(np.asarray(cams.c2w)[i:i + 1, :3, :4])[0]
    Kp = np.asarray(cams.K[i], dtype=np.float64) * np.array([[W / cams.width], [H / cams.height], [1.0]])
    spark = spark_screenshot(splat_clients, exported["path"], c2w, Kp, W, H)
    ours = rasterize(read_ply(exported["path"]), torch.tensor(c2w, dtype=torch.float32),
                     torch.tensor(Kp, dtype=torch.float32), H, W)["rgb"].numpy()
    a, b = ours.sum(-1) < 2.9, spark.sum(-1) < 2.9
    iou = (a & b).sum() / max(1, (a | b).sum())
    psnr_db = -10 * np.log10(((ours - spark) ** 2).mean())
    assert a.mean() > 0.05 and iou >= 0.9 and psnr_db >= 20, (iou, psnr_db)


@pytest.mark.slow
def test_stage_export_writes_splats_and_records_their_fit(shared_runs, exported):
    """``stage=export export.splats=true`` beside the meshes: the .ply in the run's splats/, its fit in the log
    and in the run's metrics.json."""
    from pipeline_helpers import TINY, composed

    from nerfart_plugin.run.pipeline import run

    folder = Path(exported["run"].folder)
    out = run(composed(f"output_root={shared_runs}", *TINY, "stage=export", "reconstruct.steps=300", "export.splats=true",
                       "export.splat_count=500", "export.splat_steps=20", "export.splat_resolution=32"))
    report = out["export"]["splats"]
    assert Path(report["file"]).parent == folder / "splats" and len(read_ply(Path(report["file"]))) == 500
    recorded = json.loads((folder / "metrics.json").read_text())["splats"][Path(report["file"]).name]
    assert recorded["psnr"] == report["psnr"] and recorded["frame"] == "world" and recorded["steps"] == 20
    mesh_files = sorted(Path(out["export"]["mesh"]).parent.glob(Path(out["export"]["mesh"]).name + "*"))
    stamps = {f: f.stat().st_mtime_ns for f in [Path(report["file"]), *mesh_files]}
    settings = [f"output_root={shared_runs}", *TINY, "stage=export", "reconstruct.steps=300", "export.splats=true",
                "export.splat_count=500", "export.splat_steps=20", "export.splat_resolution=32"]
    again = run(composed(*settings))["export"]
    assert again == out["export"] and mesh_files  # the same run and settings: reused, not written again
    assert {f: f.stat().st_mtime_ns for f in stamps} == stamps
    other = run(composed(*settings, "export.splat_steps=10"))["export"]["splats"]
    assert other["steps"] == 10 and Path(report["file"]).stat().st_mtime_ns != stamps[Path(report["file"])]
    assert all(f.stat().st_mtime_ns == stamps[f] for f in mesh_files)  # the splat settings do not touch the mesh
