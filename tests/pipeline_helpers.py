"""Tiny, fast pipeline configs for end-to-end tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from nerfart_plugin.config_paths import config_dir

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
]


def tiny_cfg(out: Path, data_path: Path, *overrides: str) -> DictConfig:
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[f"output_root={out}", f"data.path={data_path}", *TINY, *overrides])


def cli_args(out: Path, data_path: Path, *overrides: str) -> list[str]:
    return [f"output_root={out}", f"data.path={data_path}", *TINY, *overrides, f"hydra.run.dir={out}/hydra"]


REPO = Path(__file__).resolve().parents[1]


def run_cli(args: list[str], timeout: int = 600, cwd: Path | None = None,
            env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -m nerfart_plugin ARGS`` in a subprocess (from the repo root by default), output captured."""
    return subprocess.run([sys.executable, "-m", "nerfart_plugin", *args], cwd=cwd or REPO, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)
