"""The web viewer in a real browser (headless Chromium through Playwright) on trained runs, and the fields it
renders. Without a Chromium the browser tests skip with the reason; CI sets NERFART_REQUIRE_BROWSER=1, so
there they fail instead of skipping.

``NERFART_VIEWER_SCREENSHOT=path.png`` keeps the page's screenshot (the documentation's comes from
``python -m benchmarks viewer``, which drives the same browser)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
from pipeline_helpers import tiny_cfg

from nerfart_plugin.data.datamodule import DEFAULT_SCENE

pytestmark = pytest.mark.slow

#: the toy stylizations of test_blend.py (the same settings, so the session's run cache serves both)
STYLE = ["guidance=toy", "reconstruct.steps=20", "stylize.steps=4", "stylize.lr=0.01", "export.enabled=false"]


@pytest.fixture(scope="module")
def styles(shared_runs) -> dict[str, Path]:
    from nerfart_plugin.run.pipeline import run

    return {name: Path(run(tiny_cfg(shared_runs, DEFAULT_SCENE, *STYLE, f"prompt={name}"))["stylization"]["dir"])
            for name in ("red", "blue")}


@pytest.fixture(scope="module")
def chromium() -> None:
    from nerfart_plugin.viewer.browser import missing_browser

    why = missing_browser()
    if why:
        if os.environ.get("NERFART_REQUIRE_BROWSER"):
            pytest.fail(f"NERFART_REQUIRE_BROWSER is set but {why}")
        pytest.skip(why)


# ---------------------------------------------------------------------- the fields, without a browser
def test_the_run_field_renders_the_run_its_source_blends_and_splits(styles):
    from nerfart_plugin.api import mix, open_run
    from nerfart_plugin.viewer.cameras import capture_camera
    from nerfart_plugin.viewer.sources import RunField, ViewSettings, render_frame, sibling_runs

    run = open_run(styles["red"], device="cpu")
    assert styles["blue"] in sibling_runs(run)
    field = RunField(run, [styles["blue"]])
    cam = capture_camera(run.cameras, 2)
    chunk, dev = run.config.render.chunk, run.device
    as_trained = field.render(cam, 24, ViewSettings())
    np.testing.assert_array_equal(as_trained, render_frame(run.renderer, run.cameras, cam, 24, "rgb", chunk, dev))
    source = field.render(cam, 24, ViewSettings(mode="source"))
    np.testing.assert_array_equal(field.render(cam, 24, ViewSettings(weights=(0.0,))), source)  # s = 0: the source
    half = field.render(cam, 24, ViewSettings(weights=(0.5, 0.5)))
    blue = open_run(styles["blue"], device="cpu")
    np.testing.assert_array_equal(half, render_frame(mix([run, blue], [0.5, 0.5]).renderer, run.cameras, cam, 24,
                                                     "rgb", chunk, dev))
    split = field.render(cam, 24, ViewSettings(mode="split"))
    W = split.shape[1]
    np.testing.assert_array_equal(split[:, : W // 2 - 1], source[:, : W // 2 - 1])
    np.testing.assert_array_equal(split[:, W // 2 + 1:], as_trained[:, W // 2 + 1:])
    for channel in ("depth", "normal", "opacity"):
        img = field.render(cam, 24, ViewSettings(channel=channel))
        assert img.shape == as_trained.shape and img.dtype == np.uint8


def test_the_viewer_cli_refuses_a_missing_run_without_a_traceback(tmp_path):
    import subprocess
    import sys

    from pipeline_helpers import cli_env

    proc = subprocess.run([sys.executable, "-m", "nerfart_plugin.viewer", str(tmp_path / "nope")], env=cli_env(),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "error:" in proc.stderr and "Traceback" not in proc.stderr
    assert "nope" in proc.stderr


@pytest.mark.slow
def test_the_viewer_cli_says_which_port_it_took_when_the_asked_one_is_taken(styles):
    import socket
    import subprocess
    import sys

    from pipeline_helpers import cli_env

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = subprocess.Popen([sys.executable, "-m", "nerfart_plugin.viewer", str(styles["red"]), "--port", str(port),
                                 "--device", "cpu"], env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True)
        try:
            lines = []
            for line in proc.stdout:
                lines.append(line)
                if "in a browser" in line:
                    break
        finally:
            proc.kill()
            proc.wait(timeout=30)
    text = "".join(lines)
    assert f"port {port} is taken: serving on port" in text, text[-2000:]


def test_the_viewer_compiles_in_the_background_and_its_frames_stay_the_same(styles):
    """compile=on: frames are served (eager) while the field compiles on another thread; once it is ready the
    frames come from the compiled field and equal the eager ones (8-bit rounding)."""
    import torch

    from nerfart_plugin.api import open_run
    from nerfart_plugin.fields.compiled import compiler_missing
    from nerfart_plugin.viewer.browser import wait_for
    from nerfart_plugin.viewer.cameras import capture_camera
    from nerfart_plugin.viewer.sources import RunField, ViewSettings

    if compiler_missing(torch.device("cpu")):
        pytest.skip(compiler_missing(torch.device("cpu")))
    eager = RunField(open_run(styles["red"], device="cpu"))
    assert not eager.compiled.is_set() and eager.compile_choice == "off"
    field = RunField(open_run(styles["red"], device="cpu"), compile="on")
    cam = capture_camera(field.cameras, 1)
    reference = eager.render(cam, 32, ViewSettings())
    field.render(cam, 32, ViewSettings())  # served while the compile runs
    assert wait_for(field.compiled.is_set, 240), "the background compile did not finish"
    compiled = field.render(cam, 32, ViewSettings())
    assert field.run.renderer.field.compiled
    assert np.abs(compiled.astype(int) - reference.astype(int)).max() <= 1


# ---------------------------------------------------------------------- in the browser
@pytest.fixture(scope="module")
def page(styles, chromium):
    from nerfart_plugin.viewer import open_viewer
    from nerfart_plugin.viewer.browser import BrowserPage, wait_for

    viewer = open_viewer(styles["red"], port=0, device="cpu")
    try:
        with BrowserPage(viewer.url, size=(1000, 700)) as page:
            assert wait_for(lambda: len(viewer.tabs) == 1 and next(iter(viewer.tabs.values())).frames >= 1, 60), \
                "the page did not connect and receive a frame"
            page.viewer = viewer
            page.tab = next(iter(viewer.tabs.values()))
            yield page
    finally:
        viewer.stop()


def settle(page, timeout: float = 30.0) -> np.ndarray:
    """Wait until the tab's frames stop changing (the finest has arrived); the last frame."""
    from nerfart_plugin.viewer.browser import wait_for

    def rested() -> bool:
        n = page.tab.frames
        wait_for(lambda: page.tab.frames > n, 0.6)
        return page.tab.frames == n and page.tab.schedule.finished

    wait_for(rested, timeout, every=0.0)
    return page.tab.last_frame.copy()


