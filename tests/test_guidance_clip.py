"""CLIP guidance: random tiny model (shapes, gradients, caching) and the missing-weights error."""

from __future__ import annotations

import logging

import pytest
import torch

from nerfart_plugin.errors import ConfigError, WeightsMissingError
from nerfart_plugin.guidance import CLIPGuidance, build_guidance
from nerfart_plugin.guidance import weights as wts
from nerfart_plugin.guidance.base import WeightsPolicy
from nerfart_plugin.guidance.clip import (TINY_TEST_OVERRIDES, PatchEmbedding, attention_kernels,
    use_matmul_patch_embedding)
from nerfart_plugin.guidance.precision import LowPrecisionWeights, cpu_has_bf16

TINY_CFG = {
    "name": "clip",
    "allow_random_weights": True,
    "model": "ViT-B-32", "pretrained": None, "model_overrides": TINY_TEST_OVERRIDES,
}


@pytest.fixture(scope="module")
def tiny_clip() -> CLIPGuidance:
    g = build_guidance(TINY_CFG)
    assert isinstance(g, CLIPGuidance)
    return g


def test_random_clip_embeddings_and_gradients(tiny_clip: CLIPGuidance) -> None:
    assert tiny_clip.is_real is False
    assert tiny_clip.input_size == 32 and tiny_clip.embed_dim == 32
    assert all(not p.requires_grad for p in tiny_clip.parameters())
    assert not tiny_clip.net.training
    img = torch.rand(2, 3, 40, 56, requires_grad=True)  # non-square, not the input size
    emb = tiny_clip.encode_image(img)
    assert emb.shape == (2, 32)
    assert torch.isfinite(emb).all() and (emb.norm(dim=-1) > 1e-6).all()
    emb.sum().backward()
    assert img.grad is not None and torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0


