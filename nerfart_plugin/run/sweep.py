"""Sweeps: the objective a job returns to Hydra, and a summary table at the end of a multirun.

* :func:`objective` turns :func:`nerfart_plugin.run.pipeline.run`'s result dict into the
  single float a Hydra sweeper (Optuna, ``hydra/sweeper=lambdas_optuna``) optimizes.
  Both metrics are "higher is better", so the Optuna config uses ``direction: maximize``:

  - a stylization ran (``stage=stylize|all``): ``stylization.clip_directional_similarity``,
    the cosine between the CLIP image-space edit direction (stylized - source, over the
    held-out views) and the text direction (target - source prompt) -- the directional
    CLIP score of Eq. 4 evaluated on held-out views (``nerfart_plugin.objectives.evaluation.clip_scores``);
  - reconstruction only (``stage=reconstruct``): ``reconstruction.psnr``, the mean held-out
    PSNR in dB.

  ``objective=<stage>.<metric>`` (e.g. ``+objective=stylization.clip_score``) picks another
  flattened key of the result; ``objective=auto`` (or unset) is the rule above.
* :class:`MultirunSummary` (registered in ``conf/config.yaml`` under
  ``hydra.callbacks.summary``) writes ``summary.md`` and ``summary.json`` into the sweep
  folder when a multirun (``-m``) ends: one row per job with its swept overrides, status,
  objective and metrics. Cached stages (a reused reconstruction, an already finished
  stylization) are filled in from their folder's ``metrics.json``.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.utils.io import atomic_write_json, atomic_write_text

log = logging.getLogger("nerfart_plugin")

#: (result key, metric) tried in order by ``objective="auto"``; all are maximized.
AUTO_OBJECTIVES: tuple[tuple[str, str], ...] = (
    ("stylization", "clip_directional_similarity"),
    ("reconstruction", "psnr"),
)
#: What the Optuna sweeper does with the objective (every auto metric is "higher is better").
DIRECTION = "maximize"


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _scalar_metrics(d: dict) -> dict[str, Any]:
    return {
        k: v
        for k, v in d.items()
        if isinstance(v, (int, float, str, bool)) or v is None
    }


def complete_results(results: dict[str, Any]) -> dict[str, Any]:
    """Fill the stage entries that only carry ``dir`` (the stage was cached) from ``<dir>/metrics.json``.

    The pipeline returns just ``{"dir": ...}`` for a reconstruction or stylization it
    reused instead of recomputing; the metrics of that run are in its ``metrics.json``.
    Returns a new dict; values already in ``results`` win.
    """
    out = dict(results)
    for stage in ("reconstruction", "stylization"):
        entry = results.get(stage)
        if not isinstance(entry, dict) or not entry.get("dir"):
            continue
        mfile = Path(entry["dir"]) / "metrics.json"
        if not mfile.is_file():
            continue
        try:
            metrics = json.loads(mfile.read_text())
        except (OSError, ValueError):
            continue
        if stage == "reconstruction":
            keep = {k: v for k, v in metrics.items() if k.startswith(("psnr", "ssim"))}
        else:
            keep = {
                k: v
                for k, v in metrics.items()
                if k.startswith(("clip_", "view_", "mesh_"))
            }
        out[stage] = {**_scalar_metrics(keep), **entry}
    return out


def objective(results: dict[str, Any], metric: str | None = "auto") -> float:
    """The float a sweeper optimizes (higher is better), from ``pipeline.run``'s result.

    Args:
        results: ``{"stage": ..., "reconstruction": {"psnr": ...}, "stylization":
            {"clip_directional_similarity": ...}}`` as returned by ``pipeline.run``.
        metric: ``"auto"``/None -> stylization.clip_directional_similarity if a
            stylization ran, else reconstruction.psnr (dB); or an explicit flattened
            key such as ``"stylization.clip_score"``.
    Raises:
        ConfigError: the metric is not in the results (e.g. ``stage=export``) or not finite.
    """
    flat = _flatten(complete_results(results))
    if metric in (None, "", "auto"):
        keys = [f"{s}.{m}" for s, m in AUTO_OBJECTIVES]
    else:
        keys = [str(metric)]
    for key in keys:
        value = flat.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = float(value)
            if not math.isfinite(value):
                raise ConfigError(
                    f"objective {key} = {value} is not finite; the run diverged or had no "
                    "held-out views (check data.holdout_every)."
                )
            return value
    numeric = sorted(
        k
        for k, v in flat.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool)
    )
    raise ConfigError(
        f"No objective {' / '.join(keys)} in this run's results (stage={results.get('stage')!r}). "
        f"Use stage=reconstruct|stylize|all, or set objective= to one of: {', '.join(numeric) or '(none)'}."
    )


# ---------------------------------------------------------------------- multirun summary
def _read_overrides(job: Path) -> list[str]:
    f = job / ".hydra" / "overrides.yaml"
    if not f.is_file():
        return []
    try:
        data = yaml.safe_load(f.read_text()) or []
    except yaml.YAMLError:
        return []
    return [str(x) for x in data]


def collect(sweep_dir: Path, metric: str | None = "auto") -> list[dict[str, Any]]:
    """One row per job folder (``<sweep_dir>/<job.num>``): overrides, status, objective, flattened metrics.

    ``overrides`` holds only the overrides that differ between jobs (the swept
    ones; all of them when there is a single job); ``all_overrides`` the full list.
    """
    jobs = sorted(
        (p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()),
        key=lambda p: int(p.name),
    )
    overrides = {job: _read_overrides(job) for job in jobs}
    common = (
        set.intersection(*(set(o) for o in overrides.values()))
        if len(jobs) > 1
        else set()
    )
    rows = []
    for job in jobs:
        result_file = job / "result.json"
        result: dict[str, Any]
        if result_file.is_file():
            try:
                result = json.loads(result_file.read_text())
            except ValueError as exc:
                result = {"error": f"unreadable result.json: {exc}"}
        else:
            result = {"error": "no result.json (the job crashed or is still running)"}
        row: dict[str, Any] = {
            "job": int(job.name),
            "overrides": " ".join(o for o in overrides[job] if o not in common),
        }
        if "error" in result:
            row.update(status="error", objective=None, error=result["error"])
        else:
            result = complete_results(result)
            try:
                value: float | None = objective(result, metric)
            except ConfigError:
                value = None
            row.update(status="ok", objective=value)
            row.update(_flatten(result))
        row["all_overrides"] = overrides[job]
        rows.append(row)
    return rows


def markdown_table(rows: list[dict[str, Any]], title: str = "") -> str:
    """A Markdown table of :func:`collect`'s rows (folders and full override lists left out)."""
    cols: list[str] = []
    for r in rows:
        cols += [
            k
            for k in r
            if k not in cols and not k.endswith(".dir") and k != "all_overrides"
        ]

    def fmt(v: Any) -> str:
        if v is None:
            return ""
        return (
            f"{v:.4g}"
            if isinstance(v, float)
            else str(v).replace("|", "\\|").replace("\n", " ")
        )

    lines = [f"# {title}\n"] if title else []
    lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"


