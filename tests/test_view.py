"""Off-screen PyVista viewer: screenshots and the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.export.mesh import MeshExtractor, export_mesh
from nerfart_plugin.fields.analytic import SphereSDF, TorusSDF, UnionSDF
from nerfart_plugin.viewer.mesh import load_mesh, main, render_meshes

REPO = Path(__file__).resolve().parents[1]
SIZE = (240, 200)


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("meshes")
    ex = MeshExtractor(resolution=40, show_progress=False)
    return {
        "sphere": export_mesh(ex.extract(SphereSDF(0.5)), d / "sphere.ply"),
        "torus": export_mesh(ex.extract(TorusSDF()), d / "torus.glb"),
        "bumpy": export_mesh(ex.extract(UnionSDF(SphereSDF(0.45), SphereSDF(0.2, (0.4, 0, 0)))), d / "bumpy.obj"),
    }


@pytest.mark.slow
def test_opens_on_the_captures_front_view(tmp_path, mesh_files):
    """The viewer reads the run's cameras.json and looks from the capture's front camera with its up
    vector (the shipped head used to open on the underside of the bust). First in this file: loading
    a scene imports triton (through torch), which segfaults once VTK's EGL context exists."""
    import json

    from nerfart_plugin.cameras.capture import viewer_cameras
    from nerfart_plugin.data import load_scene
    from nerfart_plugin.data.datamodule import DEFAULT_SCENE
    from nerfart_plugin.viewer.mesh import capture_view, find_cameras

    cams = viewer_cameras(load_scene("h3ds", DEFAULT_SCENE, resolution=32))
    eye, centre, up = (np.asarray(v) for v in capture_view(cams))
    rel = eye - centre
    elevation = np.degrees(np.arcsin(rel @ up / np.linalg.norm(rel)))
    assert abs(elevation) < 40 and cams["names"][cams["front"]] == "0030.jpg"  # a frontal view of the face
    # found beside the meshes: <run>/mesh/x.ply -> <run>/cameras.json
    run = tmp_path / "run"
    (run / "mesh").mkdir(parents=True)
    mesh = run / "mesh" / "bumpy.obj"
    mesh.write_bytes(Path(mesh_files["bumpy"]).read_bytes())
    (run / "cameras.json").write_text(json.dumps(cams))
    assert find_cameras([mesh]) == run / "cameras.json"
    # the view follows the cameras: front at +x and at -x give different pictures of the bump at +x
    def looking_from(x: float) -> dict:
        c = {"c2w": [[[0, 0, -np.sign(x), x], [0, 1, 0, 0], [np.sign(x), 0, 0, 0]]], "front": 0,
             "centre": [0, 0, 0], "up": [0, -1, 0]}
        return c
    a = render_meshes([mesh], screenshot=tmp_path / "a.png", window_size=SIZE, cameras=looking_from(2.0))
    b = render_meshes([mesh], screenshot=tmp_path / "b.png", window_size=SIZE, cameras=looking_from(-2.0))
    assert np.abs(a.astype(float) - b.astype(float)).mean() > 2
    with pytest.raises(Exception, match="malformed"):
        render_meshes([mesh], screenshot=tmp_path / "c.png", window_size=SIZE, cameras={"front": 0})


@pytest.mark.slow
def test_one_mesh_screenshot_not_blank_and_differs(tmp_path, mesh_files):
    a = render_meshes([mesh_files["sphere"]], screenshot=tmp_path / "a.png", window_size=SIZE)
    b = render_meshes([mesh_files["torus"]], screenshot=tmp_path / "b.png", window_size=SIZE)
    img = iio.imread(tmp_path / "a.png")
    assert img.shape[:2] == (SIZE[1], SIZE[0]) and np.array_equal(img[..., :3], a)
    assert a.std() > 10 and b.std() > 10
    assert np.abs(a.astype(float) - b.astype(float)).mean() > 5
    # Vertex colours are shown: many distinct hues, not one flat material colour.
    assert len(np.unique(a.reshape(-1, 3) // 16, axis=0)) > 20


def test_two_meshes_side_by_side(tmp_path, mesh_files):
    two = render_meshes([mesh_files["sphere"], mesh_files["bumpy"]], screenshot=tmp_path / "two.png", window_size=SIZE)
    same = render_meshes(
        [mesh_files["sphere"], mesh_files["sphere"]], screenshot=tmp_path / "same.png", window_size=SIZE
    )
    assert two.shape[:2] == (SIZE[1], SIZE[0]) and two.std() > 10
    assert np.abs(two.astype(float) - same.astype(float)).mean() > 2
    # Displacement colormap on the right: the bump (outward) is red, the shrunken body blue.
    right = two[:, SIZE[0] // 2 :].reshape(-1, 3).astype(int)
    assert ((right[:, 0] - right[:, 2]) > 60).sum() > 30 and ((right[:, 2] - right[:, 0]) > 60).sum() > 30


def test_errors_name_the_file(tmp_path, capsys):
    with pytest.raises(DataError, match="missing.ply"):
        load_mesh(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("not a mesh")
    with pytest.raises(DataError, match="bad.ply"):
        load_mesh(bad)
    with pytest.raises(ConfigError, match="two meshes"):
        render_meshes([tmp_path / "x.ply"], scalars="displacement")
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "missing.ply"), "--screenshot", str(tmp_path / "o.png")])
    assert info.value.code == 2
    for size in (["0", "-5"], ["100", "0"], ["20000", "100"]):  # refused before any mesh is read
        with pytest.raises(ConfigError, match=r"--window-size .*from 16 to 16384"):
            render_meshes([tmp_path / "missing.ply"], screenshot=tmp_path / "o.png", window_size=tuple(map(int, size)))
        with pytest.raises(SystemExit) as info:
            main([str(tmp_path / "missing.ply"), "--screenshot", str(tmp_path / "o.png"), "--window-size", *size])
        assert info.value.code == 2 and f"--window-size {' '.join(size)}" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="--samples 0"):
        render_meshes([tmp_path / "a.ply", tmp_path / "b.ply"], screenshot=tmp_path / "o.png", n_samples=0)
    assert not (tmp_path / "o.png").exists()


@pytest.mark.slow
def test_cli_subprocess(tmp_path, mesh_files):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}

    def view(*args: str, timeout: int = 120) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "nerfart_plugin.viewer.mesh", *args], cwd=tmp_path, env=env,
                              check=False, capture_output=True, text=True, timeout=timeout)

    out = tmp_path / "cli.png"
    res = view(str(mesh_files["sphere"]), str(mesh_files["torus"]), "--screenshot", str(out), "--window-size",
               "200", "120", "--scalars", "rgb", timeout=300)
    assert res.returncode == 0, res.stderr
    img = iio.imread(out)
    assert img.shape[:2] == (120, 200) and img.std() > 10
    help_ = view("--help")
    assert help_.returncode == 0 and "--screenshot" in help_.stdout
    bad = view(str(tmp_path / "nope.ply"), "--screenshot", str(tmp_path / "x.png"))
    assert bad.returncode == 2 and "nope.ply" in bad.stderr

