"""Atomic file output: write to a temporary file in the same folder, fsync, rename.

A process killed at any moment (SIGKILL included) leaves either the previous
complete file or the new complete file, never a truncated one.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

from nerfart_plugin.errors import ConfigError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 (hex) of one file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def hash_files(paths: list[Path], extra: str = "") -> str:
    """SHA-256 over the contents (and relative names) of ``paths``, plus ``extra``; hex digest."""
    h = hashlib.sha256()
    for p in sorted(Path(p) for p in paths):
        h.update(p.name.encode())
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    h.update(extra.encode())
    return h.hexdigest()


#: free disk space an output root needs (checkpoints, renders, meshes of a small run)
MIN_FREE_BYTES = 64 * 2**20


def check_writable_dir(path: str | os.PathLike, key: str = "output_root", create: bool = True) -> Path:
    """Create folder ``path`` if needed and check that files can be written there, with free space left.
    ``create=False`` creates nothing: a missing folder is judged by its nearest existing parent (the checks
    before a command is accepted leave no empty folder behind when it is refused later).

    Returns:
        the folder.
    Raises:
        ConfigError: naming ``key``, the path and the reason (a file in the way, read-only, no permission,
        a missing parent that cannot be created, a full disk).
    """

    folder = Path(path).expanduser()
    blocker = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise ConfigError(f"{key}={path}: {blocker} is a file, so no folder can be made there; choose another "
                          f"{key} (a folder) or move that file.")
    if not create:
        folder = next(p for p in (folder, *folder.parents) if p.exists())
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=folder)
        try:
            os.write(fd, b"nerfart")
            os.fsync(fd)
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise ConfigError(f"{key}={path}: cannot write into {folder} ({exc.strerror or exc}); choose a folder you "
                          f"can write, e.g. {key}=$HOME/nerfart_outputs.") from exc
    free = shutil.disk_usage(folder).free
    if free < MIN_FREE_BYTES:
        raise ConfigError(f"{key}={path}: only {free / 2**20:.0f} MiB free on the disk of {folder}; a run needs at "
                          f"least {MIN_FREE_BYTES / 2**20:.0f} MiB for checkpoints, renders and meshes. Free some "
                          f"space or choose another {key}.")
    return folder


def config_hash(obj: Any, n: int = 12) -> str:
    """The first ``n`` hex digits of the SHA-256 of ``obj`` as sorted JSON (a run folder's key)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:n]


def slug(text: str, n: int = 40) -> str:
    """``text`` as a folder-name part: runs of other characters than letters and digits -> ``_``."""
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")[:n] or "prompt"