#: the failed jobs of the last multirun (:class:`MultirunSummary`; the CLI clears it first, exits 1 when any)
failed_jobs: list[int] = []


class MultirunSummary(Callback):
    """Writes ``summary.md`` and ``summary.json`` in the sweep folder when a multirun ends, and records the
    failed jobs in :data:`failed_jobs`.

    ``summary.json``: ``{"sweep_dir", "objective": {"metric", "direction"}, "best", "jobs": [rows]}``.
    With the Optuna sweeper, its ``optimization_results.yaml`` (best params/value) is
    included as ``optuna``.
    """

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        metric = OmegaConf.select(config, "objective", default="auto")
        rows = collect(sweep_dir, metric)
        failed_jobs[:] = [r["job"] for r in rows if r["status"] == "error"]
        ok = [r for r in rows if r.get("objective") is not None]
        best = max(ok, key=lambda r: r["objective"]) if ok else None
        summary: dict[str, Any] = {
            "sweep_dir": str(sweep_dir),
            "objective": {
                "metric": metric or "auto",
                "direction": DIRECTION,
                "auto_order": [f"{s}.{m}" for s, m in AUTO_OBJECTIVES],
            },
            "best": None
            if best is None
            else {
                "job": best["job"],
                "objective": best["objective"],
                "overrides": best["overrides"],
            },
            "jobs": rows,
        }
        optuna_file = sweep_dir / "optimization_results.yaml"
        if optuna_file.is_file():
            summary["optuna"] = yaml.safe_load(optuna_file.read_text())
        atomic_write_json(sweep_dir / "summary.json", summary)
        text = markdown_table(rows, title=f"Sweep {sweep_dir.name}: {len(rows)} jobs")
        text += f"\nObjective: {metric or 'auto'} ({DIRECTION}; auto = "
        text += (
            " if present, else ".join(f"{s}.{m}" for s, m in AUTO_OBJECTIVES) + ").\n"
        )
        if best is not None:
            text += f"Best: job {best['job']} ({best['overrides'] or 'single job'}) objective {best['objective']:.4g}.\n"
        common = (
            sorted(set.intersection(*(set(r["all_overrides"]) for r in rows)))
            if len(rows) > 1
            else []
        )
        if common:
            text += "\nShared overrides: `" + " ".join(common) + "`\n"
        atomic_write_text(sweep_dir / "summary.md", text)
        log.info(
            "multirun summary (%d jobs) -> %s\n%s",
            len(rows),
            sweep_dir / "summary.md",
            text,
        )
