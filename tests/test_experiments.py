"""Ablation presets and presets compose to the intended λ weights and settings."""

from __future__ import annotations

import pytest
from pipeline_helpers import composed as _compose

PAPER = {"lambda_dir": 1.0, "lambda_global": 0.2, "lambda_local": 0.1, "lambda_perceptual": 2.0, "lambda_reg": 0.1}


@pytest.mark.parametrize(
    "name,changed",
    [
        ("full", {}),
        ("no_contrastive", {"lambda_global": 0.0, "lambda_local": 0.0}),
        ("no_local", {"lambda_local": 0.0}),
        ("no_global", {"lambda_global": 0.0}),
        ("no_reg", {"lambda_reg": 0.0}),
        ("absolute_dir", {"lambda_global": 0.0, "lambda_local": 0.0}),
    ],
)
def test_experiment_lambdas(name: str, changed: dict) -> None:
    exp = _compose(f"experiment={name}").experiment
    assert exp.name == name
    for k, v in {**PAPER, **changed}.items():
        assert exp[k] == pytest.approx(v), k
    assert exp.directional == ("absolute" if name == "absolute_dir" else "relative")


def test_command_line_beats_preset() -> None:
    assert _compose("preset=paper", "render.num_samples=7").render.num_samples == 7


def test_ddp_settings_reach_the_trainer_and_stylize_refuses_them() -> None:
    from nerfart_plugin.config.validate import parse_config
    from nerfart_plugin.errors import ConfigError
    from nerfart_plugin.run.pipeline import check_stage

    def validate_config(c):
        check_stage(parse_config(c)[0])

    cfg = _compose("stage=reconstruct", "trainer.strategy=ddp", "trainer.devices=4", "trainer.num_nodes=2")
    validate_config(cfg)  # allowed for the reconstruction stage
    with pytest.raises(ConfigError, match="stage=reconstruct only"):
        validate_config(_compose("stage=all", "prompt=Joker", "trainer.strategy=ddp"))


def test_trainer_gets_strategy_devices_nodes(tmp_path) -> None:
    import torch

    from nerfart_plugin.run.fit import build_trainer

    t = build_trainer(3, torch.device("cpu"), {"strategy": "auto", "devices": 1, "num_nodes": 1,
                                                "precision": "32-true", "log_every_n_steps": 1}, run_dir=tmp_path)
    assert t.max_steps == 3 and t.num_nodes == 1 and t.world_size == 1
