"""Runs that never collide, never litter, never lose; checkpoints that never run code.

Locks on run folders, unwritable output roots, Ctrl-C (a real SIGINT) and resume,
incompatible checkpoints, and crafted checkpoints whose unpickling would run code.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from pipeline_helpers import REPO, cli_args, run_cli, run_cli_subprocess, tiny_cfg

from nerfart_plugin.data.datamodule import DEFAULT_SCENE
from nerfart_plugin.errors import CheckpointError, ConfigError, NerfArtError, RunInterrupted, RunLockedError
from nerfart_plugin.run.pipeline import Pipeline
from nerfart_plugin.utils.lock import lock_path

RECON_SETTINGS = ["backbone=nerf", "reconstruct.steps=12", "export.enabled=false"]
RECON = ["stage=reconstruct", *RECON_SETTINGS]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _recon_dir(root: Path, *overrides: str) -> Path:
    p = Pipeline(tiny_cfg(root, DEFAULT_SCENE, *overrides))
    p.load_data()
    return p.recon_dir


@pytest.fixture(scope="module")
def nerf_final(shared_runs) -> Path:
    """final.ckpt of a tiny NeRF reconstruction of the shipped head (12 steps), trained once per session."""
    res = Pipeline(tiny_cfg(shared_runs, DEFAULT_SCENE, *RECON)).run()
    return Path(res["reconstruction"]["dir"]) / "final.ckpt"


@pytest.mark.slow
def test_open_run_reads_a_finished_reconstruction_back(nerf_final):
    from nerfart_plugin.api import open_run

    run = open_run(nerf_final.parent, device="cpu")
    assert run.config.backbone.name == "nerf" and run.config.reconstruct.steps == 12 and "psnr" in run.metrics
    assert run.renderer.field.bound == 1.0 and run.checkpoint == nerf_final
    rays = {"rays_o": torch.tensor([[0.0, 0.0, -3.0]]), "rays_d": torch.tensor([[0.0, 0.0, 1.0]]),
            "near": torch.tensor([0.5]), "far": torch.tensor([5.0])}
    assert torch.isfinite(run.renderer.render_chunked(rays)["rgb"]).all()
    with pytest.raises(NerfArtError, match="not a run folder"):
        open_run(nerf_final.parent.parent)


def _step(ckpt: Path) -> int:
    return int(torch.load(ckpt, map_location="cpu", weights_only=True)["global_step"])


def _wait_for_checkpoint(pattern: str, root: Path, proc: subprocess.Popen, min_step: int) -> Path:
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        for found in root.glob(pattern):
            try:
                if _step(found) >= min_step:
                    return found
            except Exception:  # noqa: BLE001 - being replaced at this instant
                pass
        time.sleep(0.1)
    raise AssertionError(f"no {pattern} at step >= {min_step} before the run ended (rc={proc.poll()})")


# ---------------------------------------------------------------------- val_every=0
@pytest.mark.slow
def test_val_every_zero_trains_without_validation(tmp_path):
    res = Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON, "reconstruct.val_every=0")).run()
    run_dir = Path(res["reconstruction"]["dir"])
    assert (run_dir / "final.ckpt").exists() and not list(run_dir.glob("val/*.png"))
    assert json.loads((run_dir / "metrics.json").read_text())["val_views"] > 0  # held-out metrics after training


# ---------------------------------------------------------------------- the run-folder lock
HOLDER = """
import sys, time
from pathlib import Path
from nerfart_plugin.utils.lock import run_lock
with run_lock(Path(sys.argv[1]), None):
    print("locked", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def _hold_lock(run_dir: Path, seconds: float) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(run_dir), str(seconds)], env=ENV, cwd=REPO,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


