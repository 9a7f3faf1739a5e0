"""End-to-end: reconstruction fits, caches are keyed right, runs resume after SIGKILL, toy stylization works."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from pipeline_helpers import cli_args, tiny_cfg

from nerfart_plugin.errors import TrainingDivergedError
from nerfart_plugin.run.pipeline import Pipeline
from nerfart_plugin.systems.callbacks import check_finite_losses

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small_head(tmp_path_factory, shared_data) -> Path:
    """A copy of 8 views of the real head (images, mattes, cameras) to keep runs short and editable."""
    src = shared_data / "girl"
    dst = tmp_path_factory.mktemp("head")
    shutil.copytree(src / "images", dst / "images")
    shutil.copytree(src / "matte", dst / "matte")
    shutil.copy(src / "cameras.npz", dst / "cameras.npz")
    return dst


def _losses(run_dir: Path, key: str = "train/loss_rgb") -> list[float]:
    rows = list(csv.DictReader(open(next(run_dir.glob("logs/version_*/metrics.csv")))))
    return [float(r[key]) for r in rows if r.get(key)]


RECON = ["backbone=nerf", "reconstruct.steps=100"]


@pytest.fixture(scope="module")
def shared_root(shared_runs) -> Path:
    """The session's output root: later tests (on either xdist worker) reuse the cached reconstruction."""
    return shared_runs


def test_reconstruction_loss_drops_and_cache_is_reused(shared_root: Path, small_head: Path) -> None:
    tmp_path = shared_root
    over = ["stage=reconstruct", *RECON]
    p = Pipeline(tiny_cfg(tmp_path, small_head, *over))
    res = p.run()
    run_dir = Path(res["reconstruction"]["dir"])
    losses = _losses(run_dir)
    assert len(losses) >= 50
    first, last = sum(losses[:10]) / 10, sum(losses[-10:]) / 10
    assert last < 0.7 * first, f"rgb loss did not drop: {first:.4f} -> {last:.4f}"
    assert (run_dir / "final.ckpt").exists() and (run_dir / "metrics.json").exists()
    mtime = (run_dir / "final.ckpt").stat().st_mtime_ns

    # same data + backbone + settings: reused, not recomputed
    p2 = Pipeline(tiny_cfg(tmp_path, small_head, *over))
    p2.load_data()
    assert p2.recon_dir == run_dir
    assert p2.reconstruct() == run_dir / "final.ckpt"
    assert (run_dir / "final.ckpt").stat().st_mtime_ns == mtime

    # a changed setting -> another folder
    p3 = Pipeline(tiny_cfg(tmp_path, small_head, *over, "reconstruct.lr=0.02"))
    p3.load_data()
    assert p3.recon_dir != run_dir


def test_cache_invalidated_when_data_changes(tmp_path: Path, small_head: Path) -> None:
    data = tmp_path / "scene"
    shutil.copytree(small_head, data)
    p = Pipeline(tiny_cfg(tmp_path, data, "stage=reconstruct"))
    p.load_data()
    before = p.recon_dir
    img = sorted((data / "images").iterdir())[0]
    raw = bytearray(img.read_bytes())
    from PIL import Image

    im = Image.open(img).convert("RGB")
    im.putpixel((0, 0), (0, 255, 0))
    im.save(img, quality=95)
    p2 = Pipeline(tiny_cfg(tmp_path, data, "stage=reconstruct"))
    p2.load_data()
    assert p2.recon_dir != before, "edited image must change the reconstruction key"
    assert bytes(raw) != img.read_bytes()


def _final_state(run_root: Path) -> dict[str, torch.Tensor]:
    ckpt = next(run_root.glob("reconstructions/*/final.ckpt"))
    return torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]


