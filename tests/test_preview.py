"""stage=preview: a short low-resolution stylization that tells whether a prompt will work."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image
from pipeline_helpers import run_cli, tiny_cfg

from nerfart_plugin.data.datamodule import DEFAULT_SCENE

TINY_STYLE = ["reconstruct.steps=20", "stylize.lr=0.01", "guidance=toy", "data.resolution=32"]


@pytest.mark.slow
def test_preview_writes_the_picture_and_the_scores_and_is_reused(shared_runs, caplog):
    from nerfart_plugin.run.pipeline import run

    cfg = tiny_cfg(shared_runs, DEFAULT_SCENE, *TINY_STYLE, "stage=preview", "prompt=zebra", "preview.steps=3",
                   "preview.resolution=24")
    result = run(cfg)["preview"]
    folder = Path(result["preview"]).parent
    assert folder.parent.name == "previews" and (folder / "final.ckpt").is_file()
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["steps"] == 3 and metrics["resolution"] == 24
    views = sorted((folder / "heldout").glob("stylized_*.png"))
    assert views and Image.open(views[0]).size == (24, 24)
    with Image.open(folder / "preview.png") as im:  # one row per held-out view: source | preview
        assert im.size[0] > 2 * 24 and im.size[1] >= len(views) * 24
    judge = metrics["judge"]
    assert judge["target_class"] == "zebra" and 0 <= judge["stylized"]["mean_target_prob"] <= 1
    assert result["judge"] == judge
    assert not any(folder.glob("*.mp4")) and not (folder / "mesh").exists()  # no video, no meshes
    caplog.clear()
    with caplog.at_level("INFO", logger="nerfart_plugin"):
        again = run(cfg)["preview"]  # reused, scores reported again
    assert again["judge"] == judge
    line = f"preview of 'zebra': the guide's directional similarity {metrics['clip_directional_similarity']:.3f}"
    assert line in caplog.text and "the judge's P(zebra)" in caplog.text


def test_preview_needs_a_prompt_and_a_sane_size(tmp_path):
    proc = run_cli([f"output_root={tmp_path}", "stage=preview", f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 2 and "stage=preview needs a style: add +prompt=" in proc.stdout + proc.stderr
    proc = run_cli([f"output_root={tmp_path}", "stage=preview", "+prompt=zebra", "preview.resolution=4",
                    f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 2 and "preview.resolution=4" in proc.stdout + proc.stderr