@pytest.mark.slow
def test_a_held_run_folder_stops_or_waits_and_names_the_holder(tmp_path, caplog):
    run_dir = _recon_dir(tmp_path, *RECON)
    holder = _hold_lock(run_dir, 6.0)
    try:
        with pytest.raises(RunLockedError, match=rf"in use by process {holder.pid} on .*lock_timeout=0"):
            Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON, "lock_timeout=0")).run()
        t0 = time.time()
        with pytest.raises(RunLockedError, match=r"after waiting 1 s \(lock_timeout=1\)"):
            Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON, "lock_timeout=1")).run()
        assert 0.9 < time.time() - t0 < 30
        assert not (run_dir / "final.ckpt").exists() and not (run_dir / "last.ckpt").exists()  # nothing touched
        with caplog.at_level(logging.WARNING, logger="nerfart_plugin"):
            res = Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON)).run()  # lock_timeout=null: waits, then runs
        assert holder.poll() is not None, "ran before the holder released the folder"
        assert f"in use by process {holder.pid}" in caplog.text and "waiting until it is free" in caplog.text
        assert Path(res["reconstruction"]["dir"]) == run_dir and (run_dir / "final.ckpt").exists()
    finally:
        holder.kill()
        holder.wait()
    assert not lock_path(run_dir).with_suffix(".lock.json").exists()  # the holder note is removed on release


def test_ddp_worker_ranks_do_not_wait_for_the_lock_of_their_rank_0(tmp_path, monkeypatch):
    from nerfart_plugin.utils.lock import run_lock

    run_dir = tmp_path / "reconstructions" / "run"
    holder = _hold_lock(run_dir, 3.0)  # rank 0 of the launch holds the run folder
    try:
        monkeypatch.setenv("LOCAL_RANK", "1")  # as Lightning's launcher sets it for the worker processes
        t0 = time.time()
        with run_lock(run_dir, 0):
            assert time.time() - t0 < 1.0
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.slow
def test_two_processes_on_the_same_run_do_not_collide(tmp_path):
    """The same command twice at once: one reconstructs, the other waits for it and reuses the result."""
    over = [*RECON, "reconstruct.steps=400"]  # long enough for the second process to start meanwhile
    args = [sys.executable, "-m", "nerfart_plugin", *cli_args(tmp_path, DEFAULT_SCENE, *over)[:-1]]
    log_file = open(tmp_path / "first.log", "w")  # a file, not a pipe: a full pipe would stall the run
    first = subprocess.Popen(args + [f"hydra.run.dir={tmp_path}/h1"], cwd=REPO, env=ENV, stdout=log_file,
                             stderr=subprocess.STDOUT)
    run_dir = _recon_dir(tmp_path, *over)
    deadline = time.time() + 120
    while not lock_path(run_dir).with_suffix(".lock.json").exists() and time.time() < deadline:
        time.sleep(0.05)
    second = subprocess.run(args + [f"hydra.run.dir={tmp_path}/h2"], cwd=REPO, env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, timeout=600)
    first.wait(timeout=600)
    log_file.close()
    out1 = (tmp_path / "first.log").read_text()
    assert first.returncode == 0, out1[-2000:]
    assert second.returncode == 0, second.stdout[-2000:]
    assert f"in use by process {first.pid}" in second.stdout, second.stdout[-2000:]
    assert "reusing the cached reconstruction" in second.stdout
    assert _step(run_dir / "final.ckpt") == 400
    assert len(list((run_dir / "logs").glob("version_*"))) == 1  # trained once


# ---------------------------------------------------------------------- unwritable output roots
@pytest.mark.slow
def test_output_root_with_a_file_in_the_way_is_a_config_error(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    for root in (blocker, blocker / "runs"):
        with pytest.raises(ConfigError, match=rf"output_root={re.escape(str(root))}: {re.escape(str(blocker))} is a file"):
            Pipeline(tiny_cfg(root, DEFAULT_SCENE, *RECON))
    proc = run_cli_subprocess(["stage=reconstruct", f"output_root={blocker / 'runs'}"], timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "Traceback" not in out, out[-2000:]
    assert f"ConfigError: output_root={blocker / 'runs'}: {blocker} is a file" in out


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders (chmod does not stop it)")
def test_read_only_output_root_is_a_config_error(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(ConfigError, match="cannot write into"):
            Pipeline(tiny_cfg(ro / "runs", DEFAULT_SCENE, *RECON))
        with pytest.raises(ConfigError, match="cannot write into"):
            Pipeline(tiny_cfg(ro, DEFAULT_SCENE, *RECON))
    finally:
        ro.chmod(0o700)


def test_full_disk_is_a_config_error(tmp_path, monkeypatch):
    import shutil

    monkeypatch.setattr(shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9 - 2**20, 2**20))
    with pytest.raises(ConfigError, match=r"only 1 MiB free"):
        Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON))


