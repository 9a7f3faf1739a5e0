"""The one fit skeleton both training stages share, and the Trainer they (and the benchmarks) use.

:func:`fit_stage` trains a system in its run folder: atomic ``last.ckpt`` every
``checkpoint_every`` steps (:class:`~nerfart_plugin.systems.callbacks.AtomicCheckpoint`),
a graceful Ctrl-C (:class:`~nerfart_plugin.systems.callbacks.GracefulInterrupt`: the step
finishes, ``last.ckpt`` is written, :class:`~nerfart_plugin.errors.RunInterrupted` says how
to resume), resume from a ``last.ckpt`` that fits, an out-of-memory error translated into
the settings to lower, and checkpoints read with ``weights_only=True``.
:func:`stage_final` saves the final state on every rank (a collective under DDP) and :func:`publish_final`
renames it to ``final.ckpt`` on rank 0 once the stage's outputs are written.
:func:`train_steps` is the same Trainer without a run folder (benchmarks, experiments).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import lightning as L
import torch

from nerfart_plugin.config.schema import TrainerConfig
from nerfart_plugin.config.validate import section
from nerfart_plugin.errors import NerfArtError, RunInterrupted
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.systems.base import steps_loader
from nerfart_plugin.systems.callbacks import AtomicCheckpoint, GracefulInterrupt, ProjectedTime
from nerfart_plugin.systems.checkpoints import allow_project_types, write_checkpoint_hash
from nerfart_plugin.systems.loggers import build_loggers

log = logging.getLogger("nerfart_plugin")

OOM_HINT = ("out of memory. With stylize.backprop=retain, set stylize.backprop=patch (it keeps the graph of a "
            "whole view). Else lower one of: render.chunk (rays per no-grad chunk of evaluation), stylize.chunk (rays "
            "per no-grad chunk while stylizing), stylize.patch_size (rays per patch re-rendered with grad), "
            "stylize.resolution, reconstruct.batch_rays, render.num_samples, stylize.num_samples, export.chunk.")


def build_trainer(max_steps: int, device: torch.device, trainer_cfg: TrainerConfig | dict, callbacks: Sequence[Any] = (),
                  run_dir: Optional[Path] = None, logger_cfg: Any = None, **kw: Any) -> L.Trainer:
    """A Trainer for ``max_steps`` steps on ``device`` with the ``trainer`` section (precision,
    log_every_n_steps, strategy/devices/num_nodes for Lightning DDP).

    ``run_dir``: the ``logger`` section's loggers there (:func:`nerfart_plugin.systems.loggers.build_loggers`;
    default TensorBoard under ``<run_dir>/tb`` + CSV under ``<run_dir>/logs``) and a progress bar;
    None: no logger, no progress bar (in-memory runs). ``kw`` goes to ``lightning.Trainer``.
    """
    from lightning.pytorch.callbacks import TQDMProgressBar


    tc = section(TrainerConfig, trainer_cfg)
    accelerator = {"cuda": "gpu", "mps": "mps"}.get(device.type, "cpu")
    devices: Any = tc.devices
    if device.type == "cuda" and device.index is not None and devices == 1:
        devices = [device.index]
    logged = run_dir is not None
    return L.Trainer(
        max_steps=int(max_steps), accelerator=accelerator, devices=devices, precision=tc.precision,
        strategy=tc.strategy, num_nodes=tc.num_nodes, log_every_n_steps=tc.log_every_n_steps,
        logger=build_loggers(logger_cfg, run_dir) if logged else False,
        callbacks=[*callbacks, TQDMProgressBar(refresh_rate=10)] if logged else list(callbacks),
        enable_progress_bar=logged, enable_checkpointing=False, enable_model_summary=False, num_sanity_val_steps=0,
        default_root_dir=str(run_dir) if logged else None, **kw,
    )


@dataclass
class FitResult:
    """What a fit leaves: the trainer (global step, rank, ``save_checkpoint``) and the training seconds."""

    trainer: L.Trainer
    seconds: float

    @property
    def steps(self) -> int:
        return int(self.trainer.global_step)

    @property
    def is_global_zero(self) -> bool:
        return self.trainer.global_rank == 0


def fit_stage(system: L.LightningModule, folder: RunFolder, *, steps: int, device: torch.device,
              trainer_cfg: TrainerConfig | dict, checkpoint_every: int, callbacks: Sequence[Any] = (),
              val: Any = None, logger_cfg: Any = None, **trainer_kw: Any) -> FitResult:
    """Train ``system`` for ``steps`` steps in ``folder``, resuming from its ``last.ckpt`` if it fits.

    Raises:
        RunInterrupted: Ctrl-C, naming the step and the checkpoint to resume from.
        NerfArtError: out of memory, naming the settings to lower.
        CheckpointError: a ``last.ckpt`` that cannot be read or does not fit.
    """

    ckpt = AtomicCheckpoint(folder.path, checkpoint_every)
    stop = GracefulInterrupt(ckpt)
    projected = ProjectedTime(f"the {folder.what}")
    trainer = build_trainer(steps, device, trainer_cfg, [ckpt, stop, projected, *callbacks], run_dir=folder.path,
                            logger_cfg=logger_cfg, **trainer_kw)
    resume = folder.resume_point(system)
    t0 = time.perf_counter()
    run_fit(trainer, system, val=val, ckpt_path=resume, stop=stop, last=folder.last)
    return FitResult(trainer, time.perf_counter() - t0)


def train_steps(system: L.LightningModule, steps: int, device: torch.device,
                trainer_cfg: TrainerConfig | dict | None = None, callbacks: Sequence[Any] = ()) -> FitResult:
    """Train ``system`` for ``steps`` steps in memory (no run folder, checkpoint or logger): the stages'
    Trainer for benchmarks and experiments. OOM is translated as in :func:`fit_stage`."""
    trainer = build_trainer(steps, device, trainer_cfg, callbacks, limit_val_batches=0)
    t0 = time.perf_counter()
    run_fit(trainer, system)
    return FitResult(trainer, time.perf_counter() - t0)


def run_fit(trainer: Any, system: Any, val: Any = None, ckpt_path: Optional[str] = None, stop: Any = None,
            last: Optional[Path] = None) -> None:
    """``trainer.fit`` on the steps loader (checkpoints read with ``weights_only=True``), with the OOM
    translation and the interrupt report (``stop``: the run's GracefulInterrupt, ``last``: its resume point)."""

    try:
        with allow_project_types():
            trainer.fit(system, train_dataloaders=steps_loader(), val_dataloaders=val, ckpt_path=ckpt_path,
                        weights_only=True)
    except torch.OutOfMemoryError as exc:
        raise NerfArtError(OOM_HINT) from exc
    except RuntimeError as exc:
        if "out of memory" in str(exc).lower():
            raise NerfArtError(OOM_HINT) from exc
        raise
    except SystemExit:  # Lightning >= 2.5 ends an interrupted fit with sys.exit(1)
        if trainer.interrupted:
            raise RunInterrupted(interrupted_message(trainer, stop, last)) from None
        raise
    if trainer.interrupted or (stop is not None and stop.requested):
        raise RunInterrupted(interrupted_message(trainer, stop, last))


def interrupted_message(trainer: Any, stop: Any, last: Optional[Path]) -> str:
    """What an interrupted fit says: the step and how to resume."""
    step = stop.stopped_at if stop is not None else None  # a graceful stop: checkpoint written at this step
    at = f"step {step}"
    if step is None:  # stopped at once (a second Ctrl-C): the last periodic checkpoint is the resume point
        saved = stop.checkpoint.last_saved if stop is not None else -1
        at = f"step {trainer.global_step}" + (f" (last checkpoint: step {saved})" if saved >= 0 else "")
    if last is not None and last.exists():
        return f"interrupted at {at}; run the same command again to resume from {last}"
    return f"interrupted at {at}, before the first checkpoint; run the same command again to start it over"


def stage_final(result: FitResult, folder: RunFolder) -> Optional[Path]:
    """Every rank, right after the fit: the trainer's full state into a staged file beside ``final.ckpt``
    (under DDP a collective: every rank calls it, rank 0 writes). Rank 0 gets the staged path for
    :func:`publish_final` once its outputs are written; the other ranks get None."""
    staged = folder.final.with_name(f".{folder.final.name}.staged")
    result.trainer.save_checkpoint(staged)
    return staged if result.is_global_zero else None


def publish_final(staged: Path, folder: RunFolder) -> Path:
    """``final.ckpt``, the mark of a finished run: the staged state renamed into place (atomically, after the
    stage's outputs), with its content hash beside it."""

    with open(staged, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(staged, folder.final)
    write_checkpoint_hash(folder.final)
    return folder.final