def view_region(shot: np.ndarray) -> np.ndarray:
    """The part of a page screenshot left of the panel (the 3D view)."""
    return shot[:, : shot.shape[1] // 2]


def covered(frame: np.ndarray) -> float:
    """The share of a frame's pixels that are not the white background."""
    return float((frame.astype(int).sum(-1) < 3 * 235).mean())


def test_the_page_opens_on_the_front_camera_and_draws_the_scene(page):
    # a new tab reports the browser's default camera first: the viewer must not show that view
    front = page.viewer.front.c2w[:, 3]
    np.testing.assert_allclose(page.tab.first_camera.c2w[:, 3], front, atol=1e-3)
    frame = settle(page)
    np.testing.assert_allclose(page.tab.camera.c2w[:, 3], front, atol=1e-3)
    assert 0.02 < covered(frame) < 0.98, f"the frame is blank or flat ({covered(frame):.0%} covered)"
    shot = page.screenshot(Path(os.environ["NERFART_VIEWER_SCREENSHOT"]) if os.environ.get(
        "NERFART_VIEWER_SCREENSHOT") else None)
    assert view_region(shot).std() > 10  # the browser drew the frame, not an empty page


def test_moving_the_camera_changes_the_frame(page):
    before, shot = settle(page), view_region(page.screenshot())
    n = page.tab.frames
    page.drag(160, 20)
    assert settle(page) is not None and page.tab.frames > n
    after = page.tab.last_frame
    assert before.shape != after.shape or np.abs(before.astype(int) - after.astype(int)).mean() > 1.0
    assert np.abs(view_region(page.screenshot()).astype(int) - shot.astype(int)).mean() > 1.0


def test_moving_the_strength_dial_changes_the_frame(page):
    before = settle(page)
    page.slider_key("Strength", "Home")  # the dial to 0: the source
    from nerfart_plugin.viewer.browser import wait_for

    assert wait_for(lambda: page.viewer.settings.weights[0] == 0.0, 10), page.viewer.settings
    after = settle(page)
    assert np.abs(before.astype(int) - after.astype(int)).max() > 0
    page.slider_key("Strength", "End")
    assert wait_for(lambda: page.viewer.settings.weights[0] == 2.0, 10)
    page.slider_key("Strength", "ArrowLeft", times=20)  # back to 1, step 0.05
    assert wait_for(lambda: page.viewer.settings.weights[0] == pytest.approx(1.0), 10)


def test_a_region_box_is_drawn_applied_and_saved(page, styles):
    """The Region panel: the box shows with its gizmo, "inside the box only" renders the composite (the frame
    changes), and "Save region" writes the box that Region.load reads back."""
    from nerfart_plugin.api import Region
    from nerfart_plugin.viewer.browser import wait_for

    panel = page.viewer.panels["region"]
    before = settle(page)
    page.check("Show the region box")
    assert wait_for(lambda: panel.gizmo.visible and panel.box.visible, 10)
    page.check("Style inside the box only")
    assert wait_for(lambda: page.viewer.settings.region is not None, 10)
    after = settle(page)
    assert np.abs(before.astype(int) - after.astype(int)).max() > 0  # the source shows outside the box
    page.click("Save region")
    assert wait_for(lambda: bool(list((styles["red"] / "regions").glob("region-*.npz"))), 10)
    saved = Region.load(next((styles["red"] / "regions").glob("region-*.npz")))
    assert saved.content_hash == panel.region().content_hash and "region.box=[" in panel.note.content
    page.check("Style inside the box only")
    assert wait_for(lambda: page.viewer.settings.region is None, 10)


def test_each_tab_keeps_its_own_camera_and_a_closed_tab_is_dropped(page):
    from nerfart_plugin.viewer.browser import wait_for

    first = page.tab
    with page.new_tab(size=(800, 600)) as other:
        assert wait_for(lambda: len(page.viewer.tabs) == 2, 60)
        second = next(t for t in page.viewer.tabs.values() if t is not first)
        assert wait_for(lambda: second.frames >= 1, 60)
        mine, theirs = first._camera.key(), second._camera.key()
        other.drag(200, 0)
        assert wait_for(lambda: second._camera.key() != theirs, 10)
        assert first._camera.key() == mine
    assert wait_for(lambda: len(page.viewer.tabs) == 1 and not second.alive, 60)  # its job ends with its frame


def test_a_keyframe_path_saves_a_camera_path_that_stage_render_renders(page, styles, tmp_path):
    from nerfart_plugin.run.pipeline import run
    from nerfart_plugin.viewer.browser import wait_for

    page.open_folder("Camera path")
    page.click("Add keyframe")
    page.drag(-120, 0)
    settle(page)
    page.click("Add keyframe")
    assert wait_for(lambda: len(page.viewer.keyframes) == 2, 10)
    page.fill_number("Frames", "3")
    page.fill_number("Resolution", "24")
    assert wait_for(lambda: int(page.viewer.path_editor.frames.value) == 3, 10)
    page.click("Save camera_path.json")
    saved = styles["red"] / "render" / "camera_paths" / "viewer_path.json"
    assert wait_for(saved.is_file, 10)
    out = run(tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=render", f"render.run={styles['red']}",
                       f"render.path={saved}", "guidance=toy"))
    video = Path(out["render"]["files"]["rgb"])
    assert video.is_file() and video.parent.parent == styles["red"] / "render"


