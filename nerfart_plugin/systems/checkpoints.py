"""Checkpoints that never run code, and say clearly when they do not fit the run.

* **Reading.** Every checkpoint (``source_checkpoint=``, a resumed ``last.ckpt``, a
  cached ``final.ckpt``) is read with ``torch.load(..., weights_only=True)``: tensors
  and plain data (dicts, lists, numbers, strings) only. A file whose unpickling would
  create any other object, which is how a pickle runs code, is refused with
  :class:`~nerfart_plugin.errors.CheckpointError` before anything is created. The only
  allow-listed type is :class:`~nerfart_plugin.data.setup.SceneSetup`, a plain
  dataclass that checkpoints written by version 0.1.0 hold in their hyper-parameters.
* **Writing.** The systems add :func:`checkpoint_meta` under ``checkpoint["nerfart"]``:
  the format, the package version, the stage, and the backbone / encoding / scene-setup
  configuration the tensors were made for (plain data).
* **Fitting.** :func:`check_fits` compares a checkpoint's tensors with the model of the
  run (names and shapes) before loading, and names the file and what differs (the
  configuration keys when the checkpoint has metadata, else the tensors).
"""

from __future__ import annotations

import contextlib
import logging
import pickle
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional

import torch
from pydantic import BaseModel

from nerfart_plugin import __version__
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.errors import CheckpointError, UnsafeCheckpointError
from nerfart_plugin.utils.io import atomic_write_text, file_sha256

log = logging.getLogger(__name__)

#: layout of ``checkpoint["nerfart"]``; a checkpoint of a newer format is refused
FORMAT = 1
META_KEY = "nerfart"


def safe_globals() -> list[Any]:
    """The project's own types allowed in a checkpoint besides tensors and plain data."""

    return [SceneSetup]


@contextlib.contextmanager
def allow_project_types() -> Iterator[None]:
    """Context in which ``torch.load(weights_only=True)`` (also Lightning's) accepts :func:`safe_globals`."""
    with torch.serialization.safe_globals(safe_globals()):
        yield


def load_checkpoint(path: str | Path, fix: str = "") -> dict[str, Any]:
    """The contents of checkpoint ``path`` (tensors on the CPU), read without running any code.

    Args:
        fix: what the user can do about an unreadable file (appended to the message).
    Raises:
        CheckpointError: not a checkpoint, truncated, or holding objects other than tensors and plain data.
    """
    path = Path(path)
    try:
        with allow_project_types():
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        code = next((line.strip() for line in str(exc).splitlines() if "GLOBAL" in line), None)
        if code is not None:  # an object of a class or function outside the allow-list: how a pickle runs code
            raise UnsafeCheckpointError(
                f"Refusing to load {path}: it holds Python objects other than tensors and plain data "
                f"({code.split(' was not an allowed')[0]}), and unpickling them could run code. nerfart_plugin only "
                f"loads checkpoints made of tensors and plain data (the ones it writes). {fix}".strip()) from None
        raise CheckpointError(f"Cannot read {path}: not a PyTorch checkpoint (no pickle data torch can read). "
                              f"{fix}".strip()) from None
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise CheckpointError(f"Cannot read checkpoint {path} ({type(exc).__name__}: {exc}): truncated or not a "
                              f"checkpoint. {fix}".strip()) from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), Mapping):
        raise CheckpointError(f"{path} is not a nerfart_plugin / Lightning checkpoint (no state_dict). {fix}".strip())
    meta = ckpt.get(META_KEY)
    if isinstance(meta, dict) and int(meta.get("format", 0)) > FORMAT:
        raise CheckpointError(f"{path} was written by nerfart_plugin {meta.get('version')} (checkpoint format "
                              f"{meta.get('format')}); this is {_version()} (format {FORMAT}): upgrade the package "
                              f"to read it. {fix}".strip())
    return ckpt


def _version() -> str:
    return __version__


def checkpoint_meta(stage: str, backbone: Mapping, encoding: Mapping, setup: Any) -> dict[str, Any]:
    """What a checkpoint records about the model its tensors belong to (plain data)."""
    setup_dict = setup.to_dict() if hasattr(setup, "to_dict") else dict(setup)
    return {"format": FORMAT, "version": _version(), "stage": stage, "backbone": _plain(backbone),
            "encoding": _plain(encoding), "setup": {k: v for k, v in _plain(setup_dict).items() if k != "reasons"}}


