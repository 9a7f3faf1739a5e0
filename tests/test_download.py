"""python -m nerfart_plugin.data.download: sample captures with checksums, tested against the local mirror."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from nerfart_plugin.data.download import download, main, manifest
from nerfart_plugin.errors import DataError, NerfArtError

MIRROR = Path(os.environ.get("NERFART_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
needs_mirror = pytest.mark.skipif(not (MIRROR / "girl").is_dir(), reason="the local mirror of the samples is absent")


def test_every_sample_names_its_source_and_its_files():
    samples = manifest()
    assert {"girl", "fangzhou_nature", "llff_fern"} <= set(samples)
    for entry in samples.values():
        assert entry["base_url"].startswith("https://") and entry["data"] in ("h3ds", "llff")
        assert all(size >= 0 and len(digest) == 64 for size, digest in entry["files"].values())
    with pytest.raises(NerfArtError, match="no sample named 'nope'; choose one of: fangzhou_nature, girl"):
        download("nope")


@pytest.mark.slow
@needs_mirror
def test_download_checks_every_file_resumes_and_loads(tmp_path, caplog):
    folder = download("girl", tmp_path, mirror=str(MIRROR))
    assert len([f for f in folder.rglob("*") if f.is_file()]) == len(manifest()["girl"]["files"])
    image = sorted((folder / "images").iterdir())[0]
    image.write_bytes(b"damaged")  # a broken file is fetched again, the others are kept
    before = {f: f.stat().st_mtime_ns for f in (folder / "matte").iterdir()}
    download("girl", tmp_path, mirror=str(MIRROR))
    assert image.stat().st_size > 1000 and before == {f: f.stat().st_mtime_ns for f in (folder / "matte").iterdir()}
    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.run.factories import build_scene

    scene = build_scene(load_config(["data=h3ds", f"data.path={folder}", "data.resolution=64"])).scene
    assert scene.num_images == 31
    import logging

    with caplog.at_level(logging.INFO, logger="nerfart_plugin"):
        assert main(["--list"]) == 0
    assert "girl" in caplog.text and "fangzhou_nature" in caplog.text


def test_content_that_does_not_match_is_refused_and_not_kept(tmp_path):
    bad = tmp_path / "mirror" / "girl"
    rel, (size, _) = next(iter(sorted(manifest()["girl"]["files"].items())))
    (bad / rel).parent.mkdir(parents=True)
    (bad / rel).write_bytes(b"x" * size)
    with pytest.raises(DataError, match="expected .* bytes with .*nothing was kept"):
        download("girl", tmp_path / "out", mirror=str(tmp_path / "mirror"))
    assert not (tmp_path / "out" / "girl" / rel).exists()


def test_ctrl_c_says_the_download_resumes(tmp_path, monkeypatch, caplog):
    import logging

    import nerfart_plugin.data.download as dl

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(dl, "fetch", interrupted)
    with caplog.at_level(logging.ERROR, logger="nerfart_plugin"):
        assert main(["girl", "--dest", str(tmp_path), "--mirror", str(tmp_path)]) == 130
    assert "interrupted; the files already downloaded are kept: run the same command again to resume" in caplog.text
