"""One record per run (``run.json``) and runs made before it: folders of the settings format 1 open, migrate and
are found again by the same settings."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from nerfart_plugin.api import open_run
from nerfart_plugin.config.compose import load_config
from nerfart_plugin.config.migrate import CONFIG_FORMAT, config_format, to_current, to_format_1
from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.guidance.style import Style
from nerfart_plugin.results.record import RECORD, RunRecord, key_in_name
from nerfart_plugin.run.factories import build_scene
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.run.stages.reconstruct import ReconstructStage
from nerfart_plugin.run.stages.stylize import StylizeStage

V1 = Path(__file__).parent / "data" / "runs_v1"
V1_RECON = "h3ds-nerf-grid-fcdae59df8f4"
V1_STYLE = "zebra-nerf-ebf1b694cf01_UNSTYLED-toy"
#: the command that made the format-1 folders (tests/data/runs_v1/README.md), as overrides
V1_SETTINGS = ["guidance=toy", "backbone=nerf", "data.resolution=24", "reconstruct.steps=10", "reconstruct.val_every=10",
               "reconstruct.batch_rays=128", "render.num_samples=8", "render.occupancy.enabled=false",
               "export.resolution=24", "stylize.steps=2", "stylize.resolution=24", "stylize.video_frames=2",
               "export.texture=false", "logger=csv", "encoding.resolution=16", "backbone.hidden_dim=16",
               "backbone.color_hidden_dim=16"]

#: folder names the code before format 2 (1ad005a) gave these settings, read off it (the stylizations with a
#: plain Style: no stamp). Not among them, and not found again: a format-1 run that switched
#: guidance.perceptual away from the guide's own network (format 1 hashed the unused network's settings too)
OLD_NAMES = [
    ([], None, "h3ds-volsdf-grid-5de7f4ec4f94", None),
    (["backbone=neus", "encoding=frequency"], None, "h3ds-neus-frequency-f47f7366e983", None),
    (["guidance=imagenet"], "brain coral", "h3ds-volsdf-grid-5de7f4ec4f94", "brain_coral-volsdf-5cbf644540fb"),
    (["guidance.precision=fp32", "stylize.steps=50"], "Joker", "h3ds-volsdf-grid-5de7f4ec4f94",
     "Joker-volsdf-7a28d8bffee8"),
    (["guidance=imagenet", "experiment=no_local", "guidance.source_top_k=3"], "zebra", "h3ds-volsdf-grid-5de7f4ec4f94",
     "zebra-volsdf-d66647647b08"),
    (["backbone=nerf", "guidance=toy", "data.resolution=32", "render.chunk=1024"], "Pixar",
     "h3ds-nerf-grid-6e6251c9ac73", "Pixar-nerf-70dcbfa225de"),
]


@pytest.fixture
def v1_root(tmp_path: Path) -> Path:
    """A copy of the format-1 run folders under a fresh output root."""
    root = tmp_path / "outputs"
    shutil.copytree(V1, root, ignore=shutil.ignore_patterns("README.md"))
    return root


@pytest.mark.parametrize("overrides,prompt,recon,style", OLD_NAMES, ids=[" ".join(c[0]) or "defaults" for c in OLD_NAMES])
def test_the_keys_of_runs_made_before_are_computed_beside_the_current_ones(tmp_path, overrides, prompt, recon, style):
    scene = build_scene(load_config([f"output_root={tmp_path}", *overrides]))
    stage = ReconstructStage(scene)
    assert stage.names[1] == recon and stage.names[0] != recon  # the current key hashes the format too
    if prompt:
        st = Style(None, None, True, "", prompt, prompt, "a photo of a person")
        assert StylizeStage(scene, st, stage.folder.final, stage.keys).names[1] == style


def test_a_folder_made_before_run_records_opens_and_says_what_it_is(v1_root):
    folder = v1_root / "stylizations" / V1_STYLE
    assert not (folder / RECORD).exists()
    run = open_run(folder, device="cpu")
    assert run.kind == "stylization" and run.config.data.name == "h3ds" and run.config.guidance.name == "toy"
    record = json.loads((folder / RECORD).read_text())  # migrated on open
    assert record["kind"] == "stylization" and record["key"] == "ebf1b694cf01" and record["config_format"] == 1
    # the outputs root moved since (metrics.json names /tmp/legacy): the source is found beside it
    assert run.source.folder == (v1_root / "reconstructions" / V1_RECON).resolve()
    assert run.source.kind == "reconstruction" and run.render(0, resolution=16)["rgb"].shape == (16, 16, 3)
    assert RunFolder(folder, "stylization").open(device="cpu").record == run.record


def test_the_same_settings_find_runs_made_before_and_reuse_them(v1_root):
    from nerfart_plugin.run.pipeline import run

    before = {p: p.stat().st_mtime_ns for p in v1_root.rglob("final.ckpt")}
    out = run(load_config([f"output_root={v1_root}", *V1_SETTINGS, "+prompt=zebra"]))
    assert Path(out["reconstruction"]["dir"]).name == V1_RECON and Path(out["stylization"]["dir"]).name == V1_STYLE
    assert sorted(p.name for p in (v1_root / "stylizations").iterdir()) == [V1_STYLE]  # nothing trained anew
    assert {p: p.stat().st_mtime_ns for p in v1_root.rglob("final.ckpt")} == before


def test_a_new_run_writes_its_record(tmp_path):
    from nerfart_plugin.run.pipeline import run

    out = run(load_config([f"output_root={tmp_path}", *V1_SETTINGS, "+prompt=zebra"]))
    recon, style = Path(out["reconstruction"]["dir"]), Path(out["stylization"]["dir"])
    assert RunRecord.read(recon).kind == "reconstruction" and RunRecord.read(recon).key == key_in_name(recon.name)
    record = RunRecord.read(style)
    assert (record.kind, record.stage, record.config_format) == ("stylization", "stylize", CONFIG_FORMAT)
    assert record.source["relative"] == f"../../reconstructions/{recon.name}"
    assert record.source_folder(style) == recon.resolve()
    assert record.produced_by["package"] == "nerfart_plugin" and record.created


def test_a_damaged_or_newer_record_is_named_with_the_fix(v1_root):
    folder = v1_root / "reconstructions" / V1_RECON
    (folder / RECORD).write_text("{not json")
    with pytest.raises(NerfArtError, match=r"run.json is damaged .* Delete it"):
        RunRecord.read(folder)
    (folder / RECORD).write_text(json.dumps({"format": 99, "kind": "reconstruction", "stage": "reconstruct",
                                             "key": "x", "produced_by": {"version": "9.0"}}))
    with pytest.raises(NerfArtError, match="upgrade the package"):
        RunRecord.read(folder)


def test_config_format_1_reads_as_the_current_layout_and_back():
    old = {"data": {"kind": "llff", "path": "x", "factor": 8},
           "guidance": {"name": "imagenet", "allow_download": False, "perceptual": "imagenet",
                        "imagenet": {"model": "lite0", "source_top_k": 5}, "lite_perceptual": {"model": "lite0"}}}
    new = to_current(old)
    assert config_format(old) == 1 and config_format(new) == CONFIG_FORMAT
    assert new["data"] == {"name": "llff", "path": "x", "factor": 8}
    assert new["guidance"] == {"name": "imagenet", "allow_download": False, "model": "lite0", "source_top_k": 5,
                               "perceptual": {"name": "imagenet", "model": "lite0"}}
    assert to_format_1(new) == old
