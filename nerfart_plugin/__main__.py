"""Hydra entry point: ``python -m nerfart_plugin [overrides]``.

Examples::

    python -m nerfart_plugin +backbone=neus +prompt=Joker
    python -m nerfart_plugin backbone=volsdf prompt="Tolkien Elf" stage=reconstruct
    python -m nerfart_plugin -m backbone=neus,volsdf +prompt=Joker,Pixar
    python -m nerfart_plugin --cfg job          # print the composed config
    python -m nerfart_plugin --help             # groups and options

Hydra 1.3 refuses ``+key=value`` when ``key`` already has a default (the groups
``backbone``, ``data``, ... and keys such as ``prompt``) with "Multiple values
for ..." / "Could not append to config". Users naturally type ``+prompt=Joker``,
so :func:`normalize_overrides` folds that ``+`` into a plain override before
Hydra parses the command line. ``++`` (force-add) is left alone.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from nerfart_plugin.config_paths import config_dir, primary_keys


def normalize_overrides(argv: list[str], known: set[str]) -> list[str]:
    """Turn ``+key=value`` into ``key=value`` for keys that already have a default."""
    out = []
    for arg in argv:
        if arg.startswith("+") and not arg.startswith("++") and "=" in arg:
            key = arg[1:].split("=", 1)[0]
            root = key.split(".", 1)[0].split("@", 1)[0]
            if key in known or root in known:
                arg = arg[1:]
        out.append(arg)
    return out


@hydra.main(config_path=str(config_dir()), config_name="config", version_base="1.3")
def _app(cfg: DictConfig) -> float | None:
    """Run the pipeline; return the sweep objective (see :func:`nerfart_plugin.sweep.objective`).

    Hydra ignores the return value of a plain run; a sweeper such as Optuna
    (``hydra/sweeper=lambdas_optuna``) maximizes it. ``None`` (a failed job, or a
    stage without a metric such as ``stage=export``) counts as a failed trial.
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from nerfart_plugin.errors import ConfigError, NerfArtError
    from nerfart_plugin.pipeline import run
    from nerfart_plugin.sweep import objective
    from nerfart_plugin.utils.io import atomic_write_json

    try:
        results = run(cfg)
    except NerfArtError as exc:
        # The project's own errors already say what is wrong and how to fix it: no traceback.
        logging.getLogger("nerfart_plugin").error("%s: %s", type(exc).__name__, exc)
        hc = HydraConfig.get()
        if hc.mode == RunMode.MULTIRUN:  # keep the sweep going; the summary shows the failure
            atomic_write_json(Path(hc.runtime.output_dir) / "result.json", {"error": f"{type(exc).__name__}: {exc}"})
            return None
        sys.exit(2)
    try:
        return objective(results, OmegaConf.select(cfg, "objective", default="auto"))
    except ConfigError as exc:
        logging.getLogger("nerfart_plugin").debug("no sweep objective: %s", exc)
        return None


def main() -> None:
    sys.argv = [sys.argv[0], *normalize_overrides(sys.argv[1:], primary_keys())]
    _app()


if __name__ == "__main__":
    main()