def test_killed_run_resumes_to_the_same_result(tmp_path: Path, small_head: Path) -> None:
    over = ["stage=reconstruct", "backbone=nerf", "reconstruct.steps=40", "render.occupancy.update_every=4"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "nerfart_plugin"]
    killed, straight = tmp_path / "killed", tmp_path / "straight"

    proc = subprocess.Popen(cmd + cli_args(killed, small_head, *over), cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    last = None
    while time.time() < deadline and proc.poll() is None:
        found = list(killed.glob("reconstructions/*/last.ckpt"))
        if found:
            step = torch.load(found[0], map_location="cpu", weights_only=True)["global_step"]
            if step >= 15:
                last = found[0]
                break
        time.sleep(0.2)
    assert last is not None and proc.poll() is None, "run finished or never checkpointed before the kill"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not list(killed.glob("reconstructions/*/final.ckpt"))
    ck = torch.load(last, map_location="cpu", weights_only=True)  # the last complete checkpoint is readable
    assert 15 <= ck["global_step"] < 40

    for root in (killed, straight):  # resume the killed run; run the other straight through
        r = subprocess.run(cmd + cli_args(root, small_head, *over), cwd=REPO, env=env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
    a, b = _final_state(killed), _final_state(straight)
    assert a.keys() == b.keys()
    for k in a:
        if a[k].is_floating_point():
            torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-5, msg=f"{k} differs after resume")
        else:
            assert torch.equal(a[k], b[k]), k


def test_export_stage_writes_meshes_in_every_format(shared_root: Path, small_head: Path) -> None:
    over = ["stage=export", *RECON, "export.level=0.5", "export.formats=[ply,obj,glb]"]
    p = Pipeline(tiny_cfg(shared_root, small_head, *over))
    p.load_data()
    if not (p.recon_dir / "final.ckpt").exists():
        Pipeline(tiny_cfg(shared_root, small_head, "stage=reconstruct", *RECON)).run()
    res = Pipeline(tiny_cfg(shared_root, small_head, *over)).run()
    stem = Path(res["export"]["mesh"])
    for ext in ("ply", "obj", "glb"):
        assert stem.with_suffix(f".{ext}").stat().st_size > 0
    import trimesh

    mesh = trimesh.load(stem.with_suffix(".ply"), force="mesh")
    assert len(mesh.vertices) == res["export"]["vertices"] > 0


def test_out_of_memory_names_the_settings_to_lower(monkeypatch) -> None:
    from nerfart_plugin.errors import NerfArtError
    from nerfart_plugin.run.fit import run_fit

    class Boom:
        def fit(self, *a, **k):
            raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")

    with pytest.raises(NerfArtError, match="stylize.patch_size") as info:
        run_fit(Boom(), None)
    assert "render.chunk" in str(info.value) and "stylize.resolution" in str(info.value)


def test_toy_stylization_toward_red_makes_renders_redder(shared_root: Path, small_head: Path) -> None:
    tmp_path = shared_root
    over = ["stage=all", "guidance=toy", "prompt=red", *RECON,
            "stylize.steps=25", "stylize.lr=0.01", "stylize.lr_mlp=0.005"]
    res = Pipeline(tiny_cfg(tmp_path, small_head, *over)).run()
    sty_dir = Path(res["stylization"]["dir"])
    assert sty_dir.name.endswith("_UNSTYLED-toy")
    import json

    m = json.loads((sty_dir / "metrics.json").read_text())
    assert m["guidance_is_real"] is False and "WARNING" in m
    red = lambda rgb: rgb[0] - 0.5 * (rgb[1] + rgb[2])
    assert red(m["mean_rgb"]) > red(m["mean_rgb_source"]) + 0.03, (m["mean_rgb"], m["mean_rgb_source"])
    # the perceptual loss (Eq. 9) keeps the structure: same run without it drifts further (cached reconstruction)
    res0 = Pipeline(tiny_cfg(tmp_path, small_head, *over, "experiment.lambda_perceptual=0")).run()
    m0 = json.loads((Path(res0["stylization"]["dir"]) / "metrics.json").read_text())
    assert m["edge_similarity"] > m0["edge_similarity"], (m["edge_similarity"], m0["edge_similarity"])
    assert m["clip_directional_similarity"] > 0
    assert list(sty_dir.glob("video_UNSTYLED-toy.mp4"))
    assert (sty_dir / "final.ckpt").exists()


def test_nan_loss_stops_with_a_diagnostic() -> None:
    terms = {"rgb": torch.tensor(0.1), "eikonal": torch.tensor(float("nan"))}
    with pytest.raises(TrainingDivergedError, match="eikonal"):
        check_finite_losses(terms, 7, "reconstruct")