# ---------------------------------------------------------------------- Ctrl-C
def _interrupt(args: list[str], pattern: str, root: Path, min_step: int) -> tuple[subprocess.CompletedProcess, Path]:
    log_file = root.parent / f"{root.name}-interrupted.log"  # a file, not a pipe: a full pipe would stall the run
    with open(log_file, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "nerfart_plugin", *args], cwd=REPO, env=ENV, stdout=fh,
                                stderr=subprocess.STDOUT)
        last = _wait_for_checkpoint(pattern, root, proc, min_step)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=300)
    out = log_file.read_text()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, out), last


def _final_state(root: Path, kind: str) -> dict[str, torch.Tensor]:
    return torch.load(next(root.glob(f"{kind}/*/final.ckpt")), map_location="cpu", weights_only=True)["state_dict"]


@pytest.mark.slow
def test_sigint_during_reconstruction_leaves_a_resumable_run(tmp_path):
    over = [*RECON, "reconstruct.steps=60", "render.occupancy.update_every=4"]
    stopped, straight = tmp_path / "stopped", tmp_path / "straight"
    proc, last = _interrupt(cli_args(stopped, DEFAULT_SCENE, *over), "reconstructions/*/last.ckpt", stopped, 10)
    assert proc.returncode == 130, proc.stderr[-3000:]
    m = re.search(r"RunInterrupted: interrupted at step (\d+); run the same command again to resume from (\S+)",
                  proc.stderr)
    assert m, proc.stderr[-3000:]
    assert Path(m.group(2)) == last and _step(last) == int(m.group(1)) < 60  # checkpoint at the step it stopped
    assert not list(stopped.glob("reconstructions/*/final.ckpt")) and "Traceback" not in proc.stderr

    for root in (stopped, straight):  # resume the interrupted run; run the other straight through
        r = run_cli(cli_args(root, DEFAULT_SCENE, *over))
        assert r.returncode == 0, r.stderr[-2000:]
        assert ("resuming the reconstruction from" in r.stdout + r.stderr) == (root == stopped)
    a, b = _final_state(stopped, "reconstructions"), _final_state(straight, "reconstructions")
    assert a.keys() == b.keys()
    for k in a:
        if a[k].is_floating_point():
            torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-5, msg=f"{k} differs after resume")


