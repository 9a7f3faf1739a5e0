"""Watch a run train: ``viewer.live=true`` on a training command starts the viewer on the field being fitted.

:class:`TrainingControl` is what the viewer and the trainer share: pause / resume, and stop-and-save (the same
path as Ctrl-C: ``last.ckpt`` written after the step, the run resumes where it stopped when the command
is run again). :class:`LiveViewer` is the Lightning callback that serves the viewer while the fit runs, renders
the frames the tabs ask for between two steps, on the training thread, and shows the logged readouts
(loss, PSNR, seconds per step) and, for a stylization whose prompt names an ImageNet class, the independent
judge's verdict on the view the browser shows (:class:`LiveJudge`).
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
import numpy as np
import torch

from nerfart_plugin.objectives.evaluation import judge_for
from nerfart_plugin.run.stages.base import LiveTarget
from nerfart_plugin.systems.callbacks import GracefulInterrupt
from nerfart_plugin.viewer import panels
from nerfart_plugin.viewer.panels import thumbnails
from nerfart_plugin.viewer.path_editor import PathEditor
from nerfart_plugin.viewer.server import Viewer
from nerfart_plugin.viewer.sources import LiveField

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


class LiveJudge:
    """The independent judge (:class:`~nerfart_plugin.objectives.evaluation.ImageNetJudge`) on the frame a tab shows, during a
    stylization: the same network and class as the run's final ``judge`` block, on the current field.

    Args:
        prompt: the stylization's prompt as typed; the judge runs when it names an ImageNet class.
        render_share: the share of wall time the viewer may take; judging waits so that it keeps to it.
    """

    #: the least time between two verdicts (seconds)
    EVERY_S = 5.0

    def __init__(self, prompt: str, render_share: float = 0.1) -> None:
        self.judge, self.target, self.skipped = judge_for(prompt)
        self.render_share = render_share
        self.text = f"judge: not run ({self.skipped})" if self.judge is None else "judge: waiting for a still view"
        self._judged: tuple[int, int] = (-1, -1)  # (tab, frame count) last judged
        self._next = 0.0

    def due(self, tab_id: int, frames: int) -> bool:
        """Whether to judge the ``frames``-th frame of tab ``tab_id`` now (a new still frame, time to spare)."""
        return self.judge is not None and (tab_id, frames) != self._judged and time.perf_counter() >= self._next

    def assess(self, frame: np.ndarray, tab_id: int, frames: int, step: int, device: torch.device) -> str:
        """Judge ``frame`` ([H,W,3] uint8, the tab's latest) and return the readout's markdown line."""
        assert self.judge is not None
        t0 = time.perf_counter()
        image = torch.from_numpy(np.ascontiguousarray(frame)).to(device).permute(2, 0, 1)[None].float() / 255.0
        view = self.judge.assess(image, self.target)["per_view"][0]
        seconds = time.perf_counter() - t0
        self._judged = (tab_id, frames)
        self._next = time.perf_counter() + max(self.EVERY_S, seconds / max(self.render_share, 1e-3))
        name = self.judge.classes.name(self.target)
        self.text = (f"judge ({self.judge.model}) on this view at step {step}: P({name}) {view['target_prob']:.3f}, "
                     f"rank {view['target_rank'] + 1}; top-1 {view['top1']}")
        return self.text


class LiveViewer(L.Callback):
    """Serves the viewer on the field a fit is training (see the module docstring).

    Args:
        cameras: the capture's cameras (:class:`~nerfart_plugin.cameras.capture.CaptureCameras`).
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
        self.judge: Optional[LiveJudge] = None
        self._last_readout = 0.0

    # ---- Lightning hooks
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_rank != 0:
            return
        self.viewer = self.start(pl_module)
        prompt = getattr(pl_module, "raw_prompt", None)  # a stylization's prompt as typed
        if prompt:
            self.judge = LiveJudge(prompt, self.render_share)
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
            text = readouts(dict(trainer.callback_metrics), trainer.global_step, self.control.paused,
                            self.control.stop_requested)
            if self.judge is not None:
                text += "\n\n" + self._judge_view(trainer.global_step, pl_module)
            self.viewer.panels["training"]["readouts"].content = text

    def _judge_view(self, step: int, pl_module: Any) -> str:
        """The judge's line: a new verdict when a tab shows a new still frame and the time share allows."""
        assert self.judge is not None
        settings = self.viewer.settings
        if self.judge.judge is not None and (settings.mode, settings.channel) != ("stylized", "rgb"):
            return "judge: shown for the stylized rgb view"
        for tab_id, tab in list(self.viewer.tabs.items()):
            frame = tab.last_frame
            if frame is not None and tab.schedule.finished and self.judge.due(tab_id, tab.frames):
                device = getattr(pl_module, "device", torch.device("cpu"))
                return self.judge.assess(frame, tab_id, tab.frames, step, device)
        return self.judge.text

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.close()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self.close()

    # ---- parts
    def start(self, system: Any) -> Any:
        field = LiveField(system, self.cameras, self.render_share, self.chunk)
        viewer = Viewer(field, host=self.host, port=self.port,
                        writable=None if self.folder is None else Path(self.folder) / "render",
                        title=f"nerfart_plugin: {self.title}")
        viewer.panels["training"] = add_training_panel(viewer, self.control)
        viewer.panels["view"] = panels.add_view_panel(viewer, field.is_stylization)
        viewer.path_editor = PathEditor(viewer, None)
        capture = panels.CaptureFrustums(viewer)
        if self.photos is not None:
            capture.set_photos(self.photos)
        return viewer

    def _request_stop(self, trainer: L.Trainer) -> None:
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


def live_viewer(target: LiveTarget) -> LiveViewer:
    """The live viewer of a training stage (what ``viewer.live=true`` hands the stage: its
    :data:`~nerfart_plugin.run.stages.base.LiveViewerFactory`)."""
    vc = target.settings
    return LiveViewer(target.cameras, host=vc.host, port=vc.port, render_share=vc.render_share, chunk=target.chunk,
                      folder=target.folder, title=target.title, photos=thumbnails(target.photos))
