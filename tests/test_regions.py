"""Regions: the file, the set operations, the composite at m = 0 and m = 1, masks lifted on a scene with a known
answer, and a regional stylization that leaves the outside unchanged."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from pipeline_helpers import TINY, composed
from render_helpers import front_view, tiny_renderer

from nerfart_plugin.api import Region, open_run
from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.config.validate import parse_config
from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.fields.analytic import DensityFromSDF, SphereSDF, UnionSDF
from nerfart_plugin.fields.composite import CompositeField, RegionMask
from nerfart_plugin.rendering import VolumeRenderer

POINTS = np.random.default_rng(0).uniform(-1.5, 1.5, (4000, 3))


def test_a_region_file_round_trips(tmp_path):
    region = (Region.box([0, 0.2, 0], [0.5, 0.3, 0.4], rotation=[0, 30, 10], feather=0.05)
              | Region.ellipsoid([0.5, 0, 0], [0.2, 0.3, 0.2])).subtract(Region.box([0, 0, 0], [0.1, 0.1, 0.1]))
    region = region.with_margin(0.07)
    back = Region.load(region.save(tmp_path / "region.npz"))
    assert back.content_hash == region.content_hash and back.margin == 0.07
    np.testing.assert_array_equal(back.mask(POINTS, 0.02), region.mask(POINTS, 0.02))
    grid = Region.grid(np.random.default_rng(1).uniform(0, 1, (5, 6, 7)), np.diag([2.0, 2.0, 2.0, 1.0]))
    back = Region.load(grid.invert().save(tmp_path / "grid.npz"))
    np.testing.assert_allclose(back.mask(POINTS, 0.02), grid.invert().mask(POINTS, 0.02))
    assert Region.box([0, 0, 0], [1, 1, 1]).content_hash != Region.box([0, 0, 0], [1, 1, 1.01]).content_hash


def test_bad_region_values_are_refused_naming_the_file_and_the_field(tmp_path):
    with pytest.raises(ConfigError, match="half_sizes"):
        Region.box([0, 0, 0], [0.5, -1, 0.5])
    with pytest.raises(ConfigError, match="center"):
        Region.ellipsoid([0, 0], [1, 1, 1])
    with pytest.raises(ConfigError, match="rotation"):
        Region.box([0, 0, 0], [1, 1, 1], rotation=[[1, 0, 0], [0, 2, 0], [0, 0, 1]])
    path = Region.box([0, 0, 0], [1, 1, 1]).save(tmp_path / "r.npz")
    spec = {"format": 1, "region": {"op": "box", "center": [0, 0, 0], "half_sizes": [1, float("nan"), 1]}}
    np.savez(path, region=np.frombuffer(json.dumps(spec).encode(), dtype=np.uint8))
    with pytest.raises(DataError, match=r"r\.npz: region half_sizes"):
        Region.load(path)
    (tmp_path / "not.npz").write_text("hello")
    with pytest.raises(DataError, match=r"not\.npz is not a region file"):
        Region.load(tmp_path / "not.npz")
    with pytest.raises(DataError, match="does not exist"):
        Region.load(tmp_path / "missing.npz")
    with pytest.raises(ConfigError, match=r"\.npz"):
        Region.box([0, 0, 0], [1, 1, 1]).save(tmp_path / "region.json")


def test_set_operations_and_the_feather():
    a, b = Region.box([0, 0, 0], [0.5, 0.5, 0.5], feather=0.0), Region.ellipsoid([0.5, 0, 0], [0.3, 0.3, 0.3], feather=0.0)
    pts = np.array([[0, 0, 0], [0.7, 0, 0], [0.45, 0, 0], [1.2, 0, 0]], dtype=float)
    assert (a.mask(pts, 0.1) == [1, 0, 1, 0]).all() and (b.mask(pts, 0.1) == [0, 1, 1, 0]).all()
    assert ((a | b).mask(pts, 0.1) == [1, 1, 1, 0]).all() and ((a - b).mask(pts, 0.1) == [1, 0, 0, 0]).all()
    assert ((a & b).mask(pts, 0.1) == [0, 0, 1, 0]).all() and ((~a).mask(pts, 0.1) == [0, 1, 0, 1]).all()
    soft = Region.box([0, 0, 0], [0.5, 0.5, 0.5], feather=0.2)  # the edge ramps outward over the feather
    np.testing.assert_allclose(soft.mask(np.array([[0.5, 0, 0], [0.6, 0, 0], [0.7, 0, 0]]), 0.1), [1.0, 0.5, 0.0],
                               atol=1e-6)
    turned = Region.box([0, 0, 0], [1.0, 0.1, 0.1], rotation=[0, 0, 90], feather=0.0)  # its long side along y
    assert turned.mask(np.array([[0, 0.9, 0], [0.9, 0, 0]]), 0.1).tolist() == [1.0, 0.0]


def test_a_bound_region_reads_its_masks_and_its_dilated_geometry():
    cams = SimpleCameras(np.eye(4))
    mask = Region.box([0, 0, 0], [0.3, 0.3, 0.3], feather=0.0).with_margin(0.2).bind(cams.field_to_world, 1.0, 41)
    colour, geometry = mask(torch.tensor([[0.0, 0, 0], [0.4, 0, 0], [0.8, 0, 0]]))
    assert colour.tolist() == [1.0, 0.0, 0.0] and geometry.tolist() == [1.0, 1.0, 0.0]
    inverted = (~Region.box([0, 0, 0], [0.3, 0.3, 0.3], feather=0.0)).bind(cams.field_to_world, 1.0, 41)
    assert inverted(torch.tensor([[5.0, 5.0, 5.0]]))[0].item() == 1.0  # beyond the grid: everywhere but the box


class SimpleCameras:
    """The frame part of CaptureCameras: the field's frame is the world scaled by ``T``."""

    def __init__(self, T: np.ndarray) -> None:
        self.normalization, self.ndc = T, False

    field_to_world = CaptureCameras.field_to_world


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
def test_the_composite_is_the_source_at_m_0_and_the_part_at_m_1(backbone):
    """Exactly: where the mask is 0 the composite renders the source's pixels, where it is 1 the part's, with and
    without grad (the training render and the no-grad march)."""
    torch.manual_seed(0)
    source, part = tiny_renderer(backbone, occupancy=0), tiny_renderer(backbone, occupancy=0)
    view = front_view(12, 10, 12.0)
    far_away = Region.box([50, 50, 50], [1, 1, 1]).bind(SimpleCameras(np.eye(4)).field_to_world, 1.0, 16)
    for mask, expected in ((RegionMask.everywhere(1.0), part), (far_away, source)):
        composite = source.with_field(CompositeField(source.field, [(part.field, 1.0, mask)]))
        for render in (lambda r: r(view)["rgb"], lambda r: r.render_chunked(view)["rgb"]):
            assert torch.equal(render(composite), render(expected))