@pytest.mark.slow
def test_sigterm_stops_every_ddp_rank_within_seconds_and_the_run_resumes(tmp_path):
    """Two CPU ranks (gloo): SIGTERM to the launching process (as ``timeout`` sends it) stops both ranks at the
    same step with ``last.ckpt`` written; the same command then resumes and finishes."""
    over = [*RECON, "reconstruct.steps=120", "reconstruct.checkpoint_every=5", "trainer.devices=2",
            "trainer.strategy=ddp", "reconstruct.val_every=0"]
    args = cli_args(tmp_path, DEFAULT_SCENE, *over)
    log_file = tmp_path.parent / f"{tmp_path.name}-sigterm.log"
    with open(log_file, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "nerfart_plugin", *args], cwd=REPO, env=ENV, stdout=fh,
                                stderr=subprocess.STDOUT, start_new_session=True)
        _wait_for_checkpoint("reconstructions/*/last.ckpt", tmp_path, proc, 10)
        ranks = _children(proc.pid)
        t0 = time.time()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(os.getpgid(proc.pid), signal.SIGKILL)
    out = log_file.read_text()
    assert time.time() - t0 < 30, out[-3000:]
    deadline = time.time() + 15  # the worker rank ends its own step and exits on its own
    while any(_alive(pid) for pid in ranks) and time.time() < deadline:
        time.sleep(0.1)
    assert ranks and not any(_alive(pid) for pid in ranks), "a worker rank outlived the launcher by 15 s"
    assert proc.returncode == 130, out[-3000:]
    m = re.search(r"RunInterrupted: interrupted at step (\d+); run the same command again to resume from (\S+)", out)
    assert m and "Traceback" not in out, out[-3000:]
    assert _step(Path(m.group(2))) == int(m.group(1)) < 120
    r = run_cli_subprocess(args, cwd=REPO, env=ENV)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    assert "resuming the reconstruction from" in r.stdout + r.stderr
    assert _step(next(tmp_path.glob("reconstructions/*/final.ckpt"))) == 120