def test_encode_images_batches_view_and_patches_like_separate_calls(tiny_clip: CLIPGuidance) -> None:
    """The stylization step encodes the whole view and its local patches in one network pass:
    same embeddings and image gradients as encoding them one by one."""
    torch.manual_seed(0)
    view = torch.rand(1, 3, 96, 80, requires_grad=True)
    patches = torch.nn.functional.interpolate(view[:, :, :32, :32], size=tiny_clip.input_size).expand(3, -1, -1, -1)
    e_view, e_patch = tiny_clip.encode_images([view, patches])
    assert e_view.shape == (1, tiny_clip.embed_dim) and e_patch.shape == (3, tiny_clip.embed_dim)
    g_batched = torch.autograd.grad(e_view.sum() + e_patch.square().sum(), view)[0]
    s_view, s_patch = tiny_clip.encode_image(view), tiny_clip.encode_image(patches)
    torch.testing.assert_close(e_view, s_view, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(e_patch, s_patch, atol=1e-5, rtol=1e-4)
    g_sep = torch.autograd.grad(s_view.sum() + s_patch.square().sum(), view)[0]
    torch.testing.assert_close(g_batched, g_sep, atol=1e-6, rtol=1e-4)
    with pytest.raises(ValueError, match="encode_images"):
        tiny_clip.encode_images([torch.rand(3, 8, 8)])


@pytest.mark.parametrize("precision", ["bf16", "auto"])
def test_reduced_precision_matches_fp32(precision: str) -> None:
    """bf16 autocast (the CPU default where the CPU has native bf16) stays close to fp32: same
    weights, embeddings and image gradients within a few bf16 ulps of direction."""
    torch.manual_seed(0)
    fp32 = build_guidance({**TINY_CFG, "precision": "fp32"})
    low = build_guidance({**TINY_CFG, "precision": precision})
    low.net.load_state_dict(fp32.net.state_dict())
    x = torch.rand(3, 3, 64, 64, requires_grad=True)
    a, b = fp32.encode_image(x), low.encode_image(x)
    assert b.dtype == torch.float32 and b.shape == a.shape
    cos = torch.nn.functional.cosine_similarity
    assert cos(a, b).min() > 0.999
    ga = torch.autograd.grad(a.square().sum(), x)[0]
    gb = torch.autograd.grad(low.encode_image(x).square().sum(), x)[0]
    assert torch.isfinite(gb).all() and cos(ga.flatten(1), gb.flatten(1)).min() > 0.99
    want = torch.bfloat16 if precision == "bf16" or cpu_has_bf16() else torch.float32
    assert low.compute_dtype(torch.device("cpu")) == want


def _ops_on_weights(g: CLIPGuidance, x: torch.Tensor, per_call: bool = False) -> tuple[int, set[str]]:
    """While ``g``'s image tower encodes the preprocessed ``x`` (bf16, forward and backward, after a first
    encode): how many of its float32 linear, convolution and attention weights are cast, and the names of
    the ops run; ``per_call``: through open_clip's own ``encode_image`` under plain autocast instead."""
    from torch.utils._python_dispatch import TorchDispatchMode

    kinds = (torch.nn.Linear, torch.nn.Conv2d, torch.nn.MultiheadAttention)
    weights = {p.data_ptr() for m in g.net.visual.modules() if isinstance(m, kinds) for p in m.parameters()}

    class Record(TorchDispatchMode):
        casts, ops = 0, set()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Record.ops.add(str(func.overloadpacket))
            if func is torch.ops.aten._to_copy.default and args[0].data_ptr() in weights:
                Record.casts += 1
            return func(*args, **(kwargs or {}))

    xp = g.preprocess(x).detach().requires_grad_(True)
    with Record():
        if per_call:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                emb = g.net.encode_image(xp)
        else:
            emb = g._net_image(xp)
        emb.float().sum().backward()
    return Record.casts, Record.ops


def test_clip_image_tower_runs_cpu_fast_paths_with_autocasts_numbers() -> None:
    """The bf16 image tower runs on weights cast once (LowPrecisionWeights), not on float32 weights that
    autocast casts on every call, its patch embedding as a matmul, and attention with the math kernel on
    CPU: bit for bit the embeddings and image gradients of open_clip under autocast with those kernels."""
    torch.manual_seed(0)
    g = build_guidance({**TINY_CFG, "precision": "bf16"})
    assert isinstance(g.net.visual.conv1, PatchEmbedding)
    x = torch.rand(3, 3, 40, 48, requires_grad=True)
    new = g.encode_image(x)
    g_new = torch.autograd.grad(new.square().sum(), x)[0]
    with attention_kernels(x.device), torch.autocast("cpu", dtype=torch.bfloat16):  # float32 weights, cast per call
        old = torch.cat([g.net.encode_image(xi[None]) for xi in g.preprocess(x)]).float()
    g_old = torch.autograd.grad(old.square().sum(), x)[0]
    assert torch.equal(new, old) and torch.equal(g_new, g_old)
    casts, ops = _ops_on_weights(g, x)
    assert casts == 0 and _ops_on_weights(g, x, per_call=True)[0] > 0  # cast once, not per call
    assert not any("flash" in op or "convolution" in op for op in ops), [op for op in ops if "flash" in op or "conv" in op]
    assert all(p.dtype == torch.float32 for p in g.net.parameters())  # the module's own weights stay float32
    assert set(g.state_dict()) == set(build_guidance(TINY_CFG).state_dict())  # the copies are not state


def test_patch_embedding_is_the_strided_convolution() -> None:
    """PatchEmbedding computes open_clip's patch convolution (float64: to rounding), keeps its parameters and
    state-dict keys, refuses an image that is not a multiple of the patch, and replaces only a
    non-overlapping convolution."""
    torch.manual_seed(0)
    visual = torch.nn.Module()
    visual.conv1 = conv = torch.nn.Conv2d(3, 8, 4, stride=4, bias=False).double()
    assert use_matmul_patch_embedding(visual) and isinstance(visual.conv1, PatchEmbedding)
    assert visual.conv1.weight is conv.weight and list(visual.state_dict()) == ["conv1.weight"]
    x = torch.rand(2, 3, 12, 16, dtype=torch.float64, requires_grad=True)
    y = visual.conv1(x)
    torch.testing.assert_close(y, conv(x), rtol=1e-12, atol=1e-12)
    gy = torch.rand_like(y)
    torch.testing.assert_close(torch.autograd.grad(y, x, gy)[0], torch.autograd.grad(conv(x), x, gy)[0])
    with pytest.raises(ValueError, match="multiple of the patch size"):
        visual.conv1(torch.rand(1, 3, 10, 16, dtype=torch.float64))
    visual.conv1 = torch.nn.Conv2d(3, 8, 4, stride=2)
    assert not use_matmul_patch_embedding(visual) and type(visual.conv1) is torch.nn.Conv2d


def test_low_precision_weights_are_remade_when_a_weight_changes() -> None:
    """The copies follow the module: the same copies while nothing changes, new ones after an in-place
    change (load_state_dict) or for another dtype; only linear, convolution and attention-projection
    weights are cast."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.Flatten(), torch.nn.LayerNorm(4 * 6 * 6),
                              torch.nn.Linear(4 * 6 * 6, 5))
    low = LowPrecisionWeights(net)
    w = low.weights(torch.bfloat16)
    assert set(w) == {"0.weight", "0.bias", "3.weight", "3.bias"} and all(t.dtype == torch.bfloat16 for t in w.values())
    assert low.weights(torch.bfloat16) is w
    x = torch.rand(2, 3, 8, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(low.run(torch.bfloat16, x), net(x))
    state = {k: v + 1 for k, v in net.state_dict().items()}
    net.load_state_dict(state)
    w2 = low.weights(torch.bfloat16)
    assert w2 is not w and torch.equal(w2["3.weight"], state["3.weight"].to(torch.bfloat16))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(low.run(torch.bfloat16, x), net(x))
    assert low.weights(torch.float16)["0.weight"].dtype == torch.float16
    mha = LowPrecisionWeights(torch.nn.MultiheadAttention(8, 2))
    assert set(mha.weights(torch.bfloat16)) == {"in_proj_weight", "in_proj_bias", "out_proj.weight", "out_proj.bias"}


def test_fp32_stays_fp32_under_an_outer_autocast() -> None:
    """guidance.precision=fp32 inside a step run under trainer.precision=bf16-mixed: the image tower
    still runs in float32 (the same embeddings as outside the autocast)."""
    torch.manual_seed(0)
    fp32 = build_guidance({**TINY_CFG, "precision": "fp32"})
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        ref = fp32.encode_image(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            inside = fp32.encode_image(x)
    torch.testing.assert_close(inside, ref, rtol=1e-5, atol=1e-6)


def test_precision_errors() -> None:
    with pytest.raises(ConfigError, match="precision"):
        build_guidance({**TINY_CFG, "precision": "int8"})
    g = build_guidance({**TINY_CFG, "precision": "fp16"})
    with pytest.raises(ConfigError, match="fp16 needs a CUDA"):
        g.encode_image(torch.rand(1, 3, 32, 32))


def test_clip_shortest_resize_mode() -> None:
    g = build_guidance({**TINY_CFG, "resize_mode": "shortest"})
    assert g.preprocess(torch.rand(1, 3, 40, 64)).shape == (1, 3, 32, 32)


def test_text_encoding_cached_and_truncation_warned(tiny_clip: CLIPGuidance, caplog: pytest.LogCaptureFixture) -> None:
    calls: list[list[str]] = []
    orig = tiny_clip._encode_texts

    def spy(texts):
        calls.append(list(texts))
        return orig(texts)

    tiny_clip._encode_texts = spy  # type: ignore[method-assign]
    try:
        t = tiny_clip.encode_text(["a photo", "Vincent van Gogh", "a photo"])
        assert t.shape == (3, 32) and not t.requires_grad
        assert torch.equal(t[0], t[2])
        t2 = tiny_clip.encode_text(["Vincent van Gogh"])
        assert torch.equal(t2[0], t[1])
        assert calls == [["a photo", "Vincent van Gogh"]]
        with caplog.at_level(logging.WARNING):
            long = tiny_clip.encode_text(["very " * 100 + "long prompt"])
        assert long.shape == (1, 32) and torch.isfinite(long).all()
        assert "truncated" in caplog.text
    finally:
        del tiny_clip._encode_texts


def test_real_default_missing_weights_error(no_network, tmp_path) -> None:
    with pytest.raises(WeightsMissingError) as ei:
        CLIPGuidance(model="ViT-B-32", pretrained="openai", cache_dir=str(tmp_path))
    msg = str(ei.value)
    assert "'ViT-B-32'" in msg and "pretrained='openai'" in msg
    assert str(tmp_path) in msg  # where it looked
    assert "open_clip.create_model_and_transforms('ViT-B-32', pretrained='openai'" in msg  # how to get them
    assert "guidance.pretrained=/path/to/file.pt" in msg


def test_real_default_without_cache_dir(no_network) -> None:
    """The shipped default config on a machine without the weights (skipped if they are cached)."""
    from open_clip import get_pretrained_cfg

    from nerfart_plugin.guidance.clip_weights import find_cached

    if find_cached(get_pretrained_cfg("ViT-B-32", "openai"), None)[0]:
        pytest.skip("ViT-B-32/openai weights are cached on this machine")
    with pytest.raises(WeightsMissingError, match="ViT-B-32"):
        build_guidance({"name": "clip"})


def test_download_allowed_but_offline(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setattr(wts, "host_reachable", lambda *a, **k: False)
    with pytest.raises(WeightsMissingError, match="not reachable"):
        CLIPGuidance(pretrained="openai", cache_dir=str(tmp_path), policy=WeightsPolicy(allow_download=True))


def test_missing_local_file_and_bad_tag(no_network, tmp_path) -> None:
    with pytest.raises(WeightsMissingError, match="nope.pt"):
        CLIPGuidance(pretrained=str(tmp_path / "nope.pt"))
    with pytest.raises(ConfigError, match="not-a-tag"):
        CLIPGuidance(pretrained="not-a-tag")
    with pytest.raises(ConfigError, match="allow_random_weights"):
        CLIPGuidance(pretrained=None)
    with pytest.raises(ConfigError, match="open_clip model"):
        CLIPGuidance(model="ViT-Nope")


def test_a_file_that_is_not_clip_weights_gets_an_error_naming_it(no_network, tmp_path) -> None:
    """Random bytes, an empty file, a pickle of something else, and another model's checkpoint: each is refused
    with WeightsMissingError naming the file and what CLIP weights are, never a raw unpickling traceback."""
    import pickle

    bad = {"random.pt": bytes(range(256)) * 64, "empty.pt": b"", "pickle.pt": pickle.dumps({"not": "weights"})}
    for name, data in bad.items():
        (tmp_path / name).write_bytes(data)
    torch.save({"state_dict": {"renderer.field.w": torch.zeros(3)}, "epoch": 0}, tmp_path / "final.ckpt")
    for name in (*bad, "final.ckpt"):
        with pytest.raises(WeightsMissingError, match=rf"CLIP checkpoint .*{name} could not be loaded .*It must be "
                                                      r"CLIP weights") as info:
            CLIPGuidance(pretrained=str(tmp_path / name), model_overrides=TINY_TEST_OVERRIDES)
        assert "guidance.pretrained" in str(info.value)


def test_random_fallback_when_allowed(no_network, tmp_path) -> None:
    g = CLIPGuidance(
        pretrained="openai", cache_dir=str(tmp_path), policy=WeightsPolicy(allow_random_weights=True), model_overrides=TINY_TEST_OVERRIDES
    )
    assert g.is_real is False


def test_local_checkpoint_file(tiny_clip: CLIPGuidance, tmp_path) -> None:
    path = tmp_path / "tiny.pt"
    torch.save(tiny_clip.net.state_dict(), path)
    g = CLIPGuidance(pretrained=str(path), model_overrides=TINY_TEST_OVERRIDES)
    assert g.is_real is True
    img = torch.rand(1, 3, 32, 32)
    assert torch.allclose(g.encode_image(img), tiny_clip.encode_image(img), atol=1e-5)


def test_weights_found_in_hf_cache_layout(no_network, tiny_clip: CLIPGuidance, tmp_path) -> None:
    """A tag whose file sits in a Hugging Face cache folder is loaded without any network access."""
    repo = tmp_path / "models--timm--vit_base_patch32_clip_224.openai"
    snap = repo / "snapshots" / "0123abcd"
    snap.mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("0123abcd")
    torch.save(tiny_clip.net.state_dict(), snap / "open_clip_pytorch_model.bin")
    g = CLIPGuidance(pretrained="openai", cache_dir=str(tmp_path), model_overrides=TINY_TEST_OVERRIDES)
    assert g.is_real is True
    assert any(type(m).__name__ == "QuickGELU" for m in g.net.modules())  # OpenAI weights need QuickGELU


def test_build_from_omegaconf() -> None:
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(TINY_CFG)
    g = build_guidance(cfg)
    assert isinstance(g, CLIPGuidance) and g.embed_dim == 32
    with pytest.raises(ConfigError, match="guidance.name=.nope.: one of clip, imagenet, toy"):
        build_guidance({"name": "nope"})
