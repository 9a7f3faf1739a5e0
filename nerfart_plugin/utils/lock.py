"""One process per run folder: a file lock (``filelock``) held while a stage works in its folder.

Two processes on the same reconstruction or stylization (a sweep with duplicate jobs,
the same command started twice, several sweep jobs sharing one reconstruction) would
otherwise write the same checkpoints and outputs at once. The lock lives under
``<output_root>/.locks/`` (next to, not inside, the run folder: ``resume=false`` moves an
unfinished folder aside), with a ``.json`` naming its holder (pid, host, start time,
command). The lock is released when the stage ends or the process dies (the OS drops it,
SIGKILL included), so a stale lock cannot block a later run.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import sys
import time
from pathlib import Path
from typing import Iterator, Optional

from filelock import FileLock, Timeout

from nerfart_plugin.errors import RunLockedError

log = logging.getLogger(__name__)


def process_rank() -> int:
    """0 for the process that leads a run (a plain run, or rank 0 of a DDP / Slurm / torchrun launch), else
    the first non-zero rank the launcher set (global, local or node rank)."""
    for var in ("RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK", "NODE_RANK", "LOCAL_RANK"):
        value = os.environ.get(var, "").strip()
        if value.isdigit() and int(value) != 0:
            return int(value)
    return 0


def lock_path(run_dir: Path) -> Path:
    """``<output_root>/.locks/<stage folder>-<run name>.lock`` for ``<output_root>/<stage folder>/<run name>``."""
    run_dir = Path(run_dir)
    return run_dir.parent.parent / ".locks" / f"{run_dir.parent.name}-{run_dir.name}.lock"


def _holder_path(lock: Path) -> Path:
    return lock.with_suffix(".lock.json")


def describe_holder(lock: Path) -> str:
    """Who holds ``lock``, as written by its holder ("another process" when unknown)."""
    try:
        h = json.loads(_holder_path(lock).read_text())
        return (f"process {h['pid']} on {h['host']} (started {h['started']}: "
                f"{' '.join(h.get('command', []))[:200]})")
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


@contextlib.contextmanager
def run_lock(run_dir: Path, timeout: Optional[float]) -> Iterator[None]:
    """Hold the lock of ``run_dir`` for the block.

    Args:
        timeout: seconds to wait when another process holds it; 0: fail at once; None: wait until it is free.
    Raises:
        RunLockedError: still held after ``timeout`` seconds (names the holder and what to do).
    """

    if process_rank() != 0:  # DDP: rank 0 holds the lock for the run; its worker ranks must not wait for it
        yield
        return
    path = lock_path(run_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(str(path))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        holder = describe_holder(path)
        if timeout is not None and timeout <= 0:
            raise RunLockedError(_busy(run_dir, holder, timeout)) from None
        log.warning("%s is in use by %s; waiting %s", run_dir, holder,
                    "until it is free (lock_timeout=null)" if timeout is None
                    else f"up to {timeout:g} s (lock_timeout={timeout:g})")
        try:
            lock.acquire(timeout=-1 if timeout is None else float(timeout))
        except Timeout:
            raise RunLockedError(_busy(run_dir, holder, timeout)) from None
        log.info("%s is free now", run_dir)
    try:
        _holder_path(path).write_text(json.dumps({
            "pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": sys.argv}))
        yield
    finally:
        with contextlib.suppress(OSError):
            _holder_path(path).unlink()
        lock.release()


def _busy(run_dir: Path, holder: str, timeout: Optional[float]) -> str:
    waited = f"after waiting {timeout:g} s (lock_timeout={timeout:g})" if timeout else "(lock_timeout=0: not waiting)"
    return (f"{run_dir} is in use by {holder} {waited}. It is the same run with the same settings: let it finish and "
            "run the command again to reuse its result, stop that process, or wait longer with lock_timeout=<seconds> "
            "(lock_timeout=null waits until it is free).")
