"""The one tiny-override list of the end-to-end tests, and how they compose configs and run the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from omegaconf import DictConfig

from nerfart_plugin.factories import load_config

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


def run_cli(args: list[str], timeout: int = 600, cwd: Path | None = None,
            env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -m nerfart_plugin ARGS`` in a subprocess, output captured. It runs in the current folder
    (the session's scratch folder, see conftest), so relative defaults (``outputs/``) stay out of the checkout."""
    return subprocess.run([sys.executable, "-m", "nerfart_plugin", *args], cwd=cwd or Path.cwd(), env=cli_env(env),
                          capture_output=True, text=True, timeout=timeout, check=False)
