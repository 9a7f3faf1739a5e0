"""Hydra entry point: ``python -m nerfart_plugin [overrides]``.

Examples::

    python -m nerfart_plugin +backbone=neus +prompt=Joker
    python -m nerfart_plugin backbone=volsdf +prompt="Van Gogh's Starry Night" stage=reconstruct
    python -m nerfart_plugin -m backbone=neus,volsdf +prompt=Joker +prompt="jack-o'-lantern"
    python -m nerfart_plugin --cfg job          # print the composed config
    python -m nerfart_plugin --help             # groups and options

Before Hydra parses the command line, :func:`normalize_overrides`
(:mod:`nerfart_plugin.config.overrides`) quotes prompt text for Hydra's grammar (any
prompt works; repeat ``+prompt=`` to sweep several) and folds ``+key`` into a
plain override where Hydra 1.3 would refuse it (a key that already has a default).
"""

from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from nerfart_plugin.config.compose import config_dir
from nerfart_plugin.config.overrides import PrimaryConfig, normalize_overrides, override_value  # noqa: F401
from nerfart_plugin.config.plugins import searchpath_overrides
from nerfart_plugin.config.schema import RunConfig
from nerfart_plugin.errors import ConfigError, NerfArtError, RunInterrupted
from nerfart_plugin.run import sweep
from nerfart_plugin.run.sweep import objective
from nerfart_plugin.utils.io import atomic_write_json, check_writable_dir

log = logging.getLogger("nerfart_plugin")


@hydra.main(config_path=str(config_dir()), config_name="config", version_base="1.3")
def _app(cfg: DictConfig) -> float | None:
    """Run the pipeline; return the sweep objective (see :func:`nerfart_plugin.run.sweep.objective`).

    Hydra ignores the return value of a plain run; a sweeper such as Optuna
    (``hydra/sweeper=lambdas_optuna``) maximizes it. ``None`` (a failed job, or a
    stage without a metric such as ``stage=export``) counts as a failed trial.
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    # the training stack and the viewer (torch, Lightning, viser) load here, so that --help and a bad argument
    # answer without them
    from nerfart_plugin.run.pipeline import run
    from nerfart_plugin.viewer.live import live_viewer

    try:
        results = run(cfg, output_dir=Path(HydraConfig.get().runtime.output_dir), live=live_viewer)
    except (RunInterrupted, KeyboardInterrupt) as exc:
        # Ctrl-C: the run folder is resumable; say so and stop (a sweep too), exit code 130 as for SIGINT
        message = str(exc) if isinstance(exc, RunInterrupted) else "interrupted; run the same command again to continue"
        log.error("RunInterrupted: %s", message)
        sys.exit(RunInterrupted.exit_code)
    except NerfArtError as exc:
        # The project's own errors already say what is wrong and how to fix it: no traceback.
        log.error("%s: %s", type(exc).__name__, exc)
        hc = HydraConfig.get()
        if hc.mode == RunMode.MULTIRUN:  # keep the sweep going; the summary shows the failure
            atomic_write_json(Path(hc.runtime.output_dir) / "result.json", {"error": f"{type(exc).__name__}: {exc}"})
            return None
        sys.exit(exc.exit_code)
    try:
        return objective(results, cfg.objective)
    except ConfigError as exc:
        log.debug("no sweep objective: %s", exc)
        return None


#: flags with which Hydra runs no job (nothing is written)
_NO_JOB_FLAGS = ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i", "--shell-completion", "-sc",
                 "--version")


def check_output_root(argv: list[str]) -> None:
    """ConfigError before Hydra writes its run folder under ``output_root`` when that cannot be written
    (a read-only folder, a file in the way, a missing parent that cannot be created, a full disk)."""

    if any(a in _NO_JOB_FLAGS for a in argv):
        return
    root = override_value(argv, "output_root")
    if root is None:
        root = RunConfig.model_fields["output_root"].default
    if isinstance(root, str) and "${" not in root:
        check_writable_dir(root, "output_root", create=False)


#: flags of a sweep: its overrides hold value lists that only the sweeper expands
_SWEEP_FLAGS = ("-m", "--multirun")
#: flags with which Hydra prints help or information and runs nothing
_HELP_FLAGS = tuple(f for f in _NO_JOB_FLAGS if f not in ("--cfg", "-c"))


def check_settings(argv: list[str]) -> None:
    """The command's settings validated before the training stack loads (a typo or a bad value answers in about a
    second, exit 2); with ``--cfg`` (job, hydra, all) the config Hydra would print is validated too, so that a typo
    is not printed with exit 0. Sweeps are left to the sweep's own checks; anything that fails to compose here
    for another reason is left to Hydra's own message."""
    printing = any(a in ("--cfg", "-c") or a.startswith("--cfg=") for a in argv)
    if not printing and any(a in _SWEEP_FLAGS + _HELP_FLAGS for a in argv):
        return
    from hydra.errors import HydraException

    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.config.validate import parse_config

    try:
        cfg = load_config([a for a in argv if "=" in a and not a.startswith(("-", "hydra."))])
    except HydraException:
        return
    parse_config(cfg)


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM (a scheduler's time limit, ``timeout``, ``kill``) outside training ends the run as Ctrl-C does: the
    same message and exit code (in training, :class:`~nerfart_plugin.systems.callbacks.GracefulInterrupt` stops at the
    end of the step first)."""
    raise KeyboardInterrupt


def main() -> None:
    signal.signal(signal.SIGTERM, _terminate)
    try:
        argv = normalize_overrides(sys.argv[1:])
        argv += searchpath_overrides(argv)  # config groups of installed plugins (nerfart_plugin.config.plugins)
        check_output_root(argv)
        check_settings(argv)
    except ConfigError as exc:  # before Hydra configures logging: Python's last-resort handler prints it to stderr
        log.error("ConfigError: %s", exc)
        sys.exit(2)
    sys.argv = [sys.argv[0], *argv]
    sweep.failed_jobs.clear()
    _app()
    if sweep.failed_jobs:  # a multirun kept going past failed jobs; schedulers and scripts see it in the exit code
        log.error("%d sweep job(s) failed: %s (their errors are in the sweep's summary.md)", len(sweep.failed_jobs),
                  ", ".join(map(str, sweep.failed_jobs)))
        sys.exit(1)


def _exit_interrupted_at_once() -> None:
    """``python -m``'s exit after an interrupt: logs and streams flushed, then exit 130 without the interpreter's
    finalization. With a normal exit, a SIGTERM that lands while the compiler's modules import ended the process
    killed by SIGINT (-2) one time and with 130 the next (CPython's own handling of a KeyboardInterrupt it has seen;
    seen under ``-m`` only, never when the same code runs as a script). Finished work is on disk already
    (checkpoints and caches are written atomically); the compiler's worker processes exit with their parent."""
    import os

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(RunInterrupted.exit_code)


if __name__ == "__main__":
    try:
        main()
    except SystemExit as exc:
        if exc.code == RunInterrupted.exit_code:
            _exit_interrupted_at_once()
        raise
