"""Hydra callback collecting a summary table at the end of a multirun (``-m``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from nerfart_plugin.utils.io import atomic_write_json, atomic_write_text

log = logging.getLogger("nerfart_plugin")


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def collect(sweep_dir: Path) -> list[dict[str, Any]]:
    """One row per job: its overrides and the flattened ``result.json``."""
    rows = []
    for job in sorted((p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)):
        overrides_file = job / ".hydra" / "overrides.yaml"
        overrides = ""
        if overrides_file.exists():
            overrides = " ".join(x.strip("- \n") for x in overrides_file.read_text().splitlines() if x.strip())
        result_file = job / "result.json"
        result = json.loads(result_file.read_text()) if result_file.exists() else {"error": "no result (crashed?)"}
        rows.append({"job": int(job.name), "overrides": overrides, **_flatten(result)})
    return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols and not k.endswith(".dir")]
    fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"


class MultirunSummary(Callback):
    """Writes ``summary.md`` and ``summary.json`` in the sweep folder when a multirun ends."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        rows = collect(sweep_dir)
        atomic_write_json(sweep_dir / "summary.json", rows)
        table = markdown_table(rows)
        atomic_write_text(sweep_dir / "summary.md", table)
        log.info("multirun summary (%d jobs) -> %s\n%s", len(rows), sweep_dir / "summary.md", table)
