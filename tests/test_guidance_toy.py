"""Toy guidance: determinism, colour words, and a directional-loss stylization toward "red"."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from nerfart_plugin.config import registry
from nerfart_plugin.guidance import ToyGuidance, build_guidance
from nerfart_plugin.objectives import losses


def _redness(img: torch.Tensor) -> float:
    m = img.mean(dim=(0, 2, 3))
    return float(m[0] - 0.5 * (m[1] + m[2]))


def test_registered_and_deterministic() -> None:
    assert {"clip", "toy"} <= set(registry.names("guidance"))
    a, b = build_guidance({"name": "toy"}), ToyGuidance()
    assert a.is_real is False and a.name == "toy"
    texts = ["red", "Vincent van Gogh", "a photo of a person"]
    assert torch.equal(a.encode_text(texts), b.encode_text(texts))
    img = torch.rand(2, 3, 20, 30)
    assert torch.equal(a.encode_image(img), b.encode_image(img))
    assert a.encode_image(img).shape == (2, a.embed_dim)


def test_colour_words_match_colour_images() -> None:
    g = ToyGuidance()
    red_img = torch.zeros(1, 3, 16, 16)
    red_img[:, 0] = 1.0
    t = F.normalize(g.encode_text(["red", "blue", "green", "a photo"]), dim=-1)
    i = F.normalize(g.encode_image(red_img), dim=-1)
    sims = (i @ t.t())[0]
    assert sims[0] > sims[1] and sims[0] > sims[2]
    # neutral prompts are grey: same embedding for "a photo" and "a photo of a person"
    assert torch.allclose(g.encode_text(["a photo"]), g.encode_text(["a photo of a person"]))
    # unknown prompts: distinct, deterministic
    u = g.encode_text(["Ukiyo-e", "Cubism"])
    assert not torch.allclose(u[0], u[1])


def test_directional_optimization_makes_image_redder() -> None:
    g = ToyGuidance()
    gen = torch.Generator().manual_seed(0)
    src = 0.3 + 0.4 * torch.rand(1, 3, 24, 24, generator=gen)
    logit = torch.logit(src).clone().requires_grad_()
    src_emb = g.encode_image(src).detach()
    t_tgt, t_src = g.encode_text(["red", "a photo"])
    opt = torch.optim.Adam([logit], lr=0.05)
    before = _redness(src)
    for _ in range(40):
        loss = losses.directional_clip_loss(g.encode_image(torch.sigmoid(logit)), src_emb, t_tgt, t_src)
        assert torch.isfinite(loss)
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = _redness(torch.sigmoid(logit).detach())
    assert after > before + 0.1, (before, after)
    assert loss.item() < 0.5
