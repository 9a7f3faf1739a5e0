"""stage=preview: a short, small version of the full run (its first steps where the sizes agree), with a verdict
on the prompt and a picture to check it by."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from PIL import Image
from pipeline_helpers import run_cli, tiny_cfg

from nerfart_plugin.data.datamodule import DEFAULT_SCENE
from nerfart_plugin.run.stages.preview import PICTURE_LONG_SIDE

TINY_STYLE = ["reconstruct.steps=20", "stylize.lr=0.01", "guidance=toy", "data.resolution=32"]


@pytest.mark.slow
def test_preview_writes_the_picture_and_the_scores_and_is_reused(shared_runs, caplog, monkeypatch):
    from nerfart_plugin.run.pipeline import run
    from nerfart_plugin.run.stages.preview import CALIBRATION, Calibration

    cfg = tiny_cfg(shared_runs, DEFAULT_SCENE, *TINY_STYLE, "stage=preview", "prompt=zebra", "preview.steps=3",
                   "preview.resolution=24")
    result = run(cfg)["preview"]
    folder = Path(result["preview"]).parent
    assert folder.parent.name == "previews" and (folder / "final.ckpt").is_file()
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["steps"] == 3 and metrics["resolution"] == 24
    views = sorted((folder / "heldout").glob("stylized_*.png"))
    assert views and Image.open(views[0]).size == (24, 24)
    with Image.open(folder / "preview.png") as im:  # one row per held-out view: source | preview, drawn larger
        assert 2 * PICTURE_LONG_SIDE <= im.size[0] < 3 * PICTURE_LONG_SIDE
        assert im.size[1] >= len(views) * PICTURE_LONG_SIDE
    judge = metrics["judge"]
    assert judge["target_class"] == "zebra" and 0 <= judge["stylized"]["mean_target_prob"] <= 1
    assert result["judge"] == judge
    assert not any(folder.glob("*.mp4")) and not (folder / "mesh").exists()  # no video, no meshes
    caplog.clear()
    with caplog.at_level("INFO", logger="nerfart_plugin"):
        again = run(cfg)["preview"]  # reused, scores reported again
    assert again["judge"] == judge
    assert metrics["verdict"]["verdict"] == "uncalibrated"  # the toy guide has no calibration
    assert "preview of 'zebra': uncalibrated (the verdict is calibrated for guidance=imagenet" in caplog.text
    assert "the judge's P(zebra)" in caplog.text
    # calibrated again since (here: the toy guide gains thresholds): a reused preview says the new verdict
    monkeypatch.setitem(CALIBRATION, "toy", Calibration("toy", likely=-1.0, unlikely=-2.0, steps=3, strength=1.0,
                                                        silhouette=5.0, resolution=24, record="a test's"))
    assert run(cfg)["preview"]["verdict"] == "likely to work"
    assert json.loads((folder / "metrics.json").read_text())["verdict"]["verdict"] == "likely to work"


def test_preview_needs_a_prompt_and_a_sane_size(tmp_path):
    proc = run_cli([f"output_root={tmp_path}", "stage=preview", f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 2 and "stage=preview needs a style: add +prompt=" in proc.stdout + proc.stderr
    proc = run_cli([f"output_root={tmp_path}", "stage=preview", "+prompt=zebra", "preview.resolution=4",
                    f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 2 and "preview.resolution=4" in proc.stdout + proc.stderr


def test_the_verdict_reads_the_calibrated_thresholds():
    from nerfart_plugin.run.stages.preview import CALIBRATION, verdict

    cal = CALIBRATION["imagenet"]
    assert verdict(cal.likely, "imagenet")["verdict"] == "likely to work"
    assert verdict(cal.likely - 1e-6, "imagenet")["verdict"] == "uncertain: run it"
    assert verdict(cal.unlikely, "imagenet")["verdict"] == "uncertain: run it"
    assert verdict(cal.unlikely - 1e-6, "imagenet")["verdict"] == "unlikely to work"
    assert cal.unlikely <= cal.likely
    out = verdict(0.3, "clip")
    assert out["verdict"] == "uncalibrated" and out["score"] == 0.3 and "guidance=imagenet" in out["why"]
    assert verdict(None, "imagenet")["verdict"] == "uncalibrated"
    assert f"{cal.likely:.3f}" in verdict(0.9, "imagenet")["why"]
    assert verdict(0.9, "imagenet", cal.steps, cal.strength)["verdict"] == "likely to work"
    other = verdict(0.9, "imagenet", cal.steps + 5, cal.strength)
    assert other["verdict"] == "uncalibrated" and f"preview.steps={cal.steps}" in other["why"]
    assert verdict(0.9, "imagenet", cal.steps, cal.strength + 0.5)["verdict"] == "uncalibrated"
    assert verdict(0.9, "imagenet", cal.steps, cal.strength, cal.silhouette, cal.resolution)["verdict"] == \
        "likely to work"
    assert verdict(0.9, "imagenet", cal.steps, cal.strength, cal.silhouette, 256)["verdict"] == "uncalibrated"
    held_less = verdict(0.9, "imagenet", cal.steps, cal.strength, 0.0)
    assert held_less["verdict"] == "uncalibrated" and "preview.lambda_silhouette=" in held_less["why"]


def test_the_preview_holds_the_outline_unless_told_not_to(tmp_path):
    """The preview's steps carry the silhouette term at preview.lambda_silhouette (or the full run's own weight,
    where that is larger); 0 leaves the full run's start as it is."""
    from nerfart_plugin.config.validate import parse_config
    from nerfart_plugin.run.stages.preview import PREVIEW_LONG_SIDE, preview_scene

    class Scene:  # the part of a SceneContext preview_scene reads and writes
        scene = SimpleNamespace(height=256, width=192)

        def __init__(self, *overrides: str) -> None:
            self.cfg, self.plain = parse_config(tiny_cfg(tmp_path, DEFAULT_SCENE, "prompt=zebra", *overrides))

        def with_config(self, plain: dict) -> "Scene":
            out = Scene.__new__(Scene)
            out.cfg, out.plain = parse_config(plain)
            return out

    assert preview_scene(Scene()).cfg.experiment.lambda_silhouette == 5.0
    assert preview_scene(Scene("preview.lambda_silhouette=0")).cfg.experiment.lambda_silhouette == 0.0
    assert preview_scene(Scene("experiment.lambda_silhouette=8")).cfg.experiment.lambda_silhouette == 8.0
    assert Scene().cfg.experiment.lambda_silhouette == 0.0  # the full run's own: the paper's (off)
    full_size = Scene("stylize.resolution=auto")  # the images' long side: 256
    assert preview_scene(full_size).cfg.stylize.resolution == PREVIEW_LONG_SIDE
    assert preview_scene(Scene("stylize.resolution=96")).cfg.stylize.resolution == 96  # never larger
    assert preview_scene(Scene("preview.resolution=200")).cfg.stylize.resolution == 200


