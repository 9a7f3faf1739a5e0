"""Run folders: where a stage's outputs go, when a finished one is reused, how an unfinished one resumes.

Folders (under ``output_root``, default ``outputs/``):

* ``reconstructions/<data>-<backbone>-<encoding>-<key>/`` and
  ``stylizations/<prompt>-<backbone>-<key><stamp>/``: ``<key>`` hashes every setting
  that changes the stage's result (:func:`nerfart_plugin.config.validate.result_settings`), so
  the same settings find the same folder and any change another.
* ``final.ckpt`` marks a finished run: it is reused, never recomputed or overwritten. Its SHA-256 is kept
  beside it (``final.ckpt.sha256``); before a finished run is reused it is verified (the hash, or for a
  run written before hashes, a safe load). A damaged one (truncated, overwritten) is set aside as
  ``final.ckpt.damaged-<time>`` with a warning and the stage runs again, resuming from ``last.ckpt``:
  nothing healthy is deleted.
* ``last.ckpt`` is the resume point of an unfinished run (``resume=true``, the
  default); ``resume=false`` moves an unfinished folder aside (renamed
  ``*.abandoned-<time>``) and starts over.
* While a stage works in a folder it holds the folder's lock
  (:mod:`nerfart_plugin.utils.lock`, ``lock_timeout``): a second process with the
  same run waits, then reuses the result.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, TypeVar

from omegaconf import OmegaConf

from nerfart_plugin.results.run import Run, open_run
from nerfart_plugin.systems.checkpoints import HASH_SUFFIX, META_KEY, check_fits, checkpoint_damage, load_checkpoint
from nerfart_plugin.utils.io import atomic_write_text
from nerfart_plugin.utils.lock import run_lock

log = logging.getLogger("nerfart_plugin")

T = TypeVar("T")
FINAL, LAST = "final.ckpt", "last.ckpt"


@dataclass(frozen=True)
class RunFolder:
    """One stage's run folder and its reuse / resume policy.

    Attributes:
        path: the folder.
        what: what runs there, for messages ("reconstruction", "stylization").
    """

    path: Path
    what: str

    @classmethod
    def find(cls, parent: Path, names: Sequence[str], what: str) -> "RunFolder":
        """The folder of the first of ``names`` (the current key's first, then those of earlier settings formats)
        that exists under ``parent``, else the first: a run made by an earlier version is found again."""
        for i, name in enumerate(names):
            if (parent / name).is_dir():
                if i:
                    log.info("found the %s of these settings made by an earlier version: %s", what, parent / name)
                return cls(parent / name, what)
        return cls(parent / names[0], what)

    def open(self, device: str = "auto") -> Run:
        """The finished run in this folder (:func:`~nerfart_plugin.results.run.open_run`): what render, export,
        preview, the viewer and the notebook work on."""
        return open_run(self.path, device=device)

    @property
    def final(self) -> Path:
        return self.path / FINAL

    @property
    def last(self) -> Path:
        return self.path / LAST

    @property
    def finished(self) -> bool:
        return self.final.exists()

    def prepare(self, resume: bool, config: dict) -> None:
        """Create the folder (``resume=false``: an unfinished one is moved aside first) and record ``config``."""
        if self.path.exists() and not resume and not self.finished:
            aside = self.path.with_name(f"{self.path.name}.abandoned-{time.strftime('%Y%m%d-%H%M%S')}")
            shutil.move(str(self.path), str(aside))
            log.info("resume=false: moved the unfinished run to %s and starting over", aside)
        self.path.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(config)))

    def resume_point(self, system: Any) -> Optional[str]:
        """``last.ckpt`` if there is one (read safely and checked to fit ``system``), else None."""
        if not self.last.exists():
            return None
        fix = (f"Delete {self.last} (or run with resume=false, which keeps the old folder aside) to start this "
               f"{self.what} over.")
        ckpt = load_checkpoint(self.last, fix=fix)
        check_fits(system, ckpt["state_dict"], self.last, ckpt.get(META_KEY), system.model_meta, fix)
        log.info("resuming the %s from %s (step %s)", self.what, self.last, ckpt.get("global_step"))
        return str(self.last)

    def set_aside_if_damaged(self) -> None:
        """A finished run whose ``final.ckpt`` is damaged (:func:`checkpoint_damage`) becomes unfinished: the
        file is renamed ``final.ckpt.damaged-<time>`` (kept, not deleted) with a warning saying so."""
        if not self.finished:
            return
        why = checkpoint_damage(self.final)
        if why is None:
            return
        aside = self.final.with_name(f"{FINAL}.damaged-{time.strftime('%Y%m%d-%H%M%S')}")
        self.final.rename(aside)
        Path(f"{self.final}{HASH_SUFFIX}").unlink(missing_ok=True)
        log.warning("%s is damaged (%s): set aside as %s; the %s runs again%s.", self.final, why, aside.name,
                    self.what, " from its last.ckpt" if self.last.exists() else " from the start")

    def reuse_or_run(self, lock_timeout: Optional[float], work: Callable[[], T], reuse: Callable[[], T]) -> T:
        """``reuse()`` for a finished, verified run; else ``work()`` holding the folder's lock (a run finished
        meanwhile by the process we waited for is reused)."""
        if self.finished:
            with run_lock(self.path, lock_timeout):
                self.set_aside_if_damaged()
        if not self.finished:
            with run_lock(self.path, lock_timeout):
                if not self.finished:
                    return work()
        return reuse()
