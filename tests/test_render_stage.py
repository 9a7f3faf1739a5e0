"""stage=render and the Python API: a finished run re-renders along any camera path without retraining;
nerfstudio camera_path.json files are read and written in the capture's world frame."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from pipeline_helpers import run_cli, tiny_cfg

from nerfart_plugin.cameras.capture import CaptureCameras, viewer_cameras
from nerfart_plugin.cameras.path import read_camera_path, resolve_path, write_camera_path
from nerfart_plugin.data import load_scene
from nerfart_plugin.data.datamodule import DEFAULT_SCENE
from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.rendering.frames import colorize_depth, depth_normals


@pytest.fixture(scope="module")
def head_cameras() -> CaptureCameras:
    scene = load_scene("h3ds", DEFAULT_SCENE, resolution=32)
    return CaptureCameras.from_json(json.loads(json.dumps(viewer_cameras(scene, "world"))))


def test_cameras_json_reads_back_in_the_training_frame() -> None:
    scene = load_scene("h3ds", DEFAULT_SCENE, resolution=32)
    direct = CaptureCameras.from_scene(scene, ndc=False)
    for frame in ("world", "normalized"):
        back = CaptureCameras.from_json(json.loads(json.dumps(viewer_cameras(scene, frame))))
        np.testing.assert_allclose(back.c2w, direct.c2w, atol=1e-6)
        np.testing.assert_allclose(back.near, direct.near)
        assert back.train_ids == direct.train_ids and (back.width, back.height) == (32, 32)


@pytest.mark.parametrize("frame", ["world", "normalized"])
def test_camera_path_json_round_trip(head_cameras: CaptureCameras, tmp_path: Path, frame: str) -> None:
    orbit = resolve_path(head_cameras, "orbit", frames=7, long_side=48)
    file = write_camera_path(orbit, head_cameras, tmp_path / "camera_path.json", fps=12, frame=frame)
    d = json.loads(file.read_text())
    assert d["render_width"] == 48 and len(d["camera_path"]) == 7 and d["fps"] == 12
    back = read_camera_path(file, head_cameras, frame)
    assert (back.height, back.width, back.fps) == (48, 48, 12)
    torch.testing.assert_close(back.c2w, orbit.c2w, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.K, orbit.K, atol=1e-3, rtol=1e-5)
    # a long side asked for resizes the file's frames, keeping the field of view
    half = read_camera_path(file, head_cameras, frame, long_side=24)
    torch.testing.assert_close(half.K[:, :2] * 2, orbit.K[:, :2], atol=2e-3, rtol=1e-5)


def test_nerfstudio_opengl_camera_looks_where_it_says(head_cameras: CaptureCameras, tmp_path: Path) -> None:
    """A camera written by hand as nerfstudio does (OpenGL axes: looking down -z, y up) in the world frame
    looks at the point it was aimed at once read: its OpenCV +z in the training frame points there."""
    T_inv = np.linalg.inv(head_cameras.normalization)
    target_w = T_inv[:3, :3] @ np.zeros(3) + T_inv[:3, 3]            # the normalized origin, in world units
    eye_w = head_cameras.to_world(head_cameras.c2w[:1])[0, :, 3]      # at training camera 0
    back = (eye_w - target_w) / np.linalg.norm(eye_w - target_w)     # OpenGL +z: away from the target
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = np.stack([right, up, back], 1), eye_w
    file = tmp_path / "hand.json"
    file.write_text(json.dumps({"render_height": 30, "render_width": 40,
                                "camera_path": [{"camera_to_world": m.reshape(-1).tolist(), "fov": 40.0, "aspect": 4 / 3}]}))
    rp = read_camera_path(file, head_cameras)
    c2w = rp.c2w[0].double().numpy()
    to_origin = -c2w[:, 3] / np.linalg.norm(c2w[:, 3])
    assert float(c2w[:, 2] @ to_origin) > 0.9999  # looks at the normalized origin
    assert (rp.height, rp.width) == (30, 40)
    assert float(rp.K[0, 1, 1]) == pytest.approx(15 / np.tan(np.deg2rad(20)), rel=1e-5)


def test_bad_camera_paths_say_what_is_wrong(head_cameras: CaptureCameras, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="render.path=nowhere.json.*camera_path.json"):
        resolve_path(head_cameras, "nowhere.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"render_height": 10, "render_width": 10, "camera_path": [{"fov": 50}]}))
    with pytest.raises(DataError, match="bad.json.*camera_to_world"):
        read_camera_path(bad, head_cameras)
    bad.write_text(json.dumps({"camera_type": "fisheye", "camera_path": []}))
    with pytest.raises(DataError, match="fisheye.*perspective"):
        read_camera_path(bad, head_cameras)
    bad.write_text("{not json")
    with pytest.raises(DataError, match="Cannot read the camera path"):
        read_camera_path(bad, head_cameras)
    # values from a file go through the checks of the command line: render.fps=-5 is refused, so is "fps": -5
    good = tmp_path / "good.json"
    write_camera_path(resolve_path(head_cameras, "orbit", frames=3), head_cameras, good, fps=24)
    for fps in (-5, 0, 500, "fast"):
        bad.write_text(json.dumps({**json.loads(good.read_text()), "fps": fps}))
        with pytest.raises(DataError, match=r"bad.json: its fps .* is refused, as render.fps="):
            read_camera_path(bad, head_cameras)
    assert read_camera_path(good, head_cameras).fps == 24


def test_depth_normals_of_a_plane_face_the_camera() -> None:
    from nerfart_plugin.data.rays import camera_batch

    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]])
    c2w = torch.eye(4)[:3]  # at the origin looking down +z
    b = camera_batch(K, c2w, 20, 20, 0.1, 5.0, ndc=False)
    t = 2.0 / b["rays_d"][:, 2]  # the plane z = 2
    n = depth_normals(b, t.reshape(20, 20, 1))
    torch.testing.assert_close(n[1:-1, 1:-1], torch.tensor([0.0, 0.0, -1.0]).expand(18, 18, 3), atol=1e-4, rtol=0)


def test_depth_colours_share_one_range_across_frames() -> None:
    near, far = np.full((4, 4), 1.0), np.full((4, 4), 3.0)
    near[0, 0], far[0, 0] = 2.0, 2.0  # the same depth in both frames
    ones = np.ones((4, 4))
    a, b = colorize_depth([near, far], [ones, ones])
    assert (a[0, 0] == b[0, 0]).all() and not (a[1, 1] == b[1, 1]).all()


@pytest.mark.slow
def test_finished_runs_re_render_along_any_path(tmp_path: Path) -> None:
    """A toy stylization, then stage=render from the CLI (no training): every channel as mp4 + PNGs and a
    camera_path.json, which rendered again gives the same frames; the API renders the same cameras."""
    from nerfart_plugin.api import open_run
    from nerfart_plugin.run.pipeline import run

    res = run(tiny_cfg(tmp_path, DEFAULT_SCENE, "guidance=toy", "prompt=red", "reconstruct.steps=20",
                       "stylize.steps=2"))
    style_dir = Path(res["stylization"]["dir"])
    mtime = (style_dir / "final.ckpt").stat().st_mtime
    proc = run_cli([f"output_root={tmp_path}", "stage=render", f"render.run={style_dir}", "render.frames=5",
                    "render.resolution=32", "render.channels=[rgb,depth,normal,side]", "render.png=true",
                    f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = style_dir / "render" / "orbit-5f-32x32"
    for channel in ("rgb", "depth", "normal", "side"):
        video = iio.imread(out / f"{channel}_UNSTYLED-toy.mp4", plugin="pyav")
        assert video.shape[0] == 5, channel
        assert len(list((out / f"{channel}_UNSTYLED-toy").glob("*.png"))) == 5
    assert video.shape[2] > 64  # side: source | stylized
    assert (style_dir / "final.ckpt").stat().st_mtime == mtime  # nothing retrained

    # the written path, rendered again, gives the same frames
    proc = run_cli([f"output_root={tmp_path}", "stage=render", f"render.run={style_dir}",
                    f"render.path={out / 'camera_path.json'}", "render.png=true", f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    again = style_dir / "render" / "camera_path-5f-32x32"
    for i in range(5):
        a = iio.imread(out / "rgb_UNSTYLED-toy" / f"{i:05d}.png").astype(int)
        b = iio.imread(again / "rgb_UNSTYLED-toy" / f"{i:05d}.png").astype(int)
        assert np.abs(a - b).max() <= 1, i

    # the API: a training camera by index or by its world-frame matrix renders the same image
    style = open_run(style_dir, device="cpu")
    assert style.kind == "stylization" and style.source.kind == "reconstruction"
    assert open_run(style_dir / "final.ckpt", device="cpu").folder == style_dir  # a checkpoint names its run
    world = style.cameras.to_world(style.cameras.c2w[3:4])[0]
    by_index, by_matrix = style.render(3)["rgb"], style.render(world)["rgb"]
    assert by_index.shape == (24, 24, 3) and np.abs(by_index.astype(int) - by_matrix.astype(int)).max() <= 1
    assert style.mesh(resolution=24).vertices.shape[0] > 0

    # a reconstruction has no source: side is refused with the fix; the default run is this config's
    proc = run_cli([f"output_root={tmp_path}", "stage=render", f"render.run={res['reconstruction']['dir']}",
                    "render.channels=[side]", f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode != 0 and "render.channels=side" in proc.stdout + proc.stderr
    recon = run(tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=render", "reconstruct.steps=20", "render.path=training"))
    assert Path(recon["render"]["dir"]).parent.parent == Path(res["reconstruction"]["dir"])
    assert recon["render"]["frames"] == len(style.cameras.train_ids)
