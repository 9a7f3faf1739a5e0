"""The strength dial and style mixing (nerfart_plugin.results.blend, api.Run.with_strength, api.mix, strength=)."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from pipeline_helpers import run_cli, tiny_cfg

from nerfart_plugin.data.datamodule import DEFAULT_SCENE
from nerfart_plugin.errors import ConfigError, NerfArtError
from nerfart_plugin.results.blend import blend_states, blend_tag, check_strength, check_weights


def test_blend_states_is_the_weighted_delta_and_copies_what_it_must_not_blend():
    src = {"w": torch.tensor([1.0, 2.0]), "occupancy.score": torch.tensor([0.5]), "steps": torch.tensor(3),
           "occupancy.occupied": torch.tensor([True])}
    a = {"w": torch.tensor([3.0, 2.0]), "occupancy.score": torch.tensor([0.9]), "steps": torch.tensor(7),
         "occupancy.occupied": torch.tensor([False])}
    b = {**a, "w": torch.tensor([1.0, 6.0])}
    out = blend_states(src, [a, b], [0.5, 0.25])
    torch.testing.assert_close(out["w"], torch.tensor([2.0, 3.0]))
    assert out["occupancy.score"] == 0.5 and out["steps"] == 3 and bool(out["occupancy.occupied"])  # not blended
    torch.testing.assert_close(blend_states(src, [a], [1.5])["w"], torch.tensor([4.0, 2.0]))  # past the run
    with pytest.raises(ConfigError, match="run 0 has no tensor 'w' of shape"):
        blend_states(src, [{**a, "w": torch.zeros(3)}], [1.0])


def test_strength_and_weights_outside_their_range_are_config_errors():
    assert [check_strength(s) for s in (0, 1, 2, "0.5")] == [0.0, 1.0, 2.0, 0.5]
    for bad in (-0.1, 2.01, float("nan"), "abc", None):
        with pytest.raises(ConfigError, match=r"strength=.*pick a value in \[0, 2\]"):
            check_strength(bad)
    assert check_weights([0.5, -1, 2], 3) == [0.5, -1.0, 2.0]
    with pytest.raises(ConfigError, match="2 run\\(s\\) and 1 weight"):
        check_weights([0.5], 2)
    with pytest.raises(ConfigError, match=r"mix weight 1 = 2.5: each weight must lie in \[-1, 2\]"):
        check_weights([0.5, 2.5], 2)
    assert [blend_tag(w) for w in ([1.0], [0.5])] == ["", "-s0.50"]
    a_b, a_c = blend_tag([0.5, 0.25], ["runs/a", "runs/b"]), blend_tag([0.5, 0.25], ["runs/a", "runs/c"])
    assert a_b.startswith("-mix0.50_0.25-") and a_b != a_c  # two mixes at the same weights never share a name


# ---------------------------------------------------------------------- on trained runs
STYLE = ["guidance=toy", "reconstruct.steps=20", "stylize.steps=4", "stylize.lr=0.01", "export.enabled=false"]


@pytest.fixture(scope="module")
def styles(shared_runs) -> dict[str, Path]:
    """Two toy stylizations of one tiny reconstruction of the shipped head, and one of another (seed 1)."""
    from nerfart_plugin.run.pipeline import run

    out = {}
    for name, extra in (("red", ["prompt=red"]), ("blue", ["prompt=blue"]), ("other", ["prompt=red", "seed=1"])):
        out[name] = Path(run(tiny_cfg(shared_runs, DEFAULT_SCENE, *STYLE, *extra))["stylization"]["dir"])
    return out


def _state_equal(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k].to(sa[k].device)) for k in sa)


@pytest.mark.slow
def test_strength_zero_is_the_source_one_is_the_run_and_beyond_gets_its_own_grid(styles):
    from nerfart_plugin.api import open_run
    from nerfart_plugin.results.blend import refresh_occupancy

    run = open_run(styles["red"], device="cpu")
    zero, one, past = run.with_strength(0.0), run.with_strength(1.0), run.with_strength(1.5)
    assert _state_equal(zero.renderer, run.source.renderer) and _state_equal(one.renderer, run.renderer)
    assert np.array_equal(one.render(3)["rgb"], run.render(3)["rgb"])  # s = 1: the run exactly
    assert not _state_equal(past.renderer, run.renderer)
    # s > 1: the grid is estimated for the blended field, not copied from either side
    grid = past.renderer.occupancy
    assert not torch.equal(grid.score, run.renderer.occupancy.score)
    expected = copy.deepcopy(grid)

    class Holder(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.field, self.occupancy = past.renderer.field, expected

    refresh_occupancy(Holder())
    assert torch.equal(expected.occupied, grid.occupied)
    img = past.render(3)["rgb"]
    assert np.isfinite(img).all() and not np.array_equal(img, run.render(3)["rgb"])
    assert past.tag == "-s1.50" and zero.tag == "-s0.00" and one.tag == ""
    with pytest.raises(NerfArtError, match="not to a blend"):
        past.with_strength(0.5)
    with pytest.raises(NerfArtError, match="not to a reconstruction"):
        run.source.with_strength(0.5)
    with pytest.raises(ConfigError, match="strength=2.5"):
        run.with_strength(2.5)


@pytest.mark.slow
def test_mixing_stylizations_of_one_source_and_refusing_others(styles):
    from nerfart_plugin.api import mix, open_run

    red, blue, other = (open_run(styles[k], device="cpu") for k in ("red", "blue", "other"))
    assert _state_equal(mix([red, blue], [1.0, 0.0]).renderer, red.renderer)  # one run at 1: that run
    assert _state_equal(mix([red, blue], [0.0, 0.0]).renderer, red.source.renderer)  # none: the source
    half = mix([red, blue], [0.5, 0.5])
    sr, sb, sh, s0 = (r.state_dict() for r in (red.renderer, blue.renderer, half.renderer, red.source.renderer))
    name = next(k for k in sh if sh[k].is_floating_point() and not k.startswith("occupancy.")
                and not torch.equal(sr[k], s0[k]))
    torch.testing.assert_close(sh[name], s0[name] + 0.5 * (sr[name] - s0[name]) + 0.5 * (sb[name] - s0[name]))
    assert half.tag.startswith("-mix0.50_0.50-") and math.isfinite(float(half.render(2)["rgb"].mean()))
    with pytest.raises(ConfigError, match=r"different sources: .*final.ckpt and .*final.ckpt differ in content"):
        mix([red, other], [0.5, 0.5])


@pytest.mark.slow
def test_render_and_export_stages_take_the_strength_and_keep_each_strength_apart(styles, tmp_path):
    run = styles["red"]
    common = [f"output_root={tmp_path}", "stage=render", f"render.run={run}", "render.frames=2", "render.resolution=24",
              f"hydra.run.dir={tmp_path}/hydra"]
    for strength in ("0.5", "1.0"):
        proc = run_cli([*common, f"strength={strength}"])
        assert proc.returncode == 0, proc.stderr[-3000:]
    assert (run / "render" / "orbit-2f-24x24-s0.50" / "rgb-s0.50_UNSTYLED-toy.mp4").is_file()
    assert (run / "render" / "orbit-2f-24x24" / "rgb_UNSTYLED-toy.mp4").is_file()
    proc = run_cli([*common, "strength=2.5"])
    assert proc.returncode == 2 and "strength" in proc.stdout + proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli([f"output_root={tmp_path}", "stage=export", f"source_checkpoint={run / 'final.ckpt'}",
                    "export.resolution=24", "export.texture=false", "strength=0.5", "guidance=toy",
                    f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (run / "mesh" / "export-final-r24-s0.50.ply").is_file()


@pytest.mark.slow
def test_render_and_export_stages_mix_runs_into_the_first_runs_folder(styles, tmp_path):
    red, blue = styles["red"], styles["blue"]
    mix_args = [f"mix.runs=[{red},{blue}]", "mix.weights=[0.5,0.5]", f"output_root={tmp_path}",
                f"hydra.run.dir={tmp_path}/hydra"]
    proc = run_cli(["stage=render", "render.frames=2", "render.resolution=24", *mix_args])
    assert proc.returncode == 0, proc.stderr[-3000:]
    tag = blend_tag([0.5, 0.5], [str(red), str(blue)])
    assert (red / "render" / f"orbit-2f-24x24{tag}" / f"rgb{tag}_UNSTYLED-toy.mp4").is_file()
    proc = run_cli(["stage=export", "export.resolution=24", "export.texture=false", *mix_args])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (red / "mesh" / f"export-final-r24{tag}.ply").is_file()
    proc = run_cli(["stage=render", f"mix.runs=[{red},{styles['other']}]", "mix.weights=[0.5,0.5]",
                    f"output_root={tmp_path}", f"hydra.run.dir={tmp_path}/hydra"])
    assert proc.returncode == 2 and "different sources" in proc.stdout + proc.stderr


def test_mix_settings_are_checked_before_any_work():
    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.config.validate import parse_config

    def issues(*overrides: str) -> str:
        with pytest.raises(ConfigError) as exc:
            parse_config(load_config(overrides))
        return str(exc.value)

    assert "one weight per run of mix.runs (2 run(s))" in issues("stage=render", "mix.runs=[a,b]", "mix.weights=[0.5]")
    text = issues("stage=all", "mix.runs=[a]", "mix.weights=[0.5]", "strength=0.5")
    assert "strength=0.5: with mix.runs" in text and "add stage=render or stage=export" in text
    assert "mix.weights=[3]" in issues("stage=export", "mix.runs=[a]", "mix.weights=[3]")


@pytest.mark.slow
def test_a_run_records_what_each_auto_setting_became(styles):
    """The stylization's metrics.json names a concrete value for every setting that was ``auto`` in its config,
    except those that other outputs record (stage=render's resolution, a sweep's objective, a preview's resolution,
    the matched layers of a style picture, which this run has not)."""
    import json

    import yaml
    from test_auto import _auto_keys

    from nerfart_plugin.guidance import default_negative_threshold
    from nerfart_plugin.guidance.toy import ToyGuidance
    from nerfart_plugin.utils.device import pick_device

    run = styles["red"]
    block = json.loads((run / "metrics.json").read_text())["auto"]
    was_auto = _auto_keys(yaml.safe_load((run / "config.yaml").read_text())) - {"render.resolution", "objective",
                                                                            "preview.resolution", "style_image.layers"}
    assert set(block) == was_auto
    assert all(v is not None and v != "auto" for v in block.values()), block
    assert block["device"] == str(pick_device()) and block["trainer.strategy"] == "SingleDeviceStrategy"
    assert block["stylize.negative_threshold"] == default_negative_threshold(ToyGuidance())
    assert block["stylize.negatives"].startswith("package: ") and block["source_prompt"] == "a photo of a person"
    assert "data.resolution" not in block and "stylize.resolution" not in block  # the command set them (TINY)
    assert block["encoding.levels"] >= 1 and 128 <= block["encoding.resolution"] <= 512


@pytest.mark.slow
def test_the_gallery_script_draws_a_row_per_run(styles, tmp_path):
    """``docs/make_gallery.py``: source | stylized | geometry per run, from the runs' own renders."""
    import runpy

    from PIL import Image

    from nerfart_plugin.api import open_run

    make = runpy.run_path(str(Path(__file__).resolve().parents[1] / "docs" / "make_gallery.py"))
    out = make["make_gallery"]([styles["red"], styles["blue"]], tmp_path / "gallery.png")
    img = np.asarray(Image.open(out))
    side = open_run(styles["red"], device="cpu").resolution
    assert img.shape[:2] == (2 * side + 2, 3 * side + 2 * 2)  # 2 rows x 3 tiles, 2 px gaps
    red, blue = img[:side, side + 2:2 * side + 2], img[side + 2:, side + 2:2 * side + 2]
    assert not np.array_equal(red, blue)  # each row is its own run
    with pytest.raises(SystemExit):
        make["main"](["--runs", str(tmp_path / "nothing")])
    labelled = np.asarray(Image.open(make["make_gallery"]([styles["red"]], tmp_path / "l.png", ["no_global"])))
    assert not np.array_equal(labelled[:, side + 2:2 * side + 2], img[:side, side + 2:2 * side + 2])  # its own label
    with pytest.raises(SystemExit):  # one label per run
        make["main"](["--runs", str(styles["red"]), str(styles["blue"]), "--labels", "full"])


