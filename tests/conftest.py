"""Shared fixtures: the real data in ../shared/data and a quiet, deterministic torch."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NERFART_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to the real captures (``../shared/data``); skips the test when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (set NERFART_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


@pytest.fixture(autouse=True)
def _project_loggers_propagate():
    """In-process Hydra/Lightning/benchmark runs reconfigure logging (benchmarks raise the project's
    level to ERROR, dictConfig may disable loggers); keep the project's loggers visible to caplog."""
    import logging

    for name, lg in list(logging.root.manager.loggerDict.items()):
        if isinstance(lg, logging.Logger) and name.split(".")[0] == "nerfart_plugin":
            lg.disabled = False
            lg.propagate = True
            lg.setLevel(logging.NOTSET)
    yield
