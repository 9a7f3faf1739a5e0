"""Run folders: where a stage's outputs go, when a finished one is reused, how an unfinished one resumes.

Folders (under ``output_root``, default ``outputs/``):

* ``reconstructions/<data>-<backbone>-<encoding>-<key>/`` and
  ``stylizations/<prompt>-<backbone>-<key><stamp>/``: ``<key>`` hashes every setting
  that changes the stage's result (:func:`nerfart_plugin.schema.result_settings`), so
  the same settings find the same folder and any change another.
* ``final.ckpt`` marks a finished run: it is reused, never recomputed or overwritten.
* ``last.ckpt`` is the resume point of an unfinished run (``resume=true``, the
  default); ``resume=false`` moves an unfinished folder aside (renamed
  ``*.abandoned-<time>``) and starts over.
* While a stage works in a folder it holds the folder's lock
  (:mod:`nerfart_plugin.utils.lock`, ``lock_timeout``): a second process with the
  same run waits, then reuses the result.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, TypeVar

from omegaconf import OmegaConf

from nerfart_plugin.checkpoints import META_KEY, check_fits, load_checkpoint
from nerfart_plugin.utils.io import atomic_write_text
from nerfart_plugin.utils.lock import run_lock

log = logging.getLogger("nerfart_plugin")

T = TypeVar("T")
FINAL, LAST = "final.ckpt", "last.ckpt"


def config_hash(obj: Any, n: int = 12) -> str:
    """The first ``n`` hex digits of the SHA-256 of ``obj`` as sorted JSON (a run folder's key)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:n]


def slug(text: str, n: int = 40) -> str:
    """``text`` as a folder-name part: runs of other characters than letters and digits -> ``_``."""
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")[:n] or "prompt"


@dataclass(frozen=True)
class RunFolder:
    """One stage's run folder and its reuse / resume policy.

    Attributes:
        path: the folder.
        what: what runs there, for messages ("reconstruction", "stylization").
    """

    path: Path
    what: str

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

    def reuse_or_run(self, lock_timeout: Optional[float], work: Callable[[], T], reuse: Callable[[], T]) -> T:
        """``reuse()`` for a finished run; else ``work()`` holding the folder's lock (a run finished meanwhile
        by the process we waited for is reused)."""
        if not self.finished:
            with run_lock(self.path, lock_timeout):
                if not self.finished:
                    return work()
        return reuse()
