"""What the viewer renders: a finished run (with its source, the strength dial and mixes) or the field being
trained. Both answer :meth:`timed_render` (a frame and the seconds it took) for one camera, from any tab's
thread, and hold a ``lock`` that serializes the tabs' frames. ``version`` grows whenever the field itself
changes (a training step), so open tabs render again.

All of a field's torch work runs on ONE thread: a finished run's own render thread, a live run's training
thread (between two steps). Each thread that calls torch's CPU kernels brings its own pool of worker
threads, and two pools on the same cores spin against each other; one thread keeps one pool.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from nerfart_plugin.api import Region, mix, open_run
from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields.compiled import decide_compile, set_compiled, warm_up
from nerfart_plugin.rendering.frames import render_cameras
from nerfart_plugin.viewer.cameras import ViewCamera, render_path

log = logging.getLogger(__name__)

#: the channels the viewer shows (``render.channels`` of stage=render, without ``side``)
VIEW_CHANNELS = ("rgb", "depth", "normal", "opacity")
#: rays per no-grad chunk of a viewer frame at least (fewer, larger chunks render a frame faster on CPU)
VIEW_CHUNK = 16384
#: what a stylization tab shows: the stylized field, its source, or source | stylized split down the middle
VIEW_MODES = ("stylized", "source", "split")


@dataclass(frozen=True)
class ViewSettings:
    """What every tab shows (the panels set it; shared by all tabs).

    Attributes:
        channel: one of :data:`VIEW_CHANNELS`.
        mode: one of :data:`VIEW_MODES` (a reconstruction: always its own field).
        weights: the blend: this run's strength first, then one weight per sibling stylization (0: left out).
        region: the region this run's style applies in (the Region panel's box; None: as the run was trained).
    """

    channel: str = "rgb"
    mode: str = "stylized"
    weights: tuple[float, ...] = (1.0,)
    region: Optional[Region] = None


def render_frame(renderer: Any, cams: CaptureCameras, camera: ViewCamera, long_side: int, channel: str, chunk: int,
                 device: torch.device) -> np.ndarray:
    """One [H,W,3] uint8 frame of ``renderer`` from ``camera`` (world frame) at ``long_side`` pixels."""

    if channel not in VIEW_CHANNELS:
        raise ConfigError(f"channel {channel!r}: the viewer shows one of {', '.join(VIEW_CHANNELS)}.")
    rp = render_path(camera, cams, long_side)
    frames = render_cameras(renderer, rp, ndc=cams.ndc, near=float(cams.near.min()), far=float(cams.far.max()),
                            chunk=chunk, device=device, channels=(channel,), progress=False)
    return frames[channel][0]


def split_frame(left: np.ndarray, right: np.ndarray, line: int = 2) -> np.ndarray:
    """The left half of ``left`` and the right half of ``right`` (same shape [H,W,3]) with a white line."""
    W = left.shape[1]
    out = np.concatenate([left[:, : W // 2], right[:, W // 2:]], axis=1).copy()
    out[:, max(W // 2 - line // 2, 0): W // 2 + (line + 1) // 2] = 255
    return out


class RunField:
    """A finished run (:class:`~nerfart_plugin.api.Run`) and, for a stylization, its source, its strength dial
    and its mixes with ``siblings`` (other stylizations of the same source; opened when first given a weight)."""

    render_share: Optional[float] = None

    def __init__(self, run: Any, siblings: Sequence[Path] = (), compile: str = "off") -> None:
        self.run = run
        self.siblings = list(siblings)
        self.lock = threading.Lock()
        self.version = 0
        self._opened: dict[Path, Any] = {}
        self._source: Any = None
        self._blend: tuple[tuple[Any, ...], Any] = ((1.0,) + (0.0,) * len(self.siblings) + ("",), run.renderer)
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="viewer-render")
        self.compiled = threading.Event()  # set once the field's compiled kernels are ready
        on, self.compile_choice = decide_compile(compile, torch.device(run.device))
        if on:
            threading.Thread(target=self._compile, name="viewer-compile", daemon=True).start()

    def _compile(self) -> None:
        """Compile the run's field in the background (the frames meanwhile are eager), then render compiled."""
        field = self.run.renderer.field
        seconds = warm_up(field, self.run.device) + warm_up(field, self.run.device, with_normal=True)
        self.compiled.set()
        log.info("viewer: the field is compiled (%.0f s); frames from now on use it", seconds)

    def timed_render(self, camera: ViewCamera, long_side: int, settings: ViewSettings) -> tuple[np.ndarray, float]:
        """:meth:`render` on the field's render thread; the frame and its seconds."""
        return self.call(timed, self.render, camera, long_side, settings)

    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` on the field's render thread (any torch work on this run: a video too)."""
        return self._worker.submit(fn, *args, **kwargs).result()

    def close(self) -> None:
        self._worker.shutdown(wait=False, cancel_futures=True)

    @property
    def cameras(self) -> CaptureCameras:
        return self.run.cameras

    @property
    def is_stylization(self) -> bool:
        return self.run.kind == "stylization"

    def renderer(self, settings: ViewSettings) -> Any:
        """The renderer of ``settings.mode`` and ``settings.weights`` (a blend is built once per weights)."""
        if not self.is_stylization:
            return self.run.renderer
        if settings.mode == "source":
            return self.source_renderer
        weights = tuple(settings.weights) + (0.0,) * (1 + len(self.siblings) - len(settings.weights))
        key = weights + (settings.region.content_hash if settings.region is not None else "",)
        if key != self._blend[0]:
            self._blend = (key, self._blended(weights, settings.region))
        return self._blend[1]

    @property
    def source_renderer(self) -> Any:
        """The source field rendered with the stylization's sampling settings (the strength dial at 0), as the
        stylization's own source views are."""
        if self._source is None:

            self._source = mix([self.run], [0.0]).renderer
        return self._source

    def _blended(self, weights: tuple[float, ...], region: Optional[Region] = None) -> Any:
        runs, ws = [self.run if region is None else self.run.with_region(region)], [weights[0]]
        for folder, w in zip(self.siblings, weights[1:]):
            if w != 0.0:
                runs.append(self._sibling(folder))
                ws.append(w)
        return mix(runs, ws).renderer

    def _sibling(self, folder: Path) -> Any:
        if folder not in self._opened:
            log.info("opening %s to mix it", folder)
            self._opened[folder] = open_run(folder, device=str(self.run.device))
        return self._opened[folder]

    def render(self, camera: ViewCamera, long_side: int, settings: ViewSettings) -> np.ndarray:
        """One frame (see :func:`render_frame`) of what ``settings`` select; ``split``: source | stylized."""
        chunk, dev = max(self.run.config.render.chunk, VIEW_CHUNK), self.run.device
        if self.compiled.is_set():  # every field a frame may use (blends and siblings opened later too)
            for renderer in (self.run.renderer, self._source, self.renderer(settings)):
                if renderer is not None:
                    set_compiled(renderer, True)
        if settings.mode == "split" and self.is_stylization:
            left = render_frame(self.source_renderer, self.cameras, camera, long_side, settings.channel, chunk, dev)
            right = render_frame(self.renderer(ViewSettings(settings.channel, "stylized", settings.weights)),
                                 self.cameras, camera, long_side, settings.channel, chunk, dev)
            return split_frame(left, right)
        return render_frame(self.renderer(settings), self.cameras, camera, long_side, settings.channel, chunk, dev)


def timed(fn: Callable[..., np.ndarray], *args: Any) -> tuple[np.ndarray, float]:
    """``fn(*args)`` and the seconds it took."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def sibling_runs(run: Any) -> list[Path]:
    """The other finished stylizations beside ``run`` (its parent folder) that name the same source
    checkpoint: the runs the viewer offers to mix with it (:func:`nerfart_plugin.api.mix` checks content)."""

    if run.kind != "stylization":
        return []
    source = run.metrics.get("source_checkpoint") or run.config.source_checkpoint
    out = []
    for folder in sorted(Path(run.folder).parent.iterdir()):
        if folder.resolve() == Path(run.folder).resolve() or not (folder / "final.ckpt").is_file():
            continue
        try:
            other = json.loads((folder / "metrics.json").read_text()).get("source_checkpoint")
        except (OSError, ValueError):
            continue
        if other and source and Path(other).resolve() == Path(source).resolve():
            out.append(folder)
    return out


class _Request:
    """One frame asked of the training thread by a tab's thread."""

    def __init__(self, fn: Callable[[], tuple[np.ndarray, float]]) -> None:
        self.fn, self.done = fn, threading.Event()
        self.value: Optional[tuple[np.ndarray, float]] = None
        self.error: Optional[BaseException] = None

    def run(self) -> None:
        try:
            self.value = self.fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the tab's thread
            self.error = exc
        self.done.set()


class LiveField:
    """The field a training run is fitting (its system's renderer). A tab's frame is a request that the training
    thread renders between two steps (:meth:`serve`, called by :class:`~nerfart_plugin.viewer.live.LiveViewer`);
    ``render_share`` caps the share of wall time frames may take (the tab waits between frames)."""

    def __init__(self, system: Any, cameras: CaptureCameras, render_share: float, chunk: int) -> None:
        self.system, self._cameras = system, cameras
        self.render_share, self.chunk = render_share, chunk
        self.lock = threading.Lock()
        self.version = 0
        self._requests: "queue.Queue[_Request]" = queue.Queue()
        self._closed = threading.Event()

    @property
    def cameras(self) -> CaptureCameras:
        return self._cameras

    @property
    def is_stylization(self) -> bool:
        return getattr(self.system, "source", None) is not None

    def timed_render(self, camera: ViewCamera, long_side: int, settings: ViewSettings) -> tuple[np.ndarray, float]:
        """Ask the training thread for a frame and wait for it (RuntimeError once the training has ended)."""
        if self._closed.is_set():
            raise RuntimeError("the training has ended")
        request = _Request(lambda: timed(self.render, camera, long_side, settings))
        self._requests.put(request)
        while not request.done.wait(0.1):
            if self._closed.is_set():
                raise RuntimeError("the training has ended")
        if request.error is not None:
            raise request.error
        assert request.value is not None
        return request.value

    def serve(self) -> int:
        """Render the frames the tabs asked for (on the calling thread: the training's); how many."""
        n = 0
        while True:
            try:
                request = self._requests.get_nowait()
            except queue.Empty:
                return n
            request.run()
            n += 1

    def close(self) -> None:
        self._closed.set()

    @property
    def closed(self) -> bool:
        """The training has ended: no more frames."""
        return self._closed.is_set()

    def render(self, camera: ViewCamera, long_side: int, settings: ViewSettings) -> np.ndarray:
        dev = self.system.device
        live = self.system.renderer
        if not self.is_stylization or settings.mode == "stylized":
            return render_frame(live, self.cameras, camera, long_side, settings.channel, self.chunk, dev)
        source = render_frame(self.system.source, self.cameras, camera, long_side, settings.channel, self.chunk, dev)
        if settings.mode == "source":
            return source
        return split_frame(source, render_frame(live, self.cameras, camera, long_side, settings.channel, self.chunk,
                                                dev))
