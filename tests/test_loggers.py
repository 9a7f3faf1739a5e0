"""logger=tensorboard|csv|wandb: event files with scalars and images, CSV kept, wandb only when installed."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.systems.loggers import build_loggers, log_images


def test_tensorboard_writes_scalars_and_images(tmp_path) -> None:
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    loggers = build_loggers({"name": "tensorboard", "csv": True}, tmp_path)
    assert [type(lg).__name__ for lg in loggers] == ["TensorBoardLogger", "CSVLogger"]
    loggers[0].log_metrics({"train/loss": 0.5}, step=3)
    img = (np.random.default_rng(0).random((8, 16, 3)) * 255).astype(np.uint8)
    log_images(loggers, "renders", [img, img], step=3)
    loggers[0].experiment.flush()
    event_dir = next((tmp_path / "tb").rglob("events.out.tfevents.*")).parent
    acc = EventAccumulator(str(event_dir), size_guidance={"images": 10})
    acc.Reload()
    assert acc.Scalars("train/loss")[0].value == pytest.approx(0.5)
    assert set(acc.Tags()["images"]) == {"renders/0", "renders/1"}
    assert acc.Images("renders/0")[0].width == 16


def test_csv_only_and_errors(tmp_path) -> None:
    assert [type(lg).__name__ for lg in build_loggers({"name": "csv"}, tmp_path)] == ["CSVLogger"]
    with pytest.raises(ConfigError, match="logger.name='mlflow': one of tensorboard, csv, wandb"):
        build_loggers({"name": "mlflow"}, tmp_path)
    if importlib.util.find_spec("wandb") is None:
        with pytest.raises(ConfigError, match="pip install wandb"):
            build_loggers({"name": "wandb"}, tmp_path)