def test_a_training_run_is_watched_paused_and_stopped_from_the_browser(page, tmp_path, monkeypatch):
    """viewer.live=true: the page shows the field being trained; Pause holds the steps; Stop and save ends the
    run through the Ctrl-C path (last.ckpt, RunInterrupted naming how to resume)."""
    import threading

    from nerfart_plugin.errors import RunInterrupted
    from nerfart_plugin.run.pipeline import run
    from nerfart_plugin.viewer import live
    from nerfart_plugin.viewer.browser import wait_for

    started: list = []
    original = live.LiveViewer.start

    def start(self, system):
        viewer = original(self, system)
        started.append((self, viewer))
        return viewer

    monkeypatch.setattr(live.LiveViewer, "start", start)
    outcome: dict = {}

    def train() -> None:
        try:
            outcome["result"] = run(tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=reconstruct", "reconstruct.steps=100000",
                                             "reconstruct.checkpoint_every=100000", "viewer.live=true",
                                             "viewer.port=0", "viewer.render_share=0.5"), live=live.live_viewer)
        except RunInterrupted as exc:
            outcome["interrupted"] = str(exc)

    worker = threading.Thread(target=train, daemon=True)
    worker.start()
    assert wait_for(lambda: bool(started), 120), "the live viewer did not start"
    callback, viewer = started[0]
    with page.new_tab(viewer.url) as watching:
        assert wait_for(lambda: viewer.tabs and next(iter(viewer.tabs.values())).frames >= 2, 60)
        tab = next(iter(viewer.tabs.values()))
        # the field being trained appears (an untrained field renders the white background at first)
        assert wait_for(lambda: tab.last_frame is not None and tab.last_frame.std() > 1.0, 90)
        watching.click("Pause")
        assert wait_for(lambda: callback.control.paused, 10)
        time.sleep(0.5)
        step = viewer.field.version
        time.sleep(1.5)
        assert viewer.field.version == step  # no training step while paused
        watching.click("Resume")
        assert wait_for(lambda: viewer.field.version > step, 20)
        watching.click("Stop and save")
        worker.join(timeout=120)
    assert not worker.is_alive() and "interrupted" in outcome, outcome
    assert "run the same command again to resume" in outcome["interrupted"]
    assert list((tmp_path / "reconstructions").glob("*/last.ckpt"))
