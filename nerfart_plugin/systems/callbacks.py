"""Callbacks shared by both stages: atomic checkpoints, Ctrl-C at a step boundary, a finite-value guard, the
projected time of a fit."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Optional

import lightning as L
import torch

from nerfart_plugin.errors import TrainingDivergedError
from nerfart_plugin.utils.io import atomic_path

log = logging.getLogger(__name__)

LAST = "last.ckpt"


class _NoSaveDefaultNote(logging.Filter):
    """Drop Lightning's "`weights_only` was not set, defaulting to `False`" note, logged at every
    ``save_checkpoint``: there the flag means "save only the weights" (we save the full, resumable state
    on purpose); it has nothing to do with how checkpoints are loaded (always ``weights_only=True``)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "`weights_only` was not set" not in record.getMessage()


logging.getLogger("lightning.pytorch.trainer.connectors.checkpoint_connector").addFilter(_NoSaveDefaultNote())


class AtomicCheckpoint(L.Callback):
    """Write ``<dirpath>/last.ckpt`` every ``every_n_steps`` optimizer steps, atomically.

    Lightning's own writer truncates the target before writing it; here the
    checkpoint goes to a temporary file in the same folder and is renamed over
    the previous one, so a run killed at any moment (SIGKILL included) leaves
    the last complete checkpoint readable.
    """

    def __init__(self, dirpath: str | Path, every_n_steps: int) -> None:
        self.dirpath = Path(dirpath)
        self.every_n_steps = max(1, int(every_n_steps))
        self.last_saved = -1

    def save(self, trainer: L.Trainer) -> Path:
        path = self.dirpath / LAST
        if trainer.world_size == 1:
            with atomic_path(path) as tmp:
                trainer.save_checkpoint(tmp)  # full state (optimizer, loops): resumable
        else:  # DDP: every rank joins save_checkpoint (rank 0 writes), rank 0 renames
            tmp = self.dirpath / f".{LAST}.step{trainer.global_step}.tmp"
            trainer.save_checkpoint(tmp)  # full state (optimizer, loops): resumable
            if trainer.is_global_zero:
                os.replace(tmp, path)
            trainer.strategy.barrier("atomic_checkpoint")
        self.last_saved = trainer.global_step
        log.debug("checkpoint at step %d -> %s", trainer.global_step, path)
        return path

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        step = trainer.global_step
        if step > 0 and step % self.every_n_steps == 0 and step != self.last_saved:
            self.save(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_step != self.last_saved and not trainer.interrupted:
            self.save(trainer)


class GracefulInterrupt(L.Callback):
    """Ctrl-C (SIGINT) or SIGTERM during training stops at the end of the current step with ``last.ckpt`` written.

    Lightning turns a KeyboardInterrupt inside ``fit`` into an interrupted run (and, in 2.6,
    ``sys.exit(1)``), mid-step; its own SIGTERM handler broadcasts from inside the signal handler, which
    leaves multi-process (DDP) ranks waiting on each other for good. Instead the first signal only sets
    :attr:`requested`; after the step in progress every rank agrees to stop (one reduction), the
    checkpoint is written and training stops, so the run resumes exactly where it stopped. A second
    signal stops at once (the last periodic checkpoint is kept). The pipeline then reports the
    interruption (exit code 130).
    """

    #: the signals that stop a run gracefully (a scheduler's or ``timeout``'s SIGTERM, as Ctrl-C)
    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, checkpoint: AtomicCheckpoint) -> None:
        self.checkpoint = checkpoint
        self.requested = False
        self.stopped_at: int | None = None
        self._previous: dict[int, Any] = {}

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        log.warning("%s: stopping after this step with a checkpoint (a second one stops at once)", name)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if threading.current_thread() is threading.main_thread():
            self._previous = {int(sig): signal.signal(sig, self._on_signal) for sig in self.SIGNALS}

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        requested = self.requested
        if trainer.world_size > 1:  # every rank stops at the same step
            requested = trainer.strategy.reduce_boolean_decision(requested, all=False)
        if requested and not trainer.should_stop:
            if self.checkpoint.last_saved != trainer.global_step:
                self.checkpoint.save(trainer)
            self.stopped_at = trainer.global_step
            trainer.should_stop = True

    def _restore(self) -> None:
        if self._previous and threading.current_thread() is threading.main_thread():
            for sig, handler in self._previous.items():
                signal.signal(sig, handler)
            self._previous = {}

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._restore()


class FiniteGradientGuard(L.Callback):
    """Stop with a diagnostic when a gradient becomes NaN/inf (the last good checkpoint is kept)."""

    def on_before_optimizer_step(self, trainer: L.Trainer, pl_module: L.LightningModule, optimizer: Any) -> None:
        check_finite_grads(pl_module, trainer.global_step)


def check_finite_grads(module: torch.nn.Module, step: int) -> None:
    """Raise TrainingDivergedError naming the parameters whose gradient is not finite."""
    bad = [n for n, p in module.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
    if bad:
        raise TrainingDivergedError(
            f"non-finite gradient at step {step} in {len(bad)} parameter(s), e.g. {bad[:3]}. The last good "
            "checkpoint is kept. Try a lower learning rate (reconstruct.lr / stylize.lr) or float32 precision."
        )


def check_finite_losses(terms: dict[str, torch.Tensor], step: int, stage: str) -> None:
    """Raise TrainingDivergedError naming the loss terms that are not finite."""
    bad = {k: float(v.detach()) for k, v in terms.items() if not torch.isfinite(v.detach()).all()}
    if bad:
        raise TrainingDivergedError(
            f"{stage}: non-finite loss at step {step}: {bad}. The last good checkpoint is kept; lower the "
            f"learning rate or the weight (lambda_*) of the term(s) {sorted(bad)}."
        )


class ProjectedTime(L.Callback):
    """Says early how long the whole fit will take: after ``probe_steps`` steps (past the first, which
    warms up), a WARNING when the projection at the measured pace passes ``warn_seconds``, naming what
    makes it shorter; an INFO line otherwise. Nothing is stopped: the user decides."""

    def __init__(self, what: str, probe_steps: int = 3, warn_seconds: float = 3600.0) -> None:
        self.what, self.probe_steps, self.warn_seconds = what, int(probe_steps), float(warn_seconds)
        self._t0: Optional[float] = None
        self._start = 0
        self.projected_s: Optional[float] = None

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        step = int(trainer.global_step)
        if self.projected_s is not None or not trainer.is_global_zero:
            return
        if self._t0 is None:  # the first step (or the first after a resume) warms up: start the clock after it
            self._t0, self._start = time.perf_counter(), step
            return
        done = step - self._start
        if done < self.probe_steps:
            return
        per_step = (time.perf_counter() - self._t0) / done
        left = max(0, int(trainer.max_steps) - step)
        self.projected_s = per_step * left
        device = pl_module.device.type
        text = (f"{self.what}: {per_step:.2f} s/step on {device}, so the {left} steps left take about "
                f"{format_duration(self.projected_s)}")
        if self.projected_s > self.warn_seconds:
            log.warning("%s. Shorter: a lighter preset (preset=balanced or preset=draft), fewer steps, or a GPU "
                        "(device=cuda); Ctrl-C stops with a checkpoint that the same command resumes.", text)
        else:
            log.info("%s.", text)


def format_duration(seconds: float) -> str:
    """``42 s``, ``12 min``, ``3.4 h``, ``90 days``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.0f} days"