def _children(pid: int) -> list[int]:
    """The live child processes of ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
def test_sigint_during_stylization_leaves_a_resumable_run(tmp_path):
    over = ["stage=all", "guidance=toy", "+prompt=red", "backbone=nerf", "reconstruct.steps=10", "export.enabled=false",
            "stylize.steps=40", "stylize.checkpoint_every=2", "stylize.video_frames=0"]
    proc, last = _interrupt(cli_args(tmp_path, DEFAULT_SCENE, *over), "stylizations/*/last.ckpt", tmp_path, 4)
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert re.search(r"interrupted at step \d+; run the same command again to resume from \S+stylizations\S+last.ckpt",
                     proc.stderr), proc.stderr[-3000:]
    assert not list(tmp_path.glob("stylizations/*/final.ckpt"))
    r = run_cli(cli_args(tmp_path, DEFAULT_SCENE, *over))
    assert r.returncode == 0, r.stderr[-2000:]
    out = r.stdout + r.stderr
    assert "resuming the stylization from" in out and "reusing the cached reconstruction" in out
    assert _step(next(tmp_path.glob("stylizations/*/final.ckpt"))) == 40


@pytest.mark.slow
def test_ctrl_c_outside_training_is_reported_as_resumable(tmp_path, monkeypatch):
    p = Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON))

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(p, "load_data", interrupted)
    with pytest.raises(RunInterrupted, match="run the same command again"):
        p.run()


# ---------------------------------------------------------------------- incompatible checkpoints
TOY = ["guidance=toy", "prompt=red", "stylize.steps=2", "export.enabled=false", "stylize.video_frames=0"]


@pytest.mark.slow
def test_source_checkpoint_of_another_backbone_names_the_file_and_the_difference(tmp_path, nerf_final):
    for overrides, differs in ((["backbone=volsdf"], "backbone.name: 'nerf' in the checkpoint, 'volsdf' here"),
                               (["backbone=nerf", "backbone.hidden_dim=32"],
                                "backbone.hidden_dim: 64 in the checkpoint, 32 here"),
                               (["backbone=nerf", "encoding=frequency"],
                                "encoding.name: 'grid' in the checkpoint, 'frequency' here")):
        for stage in ("stylize", "export"):
            cfg = tiny_cfg(tmp_path, DEFAULT_SCENE, f"stage={stage}", *TOY, *overrides,
                           f"source_checkpoint={nerf_final}")
            with pytest.raises(CheckpointError) as info:
                Pipeline(cfg).run()
            text = str(info.value)
            assert text.startswith(f"{nerf_final} does not fit this run") and differs in text, text
            assert "source_checkpoint=" in text  # the fix
    assert not list(tmp_path.glob("stylizations/*"))  # nothing started


@pytest.mark.slow
def test_files_that_are_not_checkpoints_are_clear_errors(tmp_path):
    text = tmp_path / "notes.ckpt"
    text.write_text("not a checkpoint")
    other = tmp_path / "other.ckpt"
    torch.save({"weights": torch.zeros(3)}, other)
    for path, message in ((text, "not a PyTorch checkpoint"), (other, "not a nerfart_plugin / Lightning checkpoint")):
        with pytest.raises(CheckpointError, match=message):
            Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=stylize", *TOY, f"source_checkpoint={path}")).run()


@pytest.mark.slow
def test_foreign_and_newer_checkpoints(tmp_path, nerf_final):
    from nerfart_plugin.systems.checkpoints import load_checkpoint

    ckpt = torch.load(nerf_final, map_location="cpu", weights_only=True)
    foreign = {"state_dict": {k: v[..., :1] if v.dim() else v for k, v in ckpt["state_dict"].items()}}
    path = tmp_path / "foreign.ckpt"
    torch.save(foreign, path)
    with pytest.raises(CheckpointError, match=r"its tensors do not match this model \(.*in the checkpoint.*here.*"
                                              r"records no nerfart_plugin settings"):
        Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=export", "backbone=nerf", f"source_checkpoint={path}")).run()
    newer = dict(ckpt, nerfart={**ckpt["nerfart"], "format": 99, "version": "9.0"})
    torch.save(newer, path)
    with pytest.raises(CheckpointError, match="written by nerfart_plugin 9.0 .*upgrade"):
        load_checkpoint(path)
    assert ckpt["nerfart"]["backbone"]["name"] == "nerf" and ckpt["nerfart"]["version"]


@pytest.mark.slow
def test_an_incompatible_last_ckpt_is_not_resumed(tmp_path, nerf_final):
    import shutil

    run_dir = _recon_dir(tmp_path, *RECON, "backbone=volsdf")
    run_dir.mkdir(parents=True)
    shutil.copy(nerf_final, run_dir / "last.ckpt")
    with pytest.raises(CheckpointError, match=rf"{re.escape(str(run_dir / 'last.ckpt'))} does not fit this run: .*"
                                              r"backbone.name: 'nerf' in the checkpoint, 'volsdf' here.*resume=false"):
        Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON, "backbone=volsdf")).run()


@pytest.mark.slow
def test_checkpoints_of_version_0_1_0_with_a_scene_setup_object_still_load(tmp_path, nerf_final):
    from nerfart_plugin.data.setup import SceneSetup
    from nerfart_plugin.systems.checkpoints import load_checkpoint

    ckpt = torch.load(nerf_final, map_location="cpu", weights_only=True)
    ckpt.pop("nerfart")
    ckpt["hyper_parameters"]["setup"] = SceneSetup("object", 1.0, False, [1.0, 1.0, 1.0], False, 16, 16, True, [])
    path = tmp_path / "old.ckpt"
    torch.save(ckpt, path)
    assert isinstance(load_checkpoint(path)["hyper_parameters"]["setup"], SceneSetup)


# ---------------------------------------------------------------------- checkpoints that would run code
class _RunsCode:
    """Unpickling this runs a shell command (what a malicious checkpoint does)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _evil_checkpoint(path: Path, marker: Path, template: Path) -> Path:
    ckpt = torch.load(template, map_location="cpu", weights_only=True)
    ckpt["callbacks"] = {"payload": _RunsCode(marker)}
    torch.save(ckpt, path)
    return path


