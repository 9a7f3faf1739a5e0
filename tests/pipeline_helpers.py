"""The one tiny-override list of the end-to-end tests, and how they compose configs and run the CLI."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import subprocess
import sys
import traceback
from pathlib import Path

from omegaconf import DictConfig

from nerfart_plugin.config.compose import load_config

#: tiny but complete runs (24 px, 16 samples): every end-to-end test starts from these
TINY = [
    "data.resolution=24",
    "render.num_samples=16",
    "render.chunk=2048",
    "render.occupancy.resolution=16",
    "reconstruct.batch_rays=256",
    "reconstruct.val_every=1000",
    "reconstruct.val_views=1",
    "reconstruct.checkpoint_every=5",
    "export.resolution=24",
    "stylize.resolution=24",
    "stylize.patch_size=16",
    "stylize.video_frames=3",
    "stylize.render_every=0",
    "trainer.log_every_n_steps=1",
    "export.texture=false",
    "logger=csv",
]


#: the same for runs without data (sweeps, the notebook): the shipped head, NeRF, toy guidance, no grid
TINY_TOY = [
    "guidance=toy",
    "backbone=nerf",
    "data.resolution=24",
    "reconstruct.steps=10",
    "reconstruct.val_every=10",
    "reconstruct.batch_rays=128",
    "render.num_samples=8",
    "render.occupancy.enabled=false",
    "export.resolution=24",
    "stylize.steps=2",
    "stylize.resolution=24",
    "stylize.video_frames=2",
]

REPO = Path(__file__).resolve().parents[1]


def composed(*overrides: str) -> DictConfig:
    """``conf/`` composed with ``overrides`` (Hydra syntax), as the CLI does."""
    return load_config(list(overrides))


def tiny_cfg(out: Path, data_path: Path, *overrides: str) -> DictConfig:
    return composed(f"output_root={out}", f"data.path={data_path}", *TINY, *overrides)


def cli_args(out: Path, data_path: Path, *overrides: str) -> list[str]:
    return [f"output_root={out}", f"data.path={data_path}", *TINY, *overrides, f"hydra.run.dir={out}/hydra"]


def cli_env(env: dict | None = None) -> dict:
    """The environment of a CLI subprocess: ``env`` as given, else this one with the checkout first on
    ``PYTHONPATH`` (the subprocess runs outside the checkout)."""
    if env is not None:
        return env
    paths = [str(REPO), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}


def run_cli_subprocess(args: list[str], timeout: int = 600, cwd: Path | None = None,
                       env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -m nerfart_plugin ARGS`` in a subprocess, output captured: for what only a real process shows
    (exit codes under signals, the installed script, another ``PYTHONPATH``). It runs in the current folder
    (the session's scratch folder, see conftest), so relative defaults (``outputs/``) stay out of the checkout."""
    return subprocess.run([sys.executable, "-m", "nerfart_plugin", *args], cwd=cwd or Path.cwd(), env=cli_env(env),
                          capture_output=True, text=True, timeout=timeout, check=False)


def run_cli(args: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``python -m nerfart_plugin ARGS`` run in this process (no interpreter and import start-up): the entry
    point with ``sys.argv`` patched, stdout / stderr captured, the logging set-up that Hydra installs undone
    afterwards, and ``SystemExit`` turned into the return code, as a subprocess would give it."""
    from nerfart_plugin.__main__ import main

    out, err = io.StringIO(), io.StringIO()
    saved = _logging_state()
    old_argv, old_cwd = sys.argv, Path.cwd()
    code = 0
    try:
        _clear_logging()  # errors before Hydra configures logging go to Python's last-resort handler (stderr)
        sys.argv = ["nerfart_plugin", *args]
        os.chdir(cwd or old_cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except BaseException:  # what the interpreter would print on its way out
                traceback.print_exc()
                code = 1
    finally:
        sys.argv = old_argv
        os.chdir(old_cwd)
        _restore_logging(saved)
    return subprocess.CompletedProcess(["nerfart_plugin", *args], code, out.getvalue(), err.getvalue())


def _logging_state() -> dict:
    loggers = [logging.root, logging.getLogger("nerfart_plugin")]
    return {lg: (list(lg.handlers), lg.level, lg.propagate, lg.disabled) for lg in loggers}


def _clear_logging() -> None:
    for lg in (logging.root, logging.getLogger("nerfart_plugin")):
        lg.handlers.clear()


def _restore_logging(saved: dict) -> None:
    for lg, (handlers, level, propagate, disabled) in saved.items():
        for h in lg.handlers:
            if h not in handlers:
                h.close()  # the run's log file
        lg.handlers[:] = handlers
        lg.level, lg.propagate, lg.disabled = level, propagate, disabled
