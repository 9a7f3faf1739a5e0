"""VGG16 perceptual features (random weights) and the toy edge extractor."""

from __future__ import annotations

import pytest
import torch

from nerfart_plugin.errors import ConfigError, WeightsMissingError
from nerfart_plugin.guidance import EdgePerceptual, Perceptual, build_perceptual
from nerfart_plugin.guidance.base import WeightsPolicy
from nerfart_plugin.objectives import losses


def test_vgg_random_feature_shapes_and_truncation() -> None:
    p = build_perceptual({"name": "clip", "allow_random_weights": True, "perceptual": {"name": "vgg", "weights": None}})
    assert isinstance(p, Perceptual) and p.is_real is False
    assert p.layers == ["relu1_2", "relu2_2", "relu3_3", "relu4_3"]
    assert len(p.features_net) == 23  # truncated after relu4_3
    img = torch.rand(2, 3, 32, 48, requires_grad=True)
    feats = p.features(img)
    assert [tuple(f.shape) for f in feats] == [(2, 64, 32, 48), (2, 128, 16, 24), (2, 256, 8, 12), (2, 512, 4, 6)]
    losses.perceptual_loss(feats, [f.detach() * 0 for f in feats]).backward()
    assert torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0
    assert all(not q.requires_grad for q in p.parameters())


def test_vgg_custom_layers() -> None:
    p = Perceptual(weights=None, layers=["relu1_1", "relu2_1"], policy=WeightsPolicy(allow_random_weights=True))
    assert len(p.features_net) == 7
    assert [f.shape[1] for f in p.features(torch.rand(1, 3, 16, 16))] == [64, 128]
    with pytest.raises(ConfigError, match="relu9_9"):
        Perceptual(weights=None, layers=["relu9_9"], policy=WeightsPolicy(allow_random_weights=True))


def test_vgg_missing_weights(no_network, monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # empty hub cache
    with pytest.raises(WeightsMissingError) as ei:
        Perceptual()
    msg = str(ei.value)
    assert "vgg16-397923af.pth" in msg and str(tmp_path) in msg and "guidance.perceptual.weights=" in msg
    with pytest.raises(WeightsMissingError, match="missing.pth"):
        Perceptual(weights=str(tmp_path / "missing.pth"))
    with pytest.raises(ConfigError):
        Perceptual(weights=None)


def test_vgg_local_file(tmp_path) -> None:
    from torchvision.models.vgg import cfgs, make_layers

    torch.manual_seed(0)
    net = torch.nn.Module()
    net.features = make_layers(cfgs["D"])  # same keys as vgg16().state_dict() for the trunk
    path = tmp_path / "vgg.pth"
    torch.save(net.state_dict(), path)
    p = Perceptual(weights=str(path), layers=["relu1_2"], precision="fp32")  # the weights exactly as loaded
    assert p.is_real is True
    x = torch.rand(1, 3, 8, 8)
    ref = torch.relu(net.features[2](torch.relu(net.features[0](p.normalize(x)))))
    assert torch.allclose(p.features(x)[0], ref, atol=1e-5)


def test_edge_perceptual_for_toy() -> None:
    p = build_perceptual({"name": "toy"})
    assert isinstance(p, EdgePerceptual) and p.is_real is False
    img = torch.rand(2, 3, 16, 16, requires_grad=True)
    feats = p.features(img)
    assert [tuple(f.shape) for f in feats] == [(2, 3, 16, 16)] * 2 + [(2, 3, 8, 8)] * 2 + [(2, 3, 4, 4)] * 2
    losses.perceptual_loss(feats, [f.detach() + 1 for f in feats]).backward()
    assert torch.isfinite(img.grad).all()


@pytest.mark.parametrize("delta", [0.3, 0.05])
def test_vgg_bf16_matches_fp32_loss_and_image_gradient(delta: float) -> None:
    """guidance.perceptual.precision=bf16 (the CPU default where the CPU has native bf16): Eq. 9 between a view
    and a changed view (a stylization step's edit, large and small) keeps its value within 2% and its image
    gradient within cosine 0.99 of fp32, and an unchanged view scores exactly 0 with a zero gradient."""
    torch.manual_seed(0)
    fp32 = Perceptual(weights=None, policy=WeightsPolicy(allow_random_weights=True), precision="fp32")
    low = Perceptual(weights=None, policy=WeightsPolicy(allow_random_weights=True), precision="bf16")
    low.load_state_dict(fp32.state_dict())
    src = torch.rand(1, 3, 64, 64)
    edit = (src + delta * torch.randn(1, 3, 8, 8).repeat_interleave(8, -1).repeat_interleave(8, -2)).clamp(0, 1)

    def loss_and_grad(p: Perceptual, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = img.clone().requires_grad_(True)
        loss = losses.perceptual_loss(p.features(x), [f.detach() for f in p.features(src)])
        return loss.detach(), torch.autograd.grad(loss, x)[0]

    (la, ga), (lb, gb) = loss_and_grad(fp32, edit), loss_and_grad(low, edit)
    assert all(f.dtype == torch.float32 for f in low.features(src))
    assert torch.isfinite(gb).all() and abs(float(lb / la) - 1.0) < 0.02
    assert torch.nn.functional.cosine_similarity(ga.flatten(), gb.flatten(), dim=0) > 0.99
    l0, g0 = loss_and_grad(low, src)
    assert float(l0) == 0.0 and float(g0.abs().max()) == 0.0


def test_vgg_fp32_stays_fp32_under_an_outer_autocast() -> None:
    """guidance.perceptual.precision=fp32 inside a step run under trainer.precision=bf16-mixed: the resize and the
    trunk run in float32 (the same features as outside the autocast)."""
    torch.manual_seed(0)
    p = Perceptual(weights=None, policy=WeightsPolicy(allow_random_weights=True), precision="fp32", max_size=48)
    x = torch.rand(1, 3, 64, 80)
    with torch.no_grad():
        ref = p.features(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            inside = p.features(x)
    for a, b in zip(inside, ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_vgg_precision_errors() -> None:
    with pytest.raises(ConfigError, match="guidance.perceptual.precision"):
        Perceptual(weights=None, policy=WeightsPolicy(allow_random_weights=True), precision="int8")
    p = Perceptual(weights=None, policy=WeightsPolicy(allow_random_weights=True), precision="fp16")
    with pytest.raises(ConfigError, match="fp16 needs a CUDA"):
        p.features(torch.rand(1, 3, 16, 16))