@pytest.mark.slow
def test_a_checkpoint_that_would_run_code_is_refused_and_runs_nothing(tmp_path, nerf_final):
    marker = tmp_path / "PWNED"
    evil = _evil_checkpoint(tmp_path / "evil.ckpt", marker, nerf_final)
    for stage in ("stylize", "export"):
        with pytest.raises(CheckpointError, match=r"Refusing to load .*evil.ckpt: it holds Python objects other "
                                                  r"than tensors and plain data \(.*system.*could run code"):
            Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, f"stage={stage}", *TOY, "backbone=nerf",
                              f"source_checkpoint={evil}")).run()
    assert not marker.exists()

    run_dir = _recon_dir(tmp_path, *RECON)  # the same file as the last.ckpt a run would resume from
    run_dir.mkdir(parents=True)
    _evil_checkpoint(run_dir / "last.ckpt", marker, nerf_final)
    with pytest.raises(CheckpointError, match=r"Refusing to load .*last.ckpt.*could run code"):
        Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON)).run()
    assert not marker.exists()
    # ... and the cached final.ckpt of a reconstruction, read by the stylization stage
    (run_dir / "last.ckpt").unlink()
    _evil_checkpoint(run_dir / "final.ckpt", marker, nerf_final)
    with pytest.raises(CheckpointError, match="Refusing to load"):
        Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=stylize", *TOY, *RECON_SETTINGS)).run()
    assert not marker.exists()
    torch.load(evil, weights_only=False)  # the file really runs code when loaded unsafely
    assert marker.exists()


def test_no_unsafe_deserialization_in_the_package():
    src = {p: p.read_text() for p in (REPO / "nerfart_plugin").rglob("*.py")}
    for pattern in (r"weights_only\s*=\s*False", r"allow_pickle\s*=\s*True", r"\bpickle\.loads?\(",
                    r"yaml\.load\(", r"torch\.load\((?![^)]*weights_only=True)"):
        hits = [str(p) for p, text in src.items() if re.search(pattern, text)]
        assert not hits, (pattern, hits)


def test_a_fit_projected_past_an_hour_is_announced_early(monkeypatch, caplog):
    """``preset=paper`` on a CPU is ~78 s/step: the user hears the projection after a few steps, not never."""
    import logging
    import types

    from nerfart_plugin.systems import callbacks
    from nerfart_plugin.systems.callbacks import ProjectedTime, format_duration

    clock = iter([100.0, 100.0 + 3 * 78.0])
    monkeypatch.setattr(callbacks.time, "perf_counter", lambda: next(clock))
    cb = ProjectedTime("the reconstruction", probe_steps=3)
    module = types.SimpleNamespace(device=torch.device("cpu"))
    with caplog.at_level(logging.INFO, logger="nerfart_plugin.systems.callbacks"):
        for step in (1, 2, 3, 4):
            cb.on_train_batch_end(types.SimpleNamespace(global_step=step, max_steps=100_000, is_global_zero=True),
                                  module)
    assert cb.projected_s == pytest.approx(78.0 * 99_996)
    warning = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert warning and "78.00 s/step on cpu" in warning[0].getMessage() and "90 days" in warning[0].getMessage()
    assert "preset=balanced" in warning[0].getMessage()
    assert [format_duration(s) for s in (42, 600, 7200, 10 * 86400)] == ["42 s", "10 min", "2.0 h", "10 days"]


def test_what_stylization_will_need_is_checked_before_the_reconstruction(tmp_path):
    """A missing negatives file and a prompt the guide cannot take stop the command at once, not after
    the reconstruction (which took 105 s to 3 h before they were checked at the start)."""
    from pipeline_helpers import run_cli

    for args, expected in ((["guidance=toy", "+prompt=red", "stylize.negatives=/nonexistent.txt"],
                            "/nonexistent.txt"),
                           (["guidance=imagenet", "+prompt=asdfgh qwerty"], "names no ImageNet class")):
        proc = run_cli([*args, f"output_root={tmp_path}", f"hydra.run.dir={tmp_path}/hydra"])
        assert proc.returncode == 2 and expected in proc.stdout + proc.stderr, proc.stderr[-2000:]
        assert not (tmp_path / "reconstructions").exists()


