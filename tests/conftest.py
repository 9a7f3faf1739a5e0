"""Shared fixtures: the real data in ../shared/data, a quiet, deterministic torch, a scratch working
folder (nothing is written into the checkout), ``shared_runs`` and ``no_network``.

Under pytest-xdist (``-n 2``, the default in pyproject.toml) each worker takes its share of the cores
for torch (and for the CLI subprocesses it starts), so two workers do not fight over two cores.
"""

from __future__ import annotations

import os
import socket
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


def pytest_configure(config: pytest.Config) -> None:
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        threads = max(1, (os.cpu_count() or 1) // workers)
        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)  # the subprocesses this worker starts


@pytest.fixture(scope="session")
def shared_runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One output root for the whole session, shared by the xdist workers: tests that train the same tiny run
    find it in the run cache (the run folder's lock makes a second worker wait for the first, then reuse).
    A test that changes a run copies its folder first."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared-runs"
    root.mkdir(exist_ok=True)
    return root


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


def _tree(path: Path) -> set[str]:
    """Paths under ``path``, except ``benchmarks/``: the benchmarks' own output roots, which a benchmark
    running beside the tests writes (the tests' benchmark runs go to NERFART_BENCH_SCRATCH / tmp)."""
    if not path.is_dir():
        return set()
    return {str(p.relative_to(path)) for p in path.rglob("*") if p.relative_to(path).parts[0] != "benchmarks"}


@pytest.fixture(autouse=True, scope="session")
def _scratch_cwd(tmp_path_factory):
    """Run the session in a scratch folder: relative defaults (``output_root=outputs``, Hydra's run
    folder, the benchmarks' quick reports via ``NERFART_BENCH_SCRATCH``) land under tmp, never in the
    checkout; the checkout's ``outputs/`` must be unchanged at the end."""
    before = _tree(REPO / "outputs")
    old_cwd, old_env = Path.cwd(), os.environ.get("NERFART_BENCH_SCRATCH")
    scratch = tmp_path_factory.mktemp("cwd")
    os.chdir(scratch)
    os.environ["NERFART_BENCH_SCRATCH"] = str(scratch / "benchmarks")
    yield scratch
    os.chdir(old_cwd)
    if old_env is None:
        os.environ.pop("NERFART_BENCH_SCRATCH", None)
    else:
        os.environ["NERFART_BENCH_SCRATCH"] = old_env
    added = sorted(_tree(REPO / "outputs") - before)
    assert not added, f"tests wrote into the checkout's outputs/: {added[:10]}"


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch):
    """Downloads disabled; any attempt to open a socket or call the HF hub fails the test
    (recorded and asserted at teardown, so attempts from helper threads count too)."""
    from nerfart_plugin.guidance import weights as wts

    monkeypatch.delenv(wts.ALLOW_DOWNLOAD_ENV, raising=False)
    attempts: list[tuple] = []

    def boom(*a, **k):
        attempts.append(a)
        raise OSError("network disabled in this test")

    monkeypatch.setattr(socket, "create_connection", boom)
    try:
        import huggingface_hub
        import open_clip.pretrained
    except ImportError:  # pragma: no cover - both come with open_clip
        pass
    else:
        monkeypatch.setattr(huggingface_hub, "hf_hub_download", boom)
        monkeypatch.setattr(open_clip.pretrained, "hf_hub_download", boom)
    yield attempts
    assert not attempts, f"network access attempted although downloads are disabled: {attempts}"