@pytest.mark.slow
def test_the_viewer_benchmark_takes_a_frame_apart(styles):
    """``benchmarks/viewer.py``'s breakdown of a frame: the march's samples, how many carry weight, the sampler and
    the field timed apart, and cheaper settings with their distance from the default frame."""
    from benchmarks import viewer

    b = viewer.frame_breakdown(styles["red"], side=32, repeats=1)
    assert b["rays"] == 32 * 32 and 0 < b["rays_hitting"] <= b["rays"]
    assert 0 < b["samples_marched"] <= b["samples_evaluated"] <= b["rays"] * b["samples_per_ray"]
    assert 0.0 <= b["share_weighted"] <= 1.0
    assert all(b[k] > 0 for k in ("frame_s", "sampler_s", "field_s"))
    assert [(v["stop_transmittance"], v["samples_per_ray"]) for v in b["variants"]] == [
        (1e-2, b["samples_per_ray"]), (1e-4, 12)]
    assert all(math.isfinite(v["psnr_vs_default"]) for v in b["variants"])
    text = "\n".join(viewer.breakdown_lines(b))
    assert "the field alone sets a lower bound" in text and "PSNR vs the default frame" in text


@pytest.mark.slow
def test_the_strength_benchmark_dials_shape_and_colour_apart(styles):
    """``benchmarks/strength.py``'s other parameterizations: the colour net at one strength, the shape's tensors
    (what ``stylize.freeze_geometry`` freezes) at another, with the grid estimated for the result."""
    from benchmarks import strength
    from nerfart_plugin.api import open_run

    run = open_run(styles["red"], device="cpu")
    colour = {id(p) for p in run.renderer.field.color_parameters()}
    colour_names = {n for n, p in run.renderer.named_parameters() if id(p) in colour}
    assert colour_names
    blended = strength.part_blend(run, 1.5, 1.0)
    got, trained, src = blended.renderer.state_dict(), run.renderer.state_dict(), run.source.renderer.state_dict()
    for k in colour_names:  # the colour net as trained
        torch.testing.assert_close(got[k], trained[k])
    shape = [k for k in got if k not in colour_names and not k.startswith("occupancy.") and got[k].is_floating_point()
             and not torch.equal(trained[k], src[k])]
    assert shape and all(torch.allclose(got[k], src[k] + 1.5 * (trained[k] - src[k]), atol=1e-6) for k in shape)
    assert blended.weights == (1.0,) and blended.renderer is not run.renderer