@pytest.mark.slow
def test_a_damaged_final_checkpoint_is_set_aside_and_the_run_redone(tmp_path, caplog):
    """Truncating a finished run's final.ckpt used to make the same command say "already complete";
    now the damage is found, the file kept aside, and the run trained again from its last.ckpt."""
    from pipeline_helpers import tiny_cfg

    from nerfart_plugin.data.datamodule import DEFAULT_SCENE
    from nerfart_plugin.run.pipeline import run

    cfg = tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=reconstruct", "reconstruct.steps=4", "export.enabled=false")
    folder = Path(run(cfg)["reconstruction"]["dir"])
    final = folder / "final.ckpt"
    assert (folder / "final.ckpt.sha256").read_text().strip()
    healthy = final.read_bytes()
    final.write_bytes(healthy[: len(healthy) // 2])
    with caplog.at_level(logging.WARNING, logger="nerfart_plugin"):
        again = run(cfg)
    assert "is damaged" in caplog.text and "set aside" in caplog.text
    aside = list(folder.glob("final.ckpt.damaged-*"))
    assert len(aside) == 1 and aside[0].stat().st_size == len(healthy) // 2  # kept, not deleted
    assert Path(again["reconstruction"]["dir"]) == folder and final.is_file()
    from nerfart_plugin.systems.checkpoints import checkpoint_damage

    assert checkpoint_damage(final) is None  # healthy again, with a fresh hash


def test_an_evaluation_on_training_views_is_labelled_as_such():
    import types

    from nerfart_plugin.objectives.evaluation import evaluation_views

    assert evaluation_views(types.SimpleNamespace(train_ids=[1, 2, 3], val_ids=[0], num_images=4)) == "held-out views"
    for scene in (types.SimpleNamespace(train_ids=[], val_ids=[0, 1, 2], num_images=3),  # data.holdout_every=1
                  types.SimpleNamespace(train_ids=[0], val_ids=[], num_images=1)):  # a one-view capture
        assert evaluation_views(scene).startswith("TRAINING views")


def test_a_stylization_that_lost_its_subject_says_so(caplog):
    """A stylized field whose held-out silhouette kept less than half the source's (seen: 20 toy-guided steps on a
    short reconstruction leave only background) gets a WARNING in metrics.json and the log, with what to change."""
    import logging

    from nerfart_plugin.objectives.evaluation import LOST_SUBJECT_IOU, lost_subject

    with caplog.at_level(logging.WARNING, logger="nerfart_plugin"):
        text = lost_subject(0.0)
    assert "lost its subject: silhouette IoU 0.00" in text and "stylize.lr" in text and text in caplog.text
    assert lost_subject(LOST_SUBJECT_IOU) is None and lost_subject(0.97) is None and lost_subject(None) is None


@pytest.mark.parametrize("flag", [["--cfg", "job"], ["--cfg", "all"], ["-c", "hydra"]])
def test_printing_the_config_validates_it_as_a_run_does(tmp_path, flag):
    """``--cfg`` prints the config a run would use: a typo or a bad value is refused (exit 2), as the run would."""
    bad = run_cli([f"output_root={tmp_path}", "render.num_sampels=3", *flag])
    assert bad.returncode == 2 and "did you mean render.num_samples" in bad.stdout + bad.stderr
    good = run_cli([f"output_root={tmp_path}", "render.num_samples=3", *flag])
    assert good.returncode == 0


@pytest.mark.slow
def test_sigterm_outside_training_ends_as_ctrl_c_does(tmp_path):
    """SIGTERM while rendering (no training loop to stop gracefully): the same one-line RunInterrupted message and
    exit code as Ctrl-C, no traceback."""
    assert run_cli(cli_args(tmp_path, DEFAULT_SCENE, *RECON)).returncode == 0
    recon = _recon_dir(tmp_path, *RECON)
    log_file = tmp_path / "render.log"
    with open(log_file, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "nerfart_plugin", "stage=render", f"render.run={recon}",
                                 "render.frames=2000", "render.resolution=32", f"output_root={tmp_path}",
                                 f"hydra.run.dir={tmp_path}/hydra"], cwd=REPO, env=ENV, stdout=fh,
                                stderr=subprocess.STDOUT)
        deadline = time.time() + 240
        while "rendering orbit" not in log_file.read_text() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)
    out = log_file.read_text()
    assert proc.returncode == RunInterrupted.exit_code, out[-2000:]
    assert "RunInterrupted: interrupted" in out and "Traceback" not in out


