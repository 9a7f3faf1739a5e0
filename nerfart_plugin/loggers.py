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
from typing import Any, Optional

import numpy as np

from nerfart_plugin.errors import ConfigError

log = logging.getLogger(__name__)

LOGGERS = ("tensorboard", "csv", "wandb")


def build_loggers(cfg: Optional[dict[str, Any]], run_dir: Path) -> list[Any]:
    """Lightning loggers for a run folder from the ``logger`` config (``None``: tensorboard + csv)."""
    from lightning.pytorch.loggers import CSVLogger

    cfg = dict(cfg or {"name": "tensorboard", "csv": True})
    name = cfg.get("name", "tensorboard")
    if name not in LOGGERS:
        raise ConfigError(f"logger={name!r} is not one of {', '.join(LOGGERS)} (conf/logger/).")
    out: list[Any] = []
    if name == "tensorboard":
        if importlib.util.find_spec("tensorboard") is None and importlib.util.find_spec("tensorboardX") is None:
            raise ConfigError("logger=tensorboard needs the tensorboard package: pip install tensorboard "
                              "(a dependency of this project; reinstall it), or use logger=csv.")
        from lightning.pytorch.loggers import TensorBoardLogger

        out.append(TensorBoardLogger(str(run_dir), name="tb", default_hp_metric=False))
    elif name == "wandb":
        if importlib.util.find_spec("wandb") is None:
            raise ConfigError("logger=wandb needs the wandb package: pip install wandb (and wandb login, or "
                              "logger.mode=offline); or use logger=tensorboard.")
        from lightning.pytorch.loggers import WandbLogger

        out.append(WandbLogger(project=cfg.get("project") or "nerfart_plugin", entity=cfg.get("entity"),
                               mode=cfg.get("mode") or "online", save_dir=str(run_dir), name=run_dir.name))
    if name == "csv" or cfg.get("csv", True):
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