def _plain(obj: Any) -> Any:
    """Dicts / lists / numbers / strings only (a tuple becomes a list; a typed section, the settings it was
    given)."""
    if isinstance(obj, BaseModel):
        obj = obj.model_dump(mode="json", exclude_unset=True)
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def prefixed_state(ckpt: Mapping[str, Any], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors of ``ckpt["state_dict"]`` under ``prefix`` (e.g. ``"renderer."``), prefix removed."""
    return {k[len(prefix):]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)}


def config_differences(meta: Optional[Mapping], stage_meta: Mapping) -> list[str]:
    """``section.key: <checkpoint> in the checkpoint, <run> here`` for the model settings that differ."""
    if not isinstance(meta, Mapping):
        return []
    out = []
    for section in ("backbone", "encoding", "setup"):
        old, new = meta.get(section) or {}, stage_meta.get(section) or {}
        for key in sorted(set(old) | set(new)):
            if old.get(key) != new.get(key):
                name = f"scene setup {key}" if section == "setup" else f"{section}.{key}"
                out.append(f"{name}: {old.get(key)!r} in the checkpoint, {new.get(key)!r} here")
    return out


def tensor_differences(expected: Mapping[str, torch.Tensor], state: Mapping[str, torch.Tensor]) -> list[str]:
    """The tensors that keep ``state`` from loading into a module whose state dict is ``expected``."""
    out = [f"{k}: {tuple(state[k].shape)} in the checkpoint, {tuple(v.shape)} here"
           for k, v in expected.items() if k in state and tuple(state[k].shape) != tuple(v.shape)]
    missing = [k for k in expected if k not in state]
    extra = [k for k in state if k not in expected]
    if missing:
        out.append(f"missing {len(missing)} tensor(s), e.g. {missing[:3]}")
    if extra:
        out.append(f"{len(extra)} unexpected tensor(s), e.g. {extra[:3]}")
    return out


def check_fits(module: torch.nn.Module, state: Mapping[str, torch.Tensor], path: str | Path,
               meta: Optional[Mapping], stage_meta: Mapping, fix: str) -> None:
    """CheckpointError naming ``path`` and what differs if ``state`` does not load into ``module``."""
    tensors = tensor_differences(module.state_dict(), state)
    if not tensors:
        return
    settings = config_differences(meta, stage_meta)
    if settings:
        detail = "it was made with other model settings: " + "; ".join(settings)
    else:
        detail = "its tensors do not match this model (" + "; ".join(tensors[:4]) + ")"
        if not isinstance(meta, Mapping):
            detail += "; it records no nerfart_plugin settings (another version or program)"
    raise CheckpointError(f"{path} does not fit this run: {detail}. {fix}")


#: the suffix of the file beside a finished run's checkpoint holding its content hash
HASH_SUFFIX = ".sha256"


def write_checkpoint_hash(path: Path) -> None:
    """``<path>.sha256``: the content hash a finished run is verified against before it is reused."""
    atomic_write_text(Path(f"{path}{HASH_SUFFIX}"), file_sha256(path) + "\n")


def hash_mismatch(path: Path) -> Optional[str]:
    """Why ``path`` differs from the content hash stored beside it (``<path>.sha256``), or None when it matches or
    no hash is stored."""
    stored = Path(f"{path}{HASH_SUFFIX}")
    if not stored.is_file():
        return None
    return None if file_sha256(path) == stored.read_text().strip() else f"its content does not match {stored.name}"


def checkpoint_damage(path: Path) -> Optional[str]:
    """Why ``path`` (a finished run's ``final.ckpt``) cannot be trusted, or None when it is intact: its
    stored hash differs, or (no hash stored) it does not load as a checkpoint. A file that would run code
    when loaded is not damage: its :class:`~nerfart_plugin.errors.UnsafeCheckpointError` is raised."""

    if Path(f"{path}{HASH_SUFFIX}").is_file():
        return hash_mismatch(path)
    try:
        load_checkpoint(path)
    except UnsafeCheckpointError:
        raise
    except CheckpointError as exc:
        return str(exc)
    return None