@pytest.mark.slow
def test_the_preview_is_the_full_runs_start_and_shows_the_full_run_once_it_exists(shared_runs):
    """The preview's field after N steps is a full run's after N steps (the same views, seeds and schedule;
    nothing in a stylization depends on its total steps); preview.png gains the full run's column when the
    preview is asked for again after that run finished."""
    import torch

    from nerfart_plugin.run.pipeline import run

    base = [*TINY_STYLE, "prompt=zebra", "stylize.resolution=24", "stylize.video_frames=0", "export.enabled=false",
            "stylize.steps=3"]
    preview_cfg = tiny_cfg(shared_runs, DEFAULT_SCENE, *base, "stage=preview", "preview.steps=3", "preview.strength=1",
                           "preview.lambda_silhouette=0")
    preview = Path(run(preview_cfg)["preview"]["preview"]).parent

    def picture() -> tuple[int, bool]:
        with Image.open(preview / "preview.png") as im:
            return im.size[0], json.loads((preview / "metrics.json").read_text())["picture_has_full_run"]

    narrow, has_full = picture()
    assert not has_full
    full = Path(run(tiny_cfg(shared_runs, DEFAULT_SCENE, *base, "stage=stylize"))["stylization"]["dir"])
    a = torch.load(preview / "final.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    b = torch.load(full / "final.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    run(preview_cfg)  # reused: the picture is drawn again with the full run's views
    wide, has_full = picture()
    assert has_full and wide > narrow * 1.4
    dialed = Path(run(tiny_cfg(shared_runs, DEFAULT_SCENE, *base, "stage=preview", "preview.steps=3",
                               "preview.strength=1.5", "preview.lambda_silhouette=0"))["preview"]["preview"]).parent
    assert dialed != preview and dialed.name.startswith(preview.name.split("_")[0]) and "-s1.50" in dialed.name
    assert json.loads((dialed / "metrics.json").read_text())["strength"] == 1.5


@pytest.mark.slow
def test_a_preview_without_a_reconstruction_says_it_trains_one_first(tmp_path, caplog):
    from nerfart_plugin.run.pipeline import run

    cfg = tiny_cfg(tmp_path, DEFAULT_SCENE, *TINY_STYLE, "stage=preview", "prompt=zebra", "preview.steps=1",
                   "stylize.resolution=16")
    with caplog.at_level("WARNING", logger="nerfart_plugin"):
        run(cfg)
    assert "a preview starts from the reconstruction of this capture, which is not made yet" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="nerfart_plugin"):
        run(cfg)  # the reconstruction exists now: no such warning
    assert "not made yet" not in caplog.text