def test_masks_lifted_into_the_field_find_the_masked_object(tmp_path):
    """Two spheres; masks of one of them in three views where it is not hidden (what a user outlines is what a
    view shows) select it, not the other."""
    field = DensityFromSDF(UnionSDF(SphereSDF(0.25, (-0.45, 0.0, 0.0)), SphereSDF(0.25, (0.45, 0.0, 0.0))))
    renderer = VolumeRenderer(field, num_samples=64)
    alone = VolumeRenderer(DensityFromSDF(SphereSDF(0.25, (-0.45, 0.0, 0.0))), num_samples=64)
    c2ws = [torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.5]]),
            torch.tensor([[0.0, 0, 1, -2.5], [0, 1, 0, 0], [-1, 0, 0, 0]]),  # from -x: the masked sphere in front
            torch.tensor([[1.0, 0, 0, 0], [0, 0, -1, 2.5], [0, 1, 0, 0]])]
    K = np.array([[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]])
    cams = CaptureCameras(np.stack([c.numpy() for c in c2ws]), np.stack([K] * 3), 32, 32, np.full(3, 1.0),
                          np.full(3, 4.0), "object", False, np.diag([0.5, 0.5, 0.5, 1.0]), [0, 1, 2],
                          ["a.png", "b.png", "c.png"])
    folder = tmp_path / "masks"
    _write_masks(folder, alone, cams)
    run = type("Run", (), {"renderer": renderer, "cameras": cams, "device": torch.device("cpu")})()
    region = Region.from_masks(run, folder, resolution=24)
    world = lambda p: cams.field_to_world(np.asarray(p, dtype=float))  # noqa: E731
    assert region.mask(world([[-0.45, 0.0, 0.25], [-0.7, 0.0, 0.0]]), 0.1).min() == 1.0  # the masked sphere's surface
    assert region.mask(world([[0.45, 0.0, 0.25], [0.7, 0.0, 0.0], [0.0, 0.0, 0.0]]), 0.1).max() == 0.0


