"""Style from a picture (``+style_image=<file>``): the NNFM loss on a case with a known nearest neighbour, the
picture's reading (16-bit, grayscale, RGBA) and refusals (missing, not an image, too small) before any work, the
run's key following the picture's content, and image-style runs through the pipeline, the dial and mixing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.guidance.style_image import MIN_SIDE, StyleImage, match_palette, read_style_image
from nerfart_plugin.objectives.losses import colour_loss, gram_matrix, nnfm_loss


def _picture(path: Path, h: int = 48, w: int = 64, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    iio.imwrite(path, rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    return path


# ---------------------------------------------------------------------- the loss
def test_nnfm_is_the_mean_cosine_distance_to_the_nearest_style_feature():
    """Rendered features that are copies of style features (any order) are at distance 0; one rotated 90 degrees
    from all of them is at distance 1; the mean follows; the mask keeps only the pixels it covers."""
    style = torch.eye(4)[None, :, :, None].repeat(1, 1, 1, 1)  # [1,C=4,4,1]: the four axes
    same = style[:, :, [2, 0, 3, 1]]  # the same vectors, shuffled, scaled
    assert float(nnfm_loss([same * 3.0], [style])) == pytest.approx(0.0, abs=1e-6)
    style3 = torch.eye(4)[:3].T[None, :, :, None]  # [1,4,3,1]: the first three axes only
    rendered = torch.eye(4)[None, :, :, None]  # axis 3 has no neighbour closer than 90 degrees
    assert float(nnfm_loss([rendered], [style3.permute(0, 1, 2, 3)])) == pytest.approx(0.25, abs=1e-6)
    # [1,4,2,2] image: its top row matches, the bottom row is the lone axis; the mask on the top row: 0
    img = torch.stack([torch.eye(4)[0], torch.eye(4)[1], torch.eye(4)[3], torch.eye(4)[3]], -1).reshape(1, 4, 2, 2)
    top = torch.tensor([[1.0, 1.0], [0.0, 0.0]])
    assert float(nnfm_loss([img], [style3], mask=top)) == pytest.approx(0.0, abs=1e-6)
    assert float(nnfm_loss([img], [style3], mask=1 - top)) == pytest.approx(1.0, abs=1e-6)
    # two layers: their mean
    assert float(nnfm_loss([same, rendered], [style, style3])) == pytest.approx(0.125, abs=1e-6)


def test_nnfm_gradient_pulls_a_feature_toward_its_nearest_style_feature():
    style = torch.tensor([[1.0, 0.0], [0.0, 1.0]]).T.reshape(1, 2, 2, 1)
    f = torch.tensor([0.9, 0.3]).reshape(1, 2, 1, 1).requires_grad_(True)
    nnfm_loss([f], [style]).backward()
    step = -f.grad.flatten()
    assert step[1] < 0  # moves toward (1, 0): its nearest, not (0, 1)


def test_nnfm_and_gram_refuse_mismatched_shapes():
    with pytest.raises(ValueError, match="equal C"):
        nnfm_loss([torch.zeros(1, 3, 2, 2)], [torch.zeros(1, 4, 2, 2)])
    with pytest.raises(ValueError, match="layers"):
        nnfm_loss([], [])
    with pytest.raises(ValueError, match=r"\[1,C,H,W\]"):
        gram_matrix(torch.zeros(2, 3, 4, 4))
    with pytest.raises(ValueError, match="one shape"):
        colour_loss(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 4, 4))


def test_gram_matrix_weights_locations_by_the_mask():
    f = torch.zeros(1, 2, 1, 2)
    f[0, 0, 0, 0], f[0, 1, 0, 1] = 2.0, 3.0
    assert torch.allclose(gram_matrix(f), torch.tensor([[2.0, 0.0], [0.0, 4.5]]))
    assert torch.allclose(gram_matrix(f, torch.tensor([[1.0, 0.0]])), torch.tensor([[4.0, 0.0], [0.0, 0.0]]))


def test_palette_matching_moves_the_subject_to_the_pictures_colours_and_keeps_the_background():
    g = torch.Generator().manual_seed(0)
    source = torch.rand(3, 16, 16, generator=g) * 0.5
    picture = 0.5 + 0.5 * torch.rand(3, 20, 20, generator=g)
    picture[0] *= 0.2  # little red
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[4:12, 4:12] = True
    out = match_palette(source, picture, mask)
    assert torch.equal(out[:, ~mask], source[:, ~mask])
    for c in range(3):
        assert float(out[c][mask].mean()) == pytest.approx(float(picture[c].mean()), abs=0.03)


# ---------------------------------------------------------------------- reading the picture
def test_16_bit_grayscale_and_rgba_pictures_are_read_as_rgb_in_unit_range(tmp_path):
    ramp = np.linspace(0, 65535, 64 * 40).astype(np.uint16).reshape(40, 64)
    iio.imwrite(tmp_path / "gray16.png", ramp)
    img = read_style_image(tmp_path / "gray16.png")
    assert img.shape == (3, 40, 64) and img.dtype == torch.float32
    assert torch.equal(img[0], img[2]) and float(img.max()) == pytest.approx(1.0) and float(img.min()) == 0.0
    assert float(img[0, 20, 10]) == pytest.approx(ramp[20, 10] / 65535, abs=1e-6)  # all 16 bits kept

    rgb16 = (np.random.default_rng(1).random((40, 48, 3)) * 65535).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "rgb16.png"), rgb16[..., ::-1])  # Pillow cannot write 16-bit RGB; OpenCV is BGR
    assert torch.allclose(read_style_image(tmp_path / "rgb16.png").permute(1, 2, 0),
                          torch.from_numpy(rgb16 / 65535.0).float(), atol=1e-6)

    rgba = np.zeros((40, 40, 4), dtype=np.uint8)
    rgba[..., 0], rgba[:20, :, 3], rgba[20:, :, 3] = 200, 255, 0  # opaque red on top, transparent below
    iio.imwrite(tmp_path / "rgba.png", rgba)
    img = read_style_image(tmp_path / "rgba.png")
    assert torch.allclose(img[:, 5, 5], torch.tensor([200 / 255, 0.0, 0.0]))
    assert torch.allclose(img[:, 30, 5], torch.ones(3))  # transparent: white

    gray8 = np.full((36, 36), 128, dtype=np.uint8)
    iio.imwrite(tmp_path / "gray.jpg", gray8)
    assert read_style_image(tmp_path / "gray.jpg").shape == (3, 36, 36)


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "missing.png", "no such file"),
    (lambda d: (d / "notes.png").write_text("not a picture") and d / "notes.png", "not a PNG or JPEG"),
    (lambda d: (iio.imwrite(d / "p.gif", np.zeros((40, 40, 3), dtype=np.uint8)), d / "p.gif")[1], "not a PNG or JPEG"),
    (lambda d: _picture(d / "tiny.png", MIN_SIDE - 1, 200), "at least"),
    (lambda d: ((d / "cut.png").write_bytes(_picture(d / "whole.png").read_bytes()[:60]), d / "cut.png")[1],
     "cannot be decoded"),
])
def test_bad_pictures_are_refused_naming_the_file(tmp_path, make, message):
    path = make(tmp_path)
    with pytest.raises(ConfigError, match=message) as err:
        read_style_image(path)
    assert str(path) in str(err.value) and "style_image=" in str(err.value)


def test_a_bad_picture_stops_the_cli_before_any_work(tmp_path):
    from pipeline_helpers import TINY, run_cli

    (tmp_path / "style.png").write_text("not a picture")
    out = tmp_path / "out"
    proc = run_cli([f"output_root={out}", *TINY, "guidance=toy", f"+style_image={tmp_path / 'style.png'}"])
    assert proc.returncode == 2 and "not a PNG or JPEG" in proc.stdout + proc.stderr
    assert not (out / "reconstructions").exists()


def test_a_stylization_needs_a_prompt_or_a_picture():
    from pipeline_helpers import composed

    from nerfart_plugin.run.pipeline import Pipeline

    with pytest.raises(ConfigError, match=r"\+style_image="):
        Pipeline(composed("guidance=toy"))


# ---------------------------------------------------------------------- the key
def test_the_key_follows_the_pictures_content_not_its_path(tmp_path):
    from pipeline_helpers import TINY, composed

    from nerfart_plugin.guidance.style import build_style
    from nerfart_plugin.run.factories import build_scene, stylize_settings
    from nerfart_plugin.run.keys import stylization_keys

    a = _picture(tmp_path / "a.png")
    copy = tmp_path / "elsewhere" / "a-copy.png"
    copy.parent.mkdir()
    shutil.copy(a, copy)
    b = _picture(tmp_path / "b.png", seed=1)

    def key(*extra: str) -> str:
        cfg = composed(f"output_root={tmp_path / 'out'}", *TINY, "guidance=toy", *extra)
        scene = build_scene(cfg)
        return stylization_keys(scene, build_style(cfg), {1: "src", 2: "src"}, stylize_settings(scene))[2]

    assert key(f"style_image.file={a}") == key(f"style_image.file={copy}")
    assert key(f"style_image.file={a}") != key(f"style_image.file={b}")
    assert key(f"style_image.file={a}") != key(f"style_image.file={a}", "style_image.lambda_style=20")
    assert key(f"style_image.file={a}") != key(f"style_image.file={a}", "+prompt=Joker")
    # a text-only run keeps the key it had before pictures existed (no style_image block in it)
    assert key("+prompt=Joker") == key("+prompt=Joker", "style_image.size=512")


def test_style_image_file_shorthand_and_its_settings_compose():
    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.config.overrides import normalize_overrides

    cfg = load_config(normalize_overrides(["+style_image=/x/p.png", "style_image.lambda_style=3"]))
    assert cfg.style_image.file == "/x/p.png" and cfg.style_image.lambda_style == 3


def test_a_loaded_picture_is_resized_to_its_long_side_and_hashed_by_content(tmp_path):
    s = StyleImage.load(_picture(tmp_path / "p.png", 60, 120), 64)
    assert s.image.shape == (3, 32, 64) and s.name == "p" and len(s.content_hash) == 16


# ---------------------------------------------------------------------- runs
@pytest.fixture(scope="module")
def picture_runs(shared_runs, tmp_path_factory):
    """A tiny reconstruction of the shipped head, its stylization from a picture alone, from the picture and a
    prompt, and from the prompt alone (toy guide)."""
    from pipeline_helpers import TINY, composed

    from nerfart_plugin.run.pipeline import run

    pic = _picture(tmp_path_factory.mktemp("pic") / "stripes.png", 64, 64)
    base = [f"output_root={shared_runs}", *TINY, "guidance=toy", "reconstruct.steps=60", "stylize.steps=4"]
    return {name: Path(run(composed(*base, *extra))["stylization"]["dir"])
            for name, extra in (("picture", [f"style_image.file={pic}"]),
                                ("both", [f"style_image.file={pic}", "+prompt=Joker"]),
                                ("text", ["+prompt=Joker"]))}


@pytest.mark.slow
def test_picture_runs_record_their_style_and_its_distances(picture_runs):
    m = json.loads((picture_runs["picture"] / "metrics.json").read_text())
    assert m["prompt"] is None and m["style"] == "stripes" and picture_runs["picture"].name.startswith("stripes-")
    block = m["style_image"]
    assert {"nnfm_source", "nnfm_stylized", "gram_source", "colour_emd_stylized"} <= set(block)
    assert m["auto"]["style_image.layers"] == "edges: its own"
    assert "clip_score" not in m and "skipped" in m["judge"]
    both = json.loads((picture_runs["both"] / "metrics.json").read_text())
    assert both["style"] == "Joker + stripes" and "clip_directional_similarity" in both and "style_image" in both
    losses = (picture_runs["both"] / "logs").rglob("metrics.csv")
    header = next(iter(losses)).read_text().splitlines()[0]
    assert "train/loss_style" in header and "train/loss_palette" in header and "train/loss_dir" in header


@pytest.mark.slow
def test_picture_runs_take_the_dial_and_mix_with_a_text_run(picture_runs):
    from nerfart_plugin.api import mix, open_run

    picture, text = open_run(picture_runs["picture"], device="cpu"), open_run(picture_runs["text"], device="cpu")
    view = picture.cameras.train_ids[0]
    zero = picture.with_strength(0.0).render(view, 24)["rgb"]
    full = picture.render(view, 24)["rgb"]
    assert not np.allclose(zero, full, atol=1e-3)
    assert np.allclose(mix([picture, text], [1.0, 0.0]).render(view, 24)["rgb"], full, atol=1e-5)
    both = mix([picture, text], [1.0, 1.0]).render(view, 24)["rgb"]
    assert np.isfinite(both).all() and not np.allclose(both, full, atol=1e-4)


@pytest.mark.slow
def test_a_preview_takes_a_picture_and_says_how_close_it_came(picture_runs, shared_runs, caplog):
    from pipeline_helpers import TINY, composed

    from nerfart_plugin.run.pipeline import run

    pic = json.loads((picture_runs["picture"] / "metrics.json").read_text())["style_image"]["file"]
    with caplog.at_level("INFO", logger="nerfart_plugin"):
        out = run(composed(f"output_root={shared_runs}", *TINY, "guidance=toy", "reconstruct.steps=60", "stage=preview",
                           "preview.steps=2", "preview.resolution=24", f"style_image.file={pic}"))
    assert Path(out["preview"]["preview"]).is_file()
    assert "distance to the style picture" in caplog.text and "preview of 'stripes'" in caplog.text


def test_the_sample_pictures_command_writes_readable_pictures(tmp_path):
    from nerfart_plugin.data.style_pictures import PICTURES, main

    assert main(["--dest", str(tmp_path), "coffee", "swirls"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["coffee.png", "swirls.png"]
    swirls = read_style_image(tmp_path / "swirls.png")
    assert swirls.shape == (3, 512, 512) and float(swirls.std()) > 0.1  # a picture, not a flat colour
    assert set(PICTURES) == {"hubble", "stain", "coffee", "retina", "swirls"}
    with pytest.raises(SystemExit):
        main(["--dest", str(tmp_path), "monalisa"])