@pytest.mark.slow
def test_two_exports_of_one_output_do_not_write_it_at_once(tmp_path):
    """stage=export holds a lock on what it writes: a second export of the same run and strength waits (or, with
    lock_timeout=0, stops naming the holder) instead of writing the same files at the same time (the reuse of what
    the first wrote: test_splats.test_stage_export_writes_splats_and_records_their_fit)."""
    Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON)).run()
    first = Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON_SETTINGS, "stage=export")).run()["export"]
    holder = _hold_lock(Path(first["mesh"]), 30.0)
    try:
        with pytest.raises(RunLockedError, match=rf"in use by process {holder.pid}"):
            Pipeline(tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON_SETTINGS, "stage=export", "lock_timeout=0")).run()
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.slow
def test_every_reader_of_a_run_checks_its_checkpoint_as_reuse_does(tmp_path):
    """render, export, mix, the viewer and open_run verify a run's final.ckpt against its stored hash, with the
    message and the recovery of a reused run (one byte changed: the file still loads, the hash says otherwise)."""
    from nerfart_plugin.api import open_run

    cfg = tiny_cfg(tmp_path, DEFAULT_SCENE, *RECON)
    folder = Path(Pipeline(cfg).run()["reconstruction"]["dir"])
    final = folder / "final.ckpt"
    data = bytearray(final.read_bytes())
    data[len(data) // 2] ^= 0xFF
    final.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"final.ckpt is damaged \(its content does not match final.ckpt.sha256"):
        open_run(folder, device="cpu")
    proc = run_cli([f"output_root={tmp_path}", "stage=render", f"render.run={folder}", "render.frames=2",
                    f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 2 and "is damaged" in proc.stdout + proc.stderr and "Traceback" not in proc.stderr


#: (module, arguments, what the one-line answer names): a bad argument to each entry point
BAD_ARGUMENTS = [
    ("nerfart_plugin", ["bogus_key=3"], "bogus_key=3: unknown setting"),
    ("nerfart_plugin", ["render.num_samples=banana"], "render.num_samples='banana'"),
    ("nerfart_plugin", ["--bogus"], "unrecognized arguments: --bogus"),
    ("nerfart_plugin.viewer", ["somewhere", "--bogus"], "unrecognized arguments: --bogus"),
    ("nerfart_plugin.viewer", ["/nonexistent/run"], "/nonexistent/run does not exist"),
    ("nerfart_plugin.viewer", ["/nonexistent/run", "--port", "70000"], "--port 70000"),
    ("nerfart_plugin.viewer.mesh", ["/nonexistent/mesh.ply"], "/nonexistent/mesh.ply"),
    ("nerfart_plugin.data.download", ["nosuch"], "no sample named 'nosuch'"),
    ("nerfart_plugin.data.style_pictures", ["nosuch"], "no picture nosuch"),
    ("benchmarks", ["nosuch"], "no benchmark 'nosuch'"),
    ("benchmarks", ["preview", "--bogus"], "unrecognized arguments: --bogus"),
]


@pytest.mark.slow
@pytest.mark.parametrize("module,args,named", BAD_ARGUMENTS, ids=[f"{m} {' '.join(a)}" for m, a, _ in BAD_ARGUMENTS])
def test_every_entry_point_answers_a_bad_argument_with_one_line_and_exit_2(tmp_path, module, args, named):
    """Exit 2 and a line naming what is wrong, no traceback, never a hang (the timeout is a hang guard only)."""
    extra = [f"output_root={tmp_path}", f"hydra.run.dir={tmp_path}/hydra"] if module == "nerfart_plugin" else []
    proc = subprocess.run([sys.executable, "-m", module, *args, *extra], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-2000:]
    assert named in out and "Traceback" not in out, out[-2000:]
