"""Watch a run train: ``viewer.live=true`` on a training command starts the viewer on the field being fitted.

:class:`TrainingControl` is what the viewer and the trainer share: pause / resume, and stop-and-save (the same
path as Ctrl-C: ``last.ckpt`` written after the step, the run resumes where it stopped when the command
is run again). :class:`LiveViewer` is the Lightning callback that serves the viewer while the fit runs, renders
the frames the tabs ask for between two steps, on the training thread, and shows the logged readouts
(loss, PSNR, seconds per step).
Frames take at most ``viewer.render_share`` of the wall time (the tab waits between frames), which bounds
what watching costs the training.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

import lightning as L

log = logging.getLogger(__name__)

#: the logged values the training panel shows, in this order (those the system logs)
READOUTS = ("train/loss", "train/psnr", "train/loss_dir", "step_s", "rays_s")


class TrainingControl:
    """Pause, resume and stop, shared by the viewer's buttons and the trainer (thread-safe)."""


    def __init__(self) -> None:
        self._running = threading.Event()
        self._running.set()
        self.stop_requested = False

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def stop(self) -> None:
        """Stop after the step in progress, with ``last.ckpt`` written (resumable)."""
        self.stop_requested = True
        self._running.set()

    def wait_while_paused(self, serve: Callable[[], Any] = lambda: None) -> None:
        """Return when not paused; meanwhile call ``serve`` (the viewer's frames) every 50 ms."""
        while not self._running.wait(timeout=0.05):
            serve()


def readouts(metrics: dict[str, Any], step: int, paused: bool, stop: bool) -> str:
    """The training panel's markdown: the step, the state and the logged values of :data:`READOUTS`."""
    state = "stopping after this step (last.ckpt)" if stop else ("paused" if paused else "training")
    lines = [f"step **{step}** — {state}"]
    for key in READOUTS:
        if key in metrics:
            value = float(metrics[key])
            lines.append(f"{key}: {value:.4g}")
    return "\n\n".join(lines)


class LiveViewer(L.Callback):
    """Serves the viewer on the field a fit is training (see the module docstring).

    Args:
        cameras: the capture's cameras (:class:`~nerfart_plugin.data.camera_path.CaptureCameras`).
        host / port: where to serve; render_share: the share of wall time frames may take.
        chunk: rays per no-grad chunk of a frame; folder: the run folder (camera paths are saved under
            ``<folder>/render``); photos: the capture's photos as thumbnails for the frustums.
    """

    def __init__(self, cameras: Any, host: str = "127.0.0.1", port: int = 8080, render_share: float = 0.1,
                 chunk: int = 8192, folder: Optional[Path] = None, title: str = "training",
                 photos: Optional[list] = None) -> None:
        self.cameras, self.host, self.port, self.photos = cameras, host, port, photos
        self.render_share, self.chunk, self.folder, self.title = render_share, chunk, folder, title
        self.control = TrainingControl()
        self.viewer: Any = None
        self._last_readout = 0.0

    # ---- Lightning hooks
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_rank != 0:
            return
        self.viewer = self.start(pl_module)
        log.info("live viewer: open %s in a browser to watch the training (pause / stop in its panel)",
                 self.viewer.url)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        if self.viewer is not None:
            self.control.wait_while_paused(self.viewer.field.serve)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        if self.viewer is None:
            return
        self.viewer.field.version += 1
        self.viewer.field.serve()  # the frames the tabs asked for, between two steps
        if self.control.stop_requested:
            self._request_stop(trainer)
        now = time.perf_counter()
        if now - self._last_readout > 1.0:
            self._last_readout = now
            self.viewer.panels["training"]["readouts"].content = readouts(
                dict(trainer.callback_metrics), trainer.global_step, self.control.paused, self.control.stop_requested)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.close()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self.close()

    # ---- parts
    def start(self, system: Any) -> Any:
        from nerfart_plugin.viewer import panels
        from nerfart_plugin.viewer.fields import LiveField
        from nerfart_plugin.viewer.path_editor import PathEditor
        from nerfart_plugin.viewer.server import Viewer

        field = LiveField(system, self.cameras, self.render_share, self.chunk)
        viewer = Viewer(field, host=self.host, port=self.port,
                        writable=None if self.folder is None else Path(self.folder) / "render",
                        title=f"nerfart_plugin: {self.title}")
        viewer.panels["training"] = add_training_panel(viewer, self.control)
        viewer.panels["view"] = panels.add_view_panel(viewer, field.is_stylization)
        viewer.path_editor = PathEditor(viewer, None)
        capture = panels.CaptureCameras(viewer)
        if self.photos is not None:
            capture.set_photos(self.photos)
        return viewer

    def _request_stop(self, trainer: L.Trainer) -> None:
        from nerfart_plugin.systems.callbacks import GracefulInterrupt

        stops = [cb for cb in trainer.callbacks if isinstance(cb, GracefulInterrupt)]
        if stops:  # the run's Ctrl-C path: checkpoint, then RunInterrupted naming how to resume
            stops[0].requested = True
        else:
            trainer.should_stop = True

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.field.close()
            self.viewer.stop()
            self.viewer = None


def add_training_panel(viewer: Any, control: TrainingControl) -> dict[str, Any]:
    """Pause / resume / stop-and-save buttons and the readouts of a live run."""
    gui = viewer.server.gui
    with gui.add_folder("Training"):
        out = {"readouts": gui.add_markdown("waiting for the first step"),
               "pause": gui.add_button("Pause", hint="hold the training after this step (frames refine meanwhile)"),
               "resume": gui.add_button("Resume", visible=False),
               "stop": gui.add_button("Stop and save", color="red",
                                      hint="stop after this step with last.ckpt written; run the same command "
                                           "again to resume")}

    def pause(_: Any) -> None:
        control.pause()
        out["pause"].visible, out["resume"].visible = False, True
        out["readouts"].content = out["readouts"].content.replace("— training", "— paused")

    def resume(_: Any) -> None:
        control.resume()
        out["pause"].visible, out["resume"].visible = True, False
        out["readouts"].content = out["readouts"].content.replace("— paused", "— training")

    out["pause"].on_click(pause)
    out["resume"].on_click(resume)
    out["stop"].on_click(lambda _: control.stop())
    return out