@pytest.mark.slow
def test_the_strength_benchmark_sets_the_dial_beside_training(tmp_path):
    """``benchmarks/strength.py --vs-training``: the stylization trained again with snapshots, each dial strength set
    beside the snapshot of the closest judge score, with how much of the source each keeps; a finished run in the
    root (no snapshots taken) is refused."""
    from pipeline_helpers import TINY

    from benchmarks import strength
    from nerfart_plugin.objectives.evaluation import ImageNetJudge

    overrides = [f"output_root={tmp_path}", f"data.path={DEFAULT_SCENE}", *TINY, *STYLE, "prompt=zebra"]
    v = strength.dial_vs_training("zebra", overrides, ImageNetJudge(), every=2)
    assert sorted(v["trained_p"]) == [2, 4] and v["steps"] == 4
    assert [p["s"] for p in v["pairs"]] == list(strength.VS_TRAINING_STRENGTHS)
    for pair in v["pairs"]:
        assert pair["step"] in v["trained_p"] and pair["training"]["p"] == v["trained_p"][pair["step"]]
        for side in ("dial", "training"):
            assert set(pair[side]) == {"p", "psnr_to_source", "edges_to_source", "consistency", "displacement"}
    text = "\n".join(strength.vs_training_lines(v))
    assert "### The dial versus training (zebra)" in text and "training, step" in text and "dial s = 0.5" in text
    with pytest.raises(SystemExit, match="already finished"):
        strength.train_with_snapshots(overrides, 2)
