"""Sweeps: the objective, the multirun summary, and real tiny multiruns (basic + Optuna)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from pipeline_helpers import TINY_TOY, run_cli

from nerfart_plugin.config.compose import config_dir
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.run.sweep import collect, complete_results, markdown_table, objective

REPO = Path(__file__).resolve().parents[1]

TINY = TINY_TOY

_cli = run_cli


# ---------------------------------------------------------------------- objective
def test_objective_prefers_stylization_then_psnr():
    res = {
        "stage": "all",
        "reconstruction": {"dir": "x", "psnr": 21.5},
        "stylization": {
            "dir": "y",
            "clip_directional_similarity": 0.25,
            "clip_score": 0.3,
        },
    }
    assert objective(res) == pytest.approx(0.25)
    assert objective(
        {"stage": "reconstruct", "reconstruction": {"psnr": 21.5}}
    ) == pytest.approx(21.5)
    assert objective(res, "stylization.clip_score") == pytest.approx(0.3)
    assert objective(res, "reconstruction.psnr") == pytest.approx(21.5)


def test_objective_errors_name_the_fix():
    with pytest.raises(ConfigError, match="stage=.export."):
        objective({"stage": "export", "export": {"mesh": "m", "vertices": 3}})
    with pytest.raises(
        ConfigError, match="reconstruction.psnr"
    ):  # lists the numeric keys available
        objective({"stage": "all", "reconstruction": {"psnr": 3.0}}, "stylization.nope")
    with pytest.raises(ConfigError, match="not finite"):
        objective({"stage": "reconstruct", "reconstruction": {"psnr": float("nan")}})


def test_objective_reads_metrics_of_cached_stages(tmp_path):
    (tmp_path / "metrics.json").write_text(
        json.dumps(
            {
                "clip_directional_similarity": 0.5,
                "prompt": "x",
                "experiment": {"name": "full"},
            }
        )
    )
    res = {
        "stage": "stylize",
        "stylization": {"dir": str(tmp_path)},
    }  # what the pipeline returns on a cache hit
    assert objective(res) == pytest.approx(0.5)
    done = complete_results(res)
    assert (
        done["stylization"]["dir"] == str(tmp_path)
        and "experiment" not in done["stylization"]
    )


def _fake_job(sweep: Path, num: int, overrides: list[str], result: dict | None) -> None:
    job = sweep / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(
        "".join(f"- {o}\n" for o in overrides)
    )
    if result is not None:
        (job / "result.json").write_text(json.dumps(result))


def test_collect_rows_and_table(tmp_path):
    _fake_job(
        tmp_path,
        0,
        ["guidance=toy", "prompt=red"],
        {
            "stage": "all",
            "reconstruction": {"dir": "r", "psnr": 20.0},
            "stylization": {"dir": "s", "clip_directional_similarity": 0.1},
        },
    )
    _fake_job(
        tmp_path,
        1,
        ["guidance=toy", "prompt=blue"],
        {"error": "ConfigError: bad | prompt"},
    )
    _fake_job(tmp_path, 10, ["guidance=toy", "prompt=green"], None)
    rows = collect(tmp_path)
    assert [r["job"] for r in rows] == [0, 1, 10]  # numeric, not lexical, order
    assert rows[0]["overrides"] == "prompt=red"  # shared overrides left out
    assert rows[0]["status"] == "ok" and rows[0]["objective"] == pytest.approx(0.1)
    assert rows[0]["reconstruction.psnr"] == 20.0
    assert rows[1]["status"] == "error" and "bad" in rows[1]["error"]
    assert rows[2]["status"] == "error" and "no result.json" in rows[2]["error"]
    table = markdown_table(rows)
    assert "reconstruction.dir" not in table and "bad \\| prompt" in table
    assert table.count("\n") == 2 + 3


# ---------------------------------------------------------------------- compose
def test_optuna_sweeper_config_composes():
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=["hydra/sweeper=lambdas_optuna", "hydra.sweeper.n_trials=3"],
            return_hydra_config=True,
        )
    sw = cfg.hydra.sweeper
    assert sw._target_.endswith("optuna_sweeper.OptunaSweeper")
    assert sw.direction == "maximize" and sw.n_trials == 3
    assert sw.sampler._target_ == "optuna.samplers.TPESampler"
    params = OmegaConf.to_container(sw.params)
    assert set(params) == {
        f"experiment.lambda_{k}" for k in ("global", "local", "perceptual", "reg")
    }
    # every range contains the paper's value (Eq. 8 weights in conf/experiment/full.yaml)
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for key, spec in params.items():
        ov = parser.parse_override(f"{key}={spec}")
        interval = ov.value()
        assert interval.start < cfg.experiment[key.split(".")[1]] < interval.end, key
        assert "log" in ov.value().tags
    assert [c["_target_"] for c in cfg.hydra.callbacks.values()] == [
        "nerfart_plugin.run.sweep.MultirunSummary"
    ]


def test_optuna_is_importable():
    """The [sweep] extra: hydra-optuna-sweeper 1.3.0 works with optuna 2.10.1 + SQLAlchemy 2.x in memory."""
    optuna = pytest.importorskip("optuna")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(
        direction="maximize", sampler=optuna.samplers.TPESampler(seed=0)
    )
    study.optimize(
        lambda t: -((t.suggest_float("x", 0.01, 1.0, log=True) - 0.1) ** 2), n_trials=5
    )
    assert len(study.trials) == 5 and study.best_value <= 0.0


# ---------------------------------------------------------------------- real multiruns
def _sweep_dir(root: Path) -> Path:
    dirs = sorted((root / "multirun").iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


@pytest.mark.slow
def test_multirun_two_jobs_summary(tmp_path):
    """`-m +prompt=red,blue`: two jobs, each in its own folder; summary lists both with metrics."""
    out = tmp_path / "out"
    proc = _cli(["-m", "stage=all", "+prompt=red,blue", f"output_root={out}", *TINY])
    assert proc.returncode == 0, proc.stderr[-3000:]
    sweep = _sweep_dir(out)
    assert sorted(
        p.name for p in sweep.iterdir() if p.is_dir() and not p.name.startswith(".")
    ) == ["0", "1"]
    for j in ("0", "1"):
        assert (sweep / j / "result.json").is_file() and (
            sweep / j / ".hydra" / "overrides.yaml"
        ).is_file()
    summary = json.loads((sweep / "summary.json").read_text())
    rows = summary["jobs"]
    assert [r["job"] for r in rows] == [0, 1]
    assert [r["overrides"] for r in rows] == ["prompt=red", "prompt=blue"]
    for r in rows:
        assert r["status"] == "ok"
        # job 1 reuses job 0's reconstruction (cache): its metrics still appear
        assert 0.0 < r["reconstruction.psnr"] < 60.0
        assert -1.0 <= r["stylization.clip_directional_similarity"] <= 1.0
        assert r["objective"] == pytest.approx(
            r["stylization.clip_directional_similarity"]
        )
    assert rows[0]["reconstruction.dir"] == rows[1]["reconstruction.dir"]
    assert rows[0]["stylization.dir"] != rows[1]["stylization.dir"]
    assert summary["best"]["job"] in (0, 1)
    md = (sweep / "summary.md").read_text()
    assert (
        "prompt=red" in md
        and "prompt=blue" in md
        and "clip_directional_similarity" in md
    )


@pytest.mark.slow
def test_optuna_two_trials(tmp_path):
    """A real 2-trial Optuna sweep over the λ weights, reconstruction shared between trials."""
    out = tmp_path / "out"
    proc = _cli(
        [
            "-m",
            "hydra/sweeper=lambdas_optuna",
            "hydra.sweeper.n_trials=2",
            "stage=all",
            "+prompt=red",
            f"output_root={out}",
            *TINY,
        ]
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    sweep = _sweep_dir(out)
    best = OmegaConf.load(sweep / "optimization_results.yaml")
    assert set(best.best_params) == {
        f"experiment.lambda_{k}" for k in ("global", "local", "perceptual", "reg")
    }
    summary = json.loads((sweep / "summary.json").read_text())
    rows = summary["jobs"]
    assert len(rows) == 2 and all(r["status"] == "ok" for r in rows)
    values = [r["objective"] for r in rows]
    assert best.best_value == pytest.approx(
        max(values), rel=1e-6
    )  # Optuna saw the returned objective
    assert summary["optuna"]["best_value"] == pytest.approx(best.best_value)
    lambdas = [r["overrides"] for r in rows]
    assert (
        all("experiment.lambda_perceptual=" in o for o in lambdas)
        and lambdas[0] != lambdas[1]
    )