def _write_masks(folder: Path, alone: VolumeRenderer, cams: CaptureCameras) -> None:
    from PIL import Image

    from nerfart_plugin.cameras.path import scaled_K
    from nerfart_plugin.data.rays import camera_batch

    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(cams.names):
        batch = camera_batch(scaled_K(cams, [i], 32, 32)[0], torch.as_tensor(cams.c2w[i], dtype=torch.float32), 32, 32,
                             1.0, 4.0, False)
        with torch.no_grad():
            opacity = alone.render_chunked(batch)["opacity"].reshape(32, 32)
        Image.fromarray(((opacity > 0.5).numpy() * 255).astype(np.uint8)).save(folder / name)


def test_the_cli_keys_of_a_region(tmp_path):
    path = Region.box([0, 0, 0], [1, 1, 1]).save(tmp_path / "r.npz")
    run, plain = parse_config(composed(f"region={path}"))
    assert str(run.region.file) == str(path) and run.region.given
    run, _ = parse_config(composed("region.box=[0,0.1,0,0.3,0.3,0.3]", "region.rotation=[0,0,45]",
                                   "region.invert=true"))
    assert run.region.box == [0, 0.1, 0, 0.3, 0.3, 0.3] and run.region.invert
    with pytest.raises(ConfigError, match="region.box"):
        parse_config(composed("region.box=[0,0,0,1]"))
    with pytest.raises(ConfigError, match="not to stage=reconstruct"):
        parse_config(composed("stage=reconstruct", "region.box=[0,0,0,1,1,1]"))


@pytest.mark.slow
def test_a_regional_stylization_changes_nothing_outside_its_region(tmp_path):
    """A tiny run inside a box: the held-out pixels whose rays miss the region are the source's exactly, the
    folder holds the region, and open_run renders the composite; the same prompt over the whole scene trains
    another run."""
    from nerfart_plugin.run.pipeline import run

    box = "region.box=[3.6,1.2,4.3,2.0,0.9,2.0]"
    base = [f"output_root={tmp_path}", *TINY, "guidance=toy", "reconstruct.steps=60", "stylize.steps=4", "+prompt=red"]
    out = run(composed(*base, box))
    folder = Path(out["stylization"]["dir"])
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["region"]["outside_max_change"] == 0.0, metrics["region"]
    assert 0.0 < min(metrics["region"]["covered_share"]) < 1.0
    assert (folder / "region.npz").is_file()
    opened = open_run(folder, device="cpu")
    assert isinstance(opened.renderer.field, CompositeField) and opened.region.content_hash == \
        Region.box([3.6, 1.2, 4.3], [2.0, 0.9, 2.0]).content_hash
    whole = run(composed(*base))
    assert Path(whole["stylization"]["dir"]) != folder
    # a region applied after training to the whole-scene run: the source outside, that run's field inside
    both = open_run(whole["stylization"]["dir"], device="cpu").with_region(opened.region)
    assert both.tag.startswith("-region") and isinstance(both.renderer.field, CompositeField)


@pytest.mark.slow
def test_a_region_that_covers_the_whole_scene_gives_the_whole_scene_result(tmp_path):
    """Inside a box larger than the scene the stylization trains to the very tensors of the whole-scene one."""
    from nerfart_plugin.run.pipeline import run
    from nerfart_plugin.systems.checkpoints import load_checkpoint

    base = [f"output_root={tmp_path}", *TINY, "guidance=toy", "reconstruct.steps=30", "stylize.steps=3", "+prompt=red",
            "export.enabled=false", "stylize.video_frames=0"]
    whole = Path(run(composed(*base))["stylization"]["dir"])
    inside = Path(run(composed(*base, "region.box=[0,0,0,1000,1000,1000]"))["stylization"]["dir"])
    assert whole != inside
    a, b = load_checkpoint(whole / "final.ckpt")["state_dict"], load_checkpoint(inside / "final.ckpt")["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
