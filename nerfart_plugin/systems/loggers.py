"""Experiment loggers as a Hydra group (``logger=tensorboard|csv|wandb``) and image logging for any of them.

* ``tensorboard`` (default): Lightning's ``TensorBoardLogger`` under ``<run>/tb``; scalars and
  the periodic render pairs (:func:`log_images`);
* ``csv``: ``CSVLogger`` under ``<run>/logs`` (what every logger keeps too with ``csv: true``);
* ``wandb``: ``WandbLogger``, only when the ``wandb`` package is installed (a clear ConfigError
  otherwise); the project never needs it.
"""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from nerfart_plugin.config.schema import LoggerConfig
from nerfart_plugin.config.validate import section
from nerfart_plugin.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from nerfart_plugin.config.schema import LoggerConfig

log = logging.getLogger(__name__)



def build_loggers(cfg: "LoggerConfig | dict[str, Any] | None", run_dir: Path) -> list[Any]:
    """Lightning loggers for a run folder from the ``logger`` section (a :class:`LoggerConfig` or a dict of
    its keys; ``None``: its defaults, tensorboard + csv)."""
    from lightning.pytorch.loggers import CSVLogger


    c = section(LoggerConfig, cfg)
    out: list[Any] = []
    if c.name == "tensorboard":
        if importlib.util.find_spec("tensorboard") is None and importlib.util.find_spec("tensorboardX") is None:
            raise ConfigError("logger=tensorboard needs the tensorboard package: pip install tensorboard "
                              "(a dependency of this project; reinstall it), or use logger=csv.")
        from lightning.pytorch.loggers import TensorBoardLogger

        out.append(TensorBoardLogger(str(run_dir), name="tb", default_hp_metric=False))
    elif c.name == "wandb":
        if importlib.util.find_spec("wandb") is None:
            raise ConfigError("logger=wandb needs the wandb package: pip install wandb (and wandb login, or "
                              "logger.mode=offline); or use logger=tensorboard.")
        from lightning.pytorch.loggers import WandbLogger

        out.append(WandbLogger(project=c.project, entity=c.entity, mode=c.mode, save_dir=str(run_dir),
                               name=run_dir.name))
    if c.name == "csv" or c.csv:
        out.append(CSVLogger(str(run_dir), name="logs"))
    return out


def log_images(loggers: list[Any], tag: str, images: list[np.ndarray], step: int) -> None:
    """Log uint8 images [H,W,3] (e.g. source | stylized) to the loggers that take images
    (TensorBoard: ``add_image`` per image; W&B: ``log_image``); the CSV logger skips them."""
    for lg in loggers:
        kind = type(lg).__name__
        if kind == "TensorBoardLogger":
            for i, img in enumerate(images):
                lg.experiment.add_image(f"{tag}/{i}", np.ascontiguousarray(img), global_step=step, dataformats="HWC")
        elif kind == "WandbLogger":
            lg.log_image(key=tag, images=list(images), step=step)
