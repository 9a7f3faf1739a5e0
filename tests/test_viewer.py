"""The web viewer's server logic without a browser: camera conversion, the frame schedule, keyframe paths,
render jobs per tab, the training controls, and the fields it renders (nerfart_plugin.viewer)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.cameras.path import read_camera_path
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.viewer.cameras import (ViewCamera, capture_camera, from_viser, matrix_to_wxyz, render_path,
    to_viser, wxyz_to_matrix)
from nerfart_plugin.viewer.jobs import TabRenderer
from nerfart_plugin.viewer.keyframes import catmull_rom, interpolate, save_path
from nerfart_plugin.viewer.live import LiveViewer, TrainingControl, readouts
from nerfart_plugin.viewer.schedule import FrameSchedule, wait_for_share
from nerfart_plugin.viewer.sources import LiveField, ViewSettings, split_frame, timed


def capture(n: int = 6, H: int = 60, W: int = 80, scale: float = 0.5) -> CaptureCameras:
    """Cameras on a circle looking at the origin, with a world->normalized similarity (scale, shift)."""
    from nerfart_plugin.cameras.orbits import _look_at

    c2w = np.stack([_look_at(np.array([3 * math.cos(a), 0.4, 3 * math.sin(a)]), np.zeros(3), np.array([0, -1.0, 0]))
                    for a in np.linspace(0, 2 * math.pi, n, endpoint=False)])
    K = np.tile(np.array([[70.0, 0, W / 2], [0, 70.0, H / 2], [0, 0, 1]]), (n, 1, 1))
    T = np.diag([scale, scale, scale, 1.0])
    T[:3, 3] = [0.1, -0.2, 0.3]
    return CaptureCameras(c2w, K, W, H, np.full(n, 1.0), np.full(n, 5.0), "object", False, T, list(range(n - 1)))


# ---------------------------------------------------------------------- cameras
def test_viser_cameras_and_opencv_cameras_convert_both_ways():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        R = wxyz_to_matrix(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(wxyz_to_matrix(matrix_to_wxyz(R)), R, atol=1e-10)
        cam = from_viser(q, rng.normal(size=3), 0.8, 1.5)
        wxyz, pos = to_viser(cam)
        back = from_viser(wxyz, pos, cam.fov_y, cam.aspect)
        np.testing.assert_allclose(back.c2w, cam.c2w, atol=1e-10)
    # viser's camera is OpenCV: +z looks forward, so a camera turned to face the origin sees it on its axis
    eye = np.array([0.0, 0.0, -4.0])
    cam = from_viser(np.array([1.0, 0, 0, 0]), eye, 1.0, 1.0)
    assert np.allclose(cam.c2w[:, 2], [0, 0, 1]) and np.allclose(cam.c2w[:, 3], eye)
    assert from_viser(np.array([1.0, 0, 0, 0]), eye, 9.0, float("nan")).aspect == 1.0  # clamped, no crash
    assert from_viser(np.array([1.0, 0, 0, 0]), eye, 9.0, 1.0).fov_y < math.pi


def test_a_capture_camera_through_the_viewer_renders_the_capture_cameras_own_rays():
    """world frame (what the browser shows) -> normalized frame (what the field sees) -> the same camera."""
    from nerfart_plugin.data.rays import camera_batch

    cams = capture()
    for i in (0, 3):
        view = capture_camera(cams, i)
        assert view.aspect == pytest.approx(80 / 60)
        rp = render_path(view, cams, long_side=80)
        assert (rp.height, rp.width) == (60, 80)
        np.testing.assert_allclose(rp.c2w[0].numpy(), cams.c2w[i], atol=1e-5)
        ours = camera_batch(rp.K[0], rp.c2w[0], 60, 80, 1.0, 5.0, False)
        theirs = camera_batch(torch.as_tensor(cams.K[i], dtype=torch.float32), torch.as_tensor(cams.c2w[i],
                              dtype=torch.float32), 60, 80, 1.0, 5.0, False)
        torch.testing.assert_close(ours["rays_d"], theirs["rays_d"], atol=1e-5, rtol=1e-5)
    # a portrait view keeps its long side
    assert ViewCamera(np.eye(4)[:3], 1.0, 0.5).size(100) == (100, 50)


# ---------------------------------------------------------------------- schedule
def test_the_moving_frame_follows_the_fields_speed_and_the_ladder_refines_to_the_finest():
    s = FrameSchedule(refine_sides=(256, 480), moving_seconds=0.1, min_side=32, max_moving_side=160)
    assert s.next_side() == 64  # no speed measured yet
    s.rendered(64 * 64, 0.01)
    assert s.next_side() == 256 and s.rays_per_second == pytest.approx(409600)
    s.rendered(256 * 256, 0.2)
    assert s.next_side() == 480
    s.rendered(480 * 270, 0.5)
    assert s.finished
    s.restart(aspect=16 / 9)
    fast = s.next_side()
    slow = FrameSchedule(rays_per_second=38_000.0)  # a draft selfie run: 3.4 s per 270x480 frame
    slow.restart(aspect=16 / 9)
    assert 32 <= slow.next_side() < fast <= 160  # a slow field gets a smaller moving frame, not a slow one
    assert slow.next_side() ** 2 * 9 / 16 / 38_000.0 == pytest.approx(0.08, rel=0.1)


def test_a_live_view_keeps_to_its_share_of_the_time():
    assert wait_for_share(0.1, None) == 0.0 and wait_for_share(0.1, 1.0) == 0.0
    assert wait_for_share(0.1, 0.1) == pytest.approx(0.9)  # 0.1 s of rendering in every second
    assert wait_for_share(0.2, 0.5) == pytest.approx(0.2)


# ---------------------------------------------------------------------- keyframes
def test_a_keyframe_path_passes_through_its_keyframes_and_saves_as_a_camera_path(tmp_path):
    cams = capture()
    keys = [capture_camera(cams, i) for i in (0, 1, 2)]
    keys[2] = ViewCamera(keys[2].c2w, keys[2].fov_y * 1.2, keys[2].aspect)
    path = interpolate(keys, 9)
    assert len(path) == 9
    for frame, key in ((0, 0), (4, 1), (8, 2)):
        np.testing.assert_allclose(path[frame].c2w, keys[key].c2w, atol=1e-9)
    assert path[0].fov_y < path[6].fov_y < path[8].fov_y == pytest.approx(keys[2].fov_y)
    for cam in path:
        np.testing.assert_allclose(cam.c2w[:, :3] @ cam.c2w[:, :3].T, np.eye(3), atol=1e-9)
    line = catmull_rom(np.array([[0.0], [1.0], [2.0], [3.0]]), np.linspace(0, 3, 7))
    np.testing.assert_allclose(line[:, 0], np.linspace(0, 3, 7))  # evenly spaced points: a straight, even line
    out, rp = save_path(keys, cams, tmp_path / "render" / "camera_paths" / "p.json", frames=9, fps=12, long_side=40)
    back = read_camera_path(out, cams)
    assert (back.height, back.width, back.fps, len(back)) == (30, 40, 12, 9)
    torch.testing.assert_close(back.c2w, rp.c2w, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(back.K, rp.K)
    with pytest.raises(ConfigError, match="no keyframes"):
        interpolate([], 10)
    with pytest.raises(ConfigError, match="frames=1"):
        interpolate(keys, 1)
    assert len(interpolate(keys[:1], 3)) == 3


# ---------------------------------------------------------------------- render jobs
class FakeField:
    """Renders a frame whose colour says which settings and camera made it; counts frames."""

    render_share = None

    def __init__(self, cams: CaptureCameras, delay: float = 0.0) -> None:
        self.cameras, self.lock, self.version, self.delay = cams, threading.Lock(), 0, delay
        self.sizes: list[int] = []

    def timed_render(self, camera: ViewCamera, long_side: int, settings: ViewSettings) -> tuple[np.ndarray, float]:
        return timed(self.render, camera, long_side, settings)

    def render(self, camera: ViewCamera, long_side: int, settings: ViewSettings) -> np.ndarray:
        self.sizes.append(long_side)  # when it starts
        time.sleep(self.delay)
        H, W = camera.size(long_side)
        value = int(abs(camera.c2w[0, 3]) * 10 + 100 * settings.weights[0]) % 256
        return np.full((H, W, 3), value, dtype=np.uint8)


def wait_until(cond, timeout: float = 10.0) -> bool:
    t0 = time.time()
    while not cond() and time.time() - t0 < timeout:
        time.sleep(0.01)
    return cond()


def test_a_tab_gets_a_fast_frame_then_refined_ones_and_a_closed_tab_stops():
    cams = capture()
    field, shown = FakeField(cams), []
    settings = ViewSettings()
    tab = TabRenderer(field, lambda: settings, FrameSchedule(refine_sides=(48, 96)), shown.append)
    tab.set_camera(capture_camera(cams, 0))
    assert wait_until(lambda: len(shown) == 2)
    assert [max(f.shape[:2]) for f in shown] == [64, 96]  # the moving frame, then the finest
    time.sleep(0.3)
    assert len(shown) == 2  # a resting camera is not rendered again
    settings = ViewSettings(weights=(0.5,))
    tab.refresh()
    assert wait_until(lambda: len(shown) == 3) and shown[-1][0, 0, 0] != shown[1][0, 0, 0]
    assert max(shown[-1].shape[:2]) == 96  # a fast field: the moving frame is already the finest
    tab.stop()
    assert not tab.alive
    n = len(field.sizes)
    time.sleep(0.3)
    assert len(field.sizes) == n  # a closed tab costs nothing


def test_a_refinement_outdated_by_a_camera_move_is_dropped():
    cams = capture()
    field, shown = FakeField(cams, delay=0.15), []
    tab = TabRenderer(field, ViewSettings, FrameSchedule(refine_sides=(200,)), shown.append)
    tab.set_camera(capture_camera(cams, 0))
    assert wait_until(lambda: len(field.sizes) >= 2)  # the 200 px refinement is under way
    tab.set_camera(capture_camera(cams, 2))
    assert wait_until(lambda: len(shown) >= 2 and max(shown[-1].shape[:2]) == 200)
    tab.stop()
    last = shown[-1][0, 0, 0]
    assert last == int(abs(capture_camera(cams, 2).c2w[0, 3]) * 10 + 100) % 256  # the new camera's frame
    assert sum(max(f.shape[:2]) == 200 for f in shown) == 1  # the old camera's refinement never reached the tab


def test_a_live_field_renders_at_most_its_share_of_the_time():
    cams = capture()
    field, shown = FakeField(cams, delay=0.05), []
    field.render_share = 0.25
    tab = TabRenderer(field, ViewSettings, FrameSchedule(refine_sides=(64,)), shown.append)
    tab.set_camera(capture_camera(cams, 0))
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < 1.5:  # training steps change the field all the time
        field.version += 1
        time.sleep(0.02)
    tab.stop()
    busy = len(field.sizes) * 0.05
    assert 2 <= len(field.sizes) and busy / 1.5 <= 0.25 + 0.1


# ---------------------------------------------------------------------- training controls
def test_pause_holds_the_trainer_resume_and_stop_release_it():
    control = TrainingControl()
    control.pause()
    passed = threading.Event()
    t = threading.Thread(target=lambda: (control.wait_while_paused(), passed.set()), daemon=True)
    t.start()
    assert not passed.wait(0.7) and control.paused
    control.resume()
    assert passed.wait(2.0)
    control.pause()
    control.stop()  # stopping a paused run lets it reach its checkpoint
    assert control.stop_requested and not control.paused
    text = readouts({"train/loss": torch.tensor(0.25), "train/psnr": 21.5, "other": 1}, 40, False, True)
    assert "step **40**" in text and "train/psnr: 21.5" in text and "stopping after this step" in text
    assert "other" not in text


def test_a_live_frame_is_rendered_on_the_training_thread_between_steps_and_stop_goes_through_the_checkpoint(
        monkeypatch):
    from nerfart_plugin.systems.callbacks import AtomicCheckpoint, GracefulInterrupt
    from nerfart_plugin.viewer import sources as fields

    threads = []

    def fake_frame(renderer, cams, camera, long_side, channel, chunk, device):
        threads.append(threading.current_thread())
        return np.zeros((4, 4, 3), np.uint8)

    monkeypatch.setattr(fields, "render_frame", fake_frame)

    class Trainer:
        global_rank, global_step, should_stop, callback_metrics = 0, 5, False, {}

        def __init__(self, callbacks):
            self.callbacks = callbacks

    system = type("System", (), {"device": torch.device("cpu"), "renderer": None})()
    field = LiveField(system, capture(), render_share=0.1, chunk=64)
    stop = GracefulInterrupt(AtomicCheckpoint(Path("."), 10))
    live = LiveViewer(capture())
    live.viewer = type("V", (), {"field": field, "panels": {"training": {"readouts": type("R", (), {"content": ""})()}},
                                 "stop": lambda self: None})()
    trainer = Trainer([stop, live])
    got = []
    tab = threading.Thread(target=lambda: got.append(field.timed_render(capture_camera(capture(), 0), 16,
                                                                        ViewSettings())), daemon=True)
    tab.start()
    time.sleep(0.3)
    assert not got  # a frame waits for the end of the step
    live.on_train_batch_end(trainer, None)
    tab.join(timeout=5)
    assert got and got[0][0].shape == (4, 4, 3) and threads == [threading.current_thread()]
    assert field.version == 1
    live.control.pause()
    tab = threading.Thread(target=lambda: got.append(field.timed_render(capture_camera(capture(), 1), 16,
                                                                        ViewSettings())), daemon=True)
    tab.start()
    waiter = threading.Thread(target=live.on_train_batch_start, args=(trainer, None), daemon=True)
    waiter.start()  # the training thread, paused: it still renders the tabs' frames
    tab.join(timeout=5)
    assert len(got) == 2 and waiter.is_alive()
    live.control.stop()
    waiter.join(timeout=5)
    live.on_train_batch_end(trainer, None)
    assert stop.requested  # the Ctrl-C path: checkpoint after this step, then RunInterrupted
    live.close()
    with pytest.raises(RuntimeError, match="training has ended"):
        field.timed_render(capture_camera(capture(), 0), 16, ViewSettings())


def test_split_shows_the_source_left_and_the_stylization_right():
    a, b = np.zeros((4, 10, 3), np.uint8), np.full((4, 10, 3), 9, np.uint8)
    out = split_frame(a, b)
    assert out[0, 0, 0] == 0 and out[0, 9, 0] == 9 and (out[:, 4:6] == 255).all()
