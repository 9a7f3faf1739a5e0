"""Selfie pipeline on the real Beer.mp4: frames -> pycolmap SfM -> scene; compared with its poses_bounds.npy."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from nerfart_plugin.data import load_scene
from nerfart_plugin.data.colmap import read_colmap_model, reprojection_errors
from nerfart_plugin.data.llff import read_poses_bounds
from nerfart_plugin.data.normalize import look_at_centre, umeyama
from nerfart_plugin.data.selfie import extract_frames, run_sfm, selfie_cache_meta

log = logging.getLogger(__name__)


@pytest.mark.slow
def test_extract_frames_sampling(shared_data, tmp_path):
    frames = extract_frames(shared_data / "video_beer" / "Beer.mp4", tmp_path, fps=15, max_frames=5, long_side=64)
    assert len(frames) == 5
    t = np.array([f["time"] for f in frames])
    assert t[0] == pytest.approx(0.0, abs=0.05) and t[-1] > 22.0 and np.all(np.diff(t) > 4.0)
    from PIL import Image

    assert Image.open(tmp_path / frames[0]["name"]).size == (36, 64)  # portrait 720x1280 -> 36x64


@pytest.mark.slow
def test_sfm_is_deterministic(shared_data, tmp_path):
    """Two SfM runs on the same frames give the same cameras (one thread per step, seeded RANSAC).

    With pycolmap's default threading, extraction and matching finish in a varying
    order and the recovered focal changed by up to 17% between runs.
    """
    frames = tmp_path / "frames"
    extract_frames(shared_data / "video_beer" / "Beer.mp4", frames, fps=15, max_frames=48, long_side=480)
    models = [read_colmap_model(run_sfm(frames, tmp_path / f"run{i}")) for i in range(2)]
    a, b = models
    assert a.names == b.names and len(a.names) >= 0.75 * 48
    np.testing.assert_array_equal(a.K, b.K)
    np.testing.assert_array_equal(np.stack(a.params), np.stack(b.params))
    np.testing.assert_array_equal(a.c2w, b.c2w)
    np.testing.assert_array_equal(a.points, b.points)


def beer_alignment_error(model, meta, ref_c2w) -> tuple[float, float]:
    """Umeyama-aligned camera-centre RMSE / median, relative to the reference spread.

    Frames are matched to the 71 reference poses by time, assuming the reference
    frames were sampled evenly over the video (linear interpolation between them).
    """
    times = {f["name"]: f["time"] for f in meta["frames"]}
    t = np.array([times[n] for n in model.names])
    rc = ref_c2w[:, :3, 3]
    duration = 706 / 30
    tj = np.arange(len(rc)) * duration / len(rc)
    ref_at = np.stack([np.interp(t, tj, rc[:, k]) for k in range(3)], 1)
    ours = model.c2w[:, :3, 3]
    s, R, tt = umeyama(ours, ref_at)
    err = np.linalg.norm(ours @ (s * R).T + tt - ref_at, axis=1)
    scale = np.linalg.norm(rc - rc.mean(0), axis=1).mean()
    return float(np.sqrt((err**2).mean()) / scale), float(np.median(err) / scale)


@pytest.mark.slow
def test_beer_video_sfm(shared_data, tmp_path, record_property):
    video = shared_data / "video_beer" / "Beer.mp4"
    scene = load_scene("selfie", video, max_frames=48, frame_long_side=480, cache_dir=tmp_path, resolution=96)
    meta = selfie_cache_meta(scene)
    assert meta is not None and len(meta["frames"]) == 48
    n_reg = scene.num_images
    assert n_reg >= 0.75 * 48, scene.notes
    assert scene.capture == "unbounded" and scene.masks is None
    assert scene.images.shape[1:] == (96, 54, 3)
    cache = next(tmp_path.glob("Beer_*"))
    model = read_colmap_model(cache / "sparse" / "0")
    # one shared camera with a physically plausible focal: a horizontal field of view between 20 and 90
    # degrees (the reference's 1105 px at 720 wide is 36 degrees, 414 px at 270). The value itself is
    # recorded, not asserted against a margin: SfM is deterministic for one pycolmap (test_sfm_is_deterministic),
    # but another pycolmap release may settle elsewhere in the focal's shallow optimum.
    assert np.allclose(model.K, model.K[0])
    focal = float(model.K[0, 0, 0])
    record_property("beer_focal_px_at_270", focal)
    assert 135.0 / np.tan(np.radians(45)) <= focal <= 135.0 / np.tan(np.radians(10)), focal
    assert np.median(reprojection_errors(model)) < 2.0
    # inward-facing orbit: cameras roughly equidistant from the common look-at point
    d = np.linalg.norm(model.c2w[:, :3, 3] - look_at_centre(model.c2w), axis=1)
    assert d.std() / d.mean() < 0.3
    # second call hits the cache
    again = load_scene("selfie", video, max_frames=48, frame_long_side=480, cache_dir=tmp_path, resolution=96)
    assert any("loaded cached" in n for n in again.notes) and again.content_hash == scene.content_hash
    # comparison with the reference COLMAP poses (see data/README.md: the can's rotational
    # symmetry folds the orbit differently in the two reconstructions, so this is a
    # recorded figure, bounded only loosely)
    ref = read_poses_bounds(shared_data / "video_beer" / "poses_bounds.npy")
    rmse, med = beer_alignment_error(model, meta, ref.c2w)
    record_property("beer_aligned_rmse_rel", rmse)
    record_property("beer_aligned_median_rel", med)
    log.warning("Beer.mp4: aligned camera-centre error vs poses_bounds: rmse %.3f, median %.3f (x scene spread)",
                rmse, med)
    assert np.isfinite(rmse) and rmse < 1.5


def _short_clip(shared_data, dst):
    """The first 5 s of Beer.mp4 at 10 fps, 180x320: a video SfM reconstructs in seconds."""
    import av

    with av.open(str(shared_data / "video_beer" / "Beer.mp4")) as src, av.open(str(dst), "w") as out:
        stream = out.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 180, 320, "yuv420p"
        for i, frame in enumerate(src.decode(video=0)):
            if frame.time > 5.0:
                break
            if i % 3 == 0:
                img = frame.to_image().resize((180, 320))
                for packet in stream.encode(av.VideoFrame.from_image(img)):
                    out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return dst


@pytest.mark.slow
def test_video_cache_goes_under_the_output_root(shared_data, tmp_path):
    """Nothing is written beside the video unless asked (data.cache_dir=beside_data)."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from pipeline_helpers import tiny_cfg

    from nerfart_plugin.run.pipeline import Pipeline

    data = tmp_path / "data"
    data.mkdir()
    clip = _short_clip(shared_data, data / "clip.mp4")
    before = sorted(p.name for p in data.rglob("*"))
    out = tmp_path / "out"
    pipe = Pipeline(tiny_cfg(out, clip, "data=selfie", "data.fps=10", "data.max_frames=30", "stage=reconstruct"))
    pipe.load_data()
    assert sorted(p.name for p in data.rglob("*")) == before == ["clip.mp4"]
    caches = list((out / "cache" / "selfie").glob("clip_*"))
    assert len(caches) == 1 and (caches[0] / "sparse" / "0" / "images.bin").is_file()
    assert any(f"cached in {caches[0]}" in n for n in pipe.scene.notes)
    # asked for: beside the data; same frames and SfM, so the same scene identity
    beside = load_scene("selfie", clip, fps=10, max_frames=30, resolution=24, cache_dir="beside_data")
    assert (data / "nerfart_cache").is_dir() and len(list((data / "nerfart_cache").glob("clip_*"))) == 1
    assert beside.content_hash == pipe.scene.content_hash
    # auto resolution: frames smaller than frame_long_side keep their native 180x320
    native = load_scene("selfie", clip, fps=10, max_frames=30, cache_dir="beside_data")
    assert any("loaded cached" in n for n in native.notes) and native.images.shape[1:3] == (320, 180)


def test_cache_base_choices(tmp_path):
    from nerfart_plugin.data.selfie import cache_base

    video = tmp_path / "v.mp4"
    video.write_bytes(b"x")
    assert cache_base(video, None, tmp_path / "out" / "cache") == tmp_path / "out" / "cache" / "selfie"
    assert cache_base(video, "auto", tmp_path / "c") == tmp_path / "c" / "selfie"
    assert cache_base(video, None, None) == Path("outputs") / "cache" / "selfie"  # the default output_root
    assert cache_base(video, "beside_data") == tmp_path / "nerfart_cache"
    assert cache_base(tmp_path, "beside_data") == tmp_path / "nerfart_cache"  # a frame folder
    assert cache_base(video, str(tmp_path / "mine")) == tmp_path / "mine"
