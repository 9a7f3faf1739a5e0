"""``run.json``: what a run folder is, in one small record beside its ``config.yaml`` and ``final.ckpt``.

::

    {"format": 1, "kind": "stylization", "stage": "stylize", "key": "5cbf644540fb", "config_format": 2,
     "source": {"relative": "../../reconstructions/h3ds-volsdf-grid-5de7f4ec4f94",
                "absolute": "/home/me/outputs/reconstructions/h3ds-volsdf-grid-5de7f4ec4f94"},
     "produced_by": {"package": "nerfart_plugin", "version": "0.1.0"}, "created": "2026-12-07T10:00:00"}

* ``kind``: reconstruction | stylization (a preview is a short stylization, ``stage: preview``).
* ``key``: the run's cache key (:mod:`nerfart_plugin.run.keys`); ``config_format``: the layout of its
  ``config.yaml`` (:mod:`nerfart_plugin.config.migrate`).
* ``source``: a stylization's reconstruction, relative to this folder first (so a moved outputs folder still
  finds it), then as it was when the run was made.

A folder made before run records has none; :meth:`RunRecord.read` infers one from what it holds (its
``metrics.json`` and config) and :func:`migrate` writes it, so every folder ends up saying what it is.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from nerfart_plugin import __version__
from nerfart_plugin.config.migrate import CONFIG_FORMAT, config_format
from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.utils.io import atomic_write_json

log = logging.getLogger("nerfart_plugin")

#: the file name of the record in a run folder
RECORD = "run.json"
#: the layout of ``run.json`` itself; a newer one is refused with the upgrade to make
RECORD_FORMAT = 1
KINDS = ("reconstruction", "stylization")


@dataclass(frozen=True)
class RunRecord:
    """One run folder's record (``run.json``).

    Attributes:
        kind: reconstruction | stylization; stage: the stage that made it (reconstruct, stylize, preview).
        key: its cache key; config_format: the layout of its ``config.yaml``.
        source: a stylization's source run folder: ``{"relative": ..., "absolute": ...}`` ({} for none).
        produced_by: the package and version that wrote the run; created: when (local time, ISO 8601).
        format: the layout of this record.
    """

    kind: str
    stage: str
    key: str
    config_format: int = CONFIG_FORMAT
    source: dict[str, str] = field(default_factory=dict)
    produced_by: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    format: int = RECORD_FORMAT

    @classmethod
    def new(cls, kind: str, stage: str, key: str, folder: Path, source: Optional[Path] = None) -> "RunRecord":
        """The record of a run made now in ``folder`` (``source``: a stylization's reconstruction folder)."""
        return cls(kind, stage, key, CONFIG_FORMAT, source_paths(folder, source),
                   {"package": "nerfart_plugin", "version": __version__}, time.strftime("%Y-%m-%dT%H:%M:%S"))

    # ------------------------------------------------------------------ reading
    @classmethod
    def read(cls, folder: Path) -> "RunRecord":
        """``folder``'s record: its ``run.json``, or for a folder made before run records, the record its
        contents imply (:meth:`infer`). Raises NerfArtError naming the file for a damaged or newer record."""
        path = Path(folder) / RECORD
        if not path.is_file():
            return cls.infer(folder)
        try:
            data = json.loads(path.read_text())
            if int(data.get("format", 0)) > RECORD_FORMAT:
                raise NerfArtError(f"{path} was written by nerfart_plugin {data.get('produced_by', {}).get('version')} "
                                   f"(record format {data['format']}); this is {__version__}: upgrade the package to "
                                   "open this run.")
            record = cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
            raise NerfArtError(f"{path} is damaged ({type(exc).__name__}: {exc}). Delete it: the run folder's "
                               "other files say what it is, and it is written again when the run is opened.") from None
        if record.kind not in KINDS:
            raise NerfArtError(f"{path}: kind {record.kind!r} is not one of {', '.join(KINDS)}. Delete the file: it "
                               "is written again from the folder's other files when the run is opened.")
        return record

    @classmethod
    def infer(cls, folder: Path) -> "RunRecord":
        """The record of a folder made before run records: a stylization when its ``metrics.json`` names a prompt
        (else its parent folder says which), its key from its name, its source from ``metrics.json``."""
        folder = Path(folder)
        metrics = _read_json(folder / "metrics.json")
        config = _read_yaml(folder / "config.yaml")
        stylized = metrics.get("prompt") is not None or folder.parent.name in ("stylizations", "previews")
        kind = "stylization" if stylized else "reconstruction"
        stage = "preview" if folder.parent.name == "previews" else ("stylize" if stylized else "reconstruct")
        source = metrics.get("source_checkpoint")
        return cls(kind, stage, key_in_name(folder.name), config_format(config) if config else 1,
                   inferred_source(Path(source).parent) if source else {},
                   {"package": "nerfart_plugin", "version": "before run records"}, "")

    def write(self, folder: Path) -> Path:
        """Write ``<folder>/run.json`` (atomically)."""
        return atomic_write_json(Path(folder) / RECORD, asdict(self))

    # ------------------------------------------------------------------ the source
    def source_folder(self, folder: Path) -> Optional[Path]:
        """The source run folder as it can be found now: beside this one as when the run was made (a moved
        outputs folder), else where it was; None when it is on neither path (or there is no source)."""
        for key in ("relative", "absolute"):
            where = self.source.get(key)
            if where:
                path = (Path(folder) / where) if key == "relative" else Path(where)
                if path.is_dir():
                    return path.resolve()
        return None


def source_paths(folder: Path, source: Optional[Path]) -> dict[str, str]:
    """``{"relative": <source from folder>, "absolute": <source>}`` ({} without a source)."""
    if source is None:
        return {}
    source, folder = Path(source).resolve(), Path(folder).resolve()
    return {"relative": os.path.relpath(source, folder), "absolute": str(source)}


def inferred_source(source: Path) -> dict[str, str]:
    """The source of a folder made before run records, from the absolute path its ``metrics.json`` names:
    relative to it the usual layout (``../../reconstructions/<run>``: found again after the whole outputs folder
    moved), absolute as recorded."""
    return {"relative": str(Path("..", "..", source.parent.name, source.name)), "absolute": str(source)}


def key_in_name(name: str) -> str:
    """The cache key in a run folder's name (``<...>-<key>``, 12 hex digits, with an optional ``_STAMP-guide``
    suffix); the name itself when it holds none."""
    found = re.findall(r"-([0-9a-f]{12})(?=_|$)", name)
    return found[-1] if found else name


def migrate(folder: Path) -> RunRecord:
    """``folder``'s record, written as ``run.json`` when the folder had none (a folder made before run records:
    from then on it says what it is). A folder that cannot be written keeps working without one."""
    record = RunRecord.read(folder)
    if not (Path(folder) / RECORD).is_file():
        try:
            record.write(folder)
            log.info("%s: wrote its run record (%s), made before run records", folder, RECORD)
        except OSError as exc:
            log.debug("could not write %s/%s: %s", folder, RECORD, exc)
    return record


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return {}
    return data if isinstance(data, dict) else {}
