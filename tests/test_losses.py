"""Tests of nerfart_plugin.objectives.losses (Eq. 2-9) against hand computations and brute force."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.objectives import losses


def _brute_weight_reg(w: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    return (w[:, :, None] * w[:, None, :] * (d[:, :, None] - d[:, None, :]).abs()).sum((1, 2)).mean()


# ----------------------------------------------------------------------------- Eq. 7
@pytest.mark.parametrize("sorted_depths", [True, False])
def test_weight_reg_matches_bruteforce_values_and_grads(sorted_depths: bool) -> None:
    g = torch.Generator().manual_seed(0)
    R, K = 7, 33
    d = torch.rand(R, K, generator=g, dtype=torch.float64) * 5 + 1
    if sorted_depths:
        d = d.sort(dim=1).values
    w = torch.rand(R, K, generator=g, dtype=torch.float64)
    w1, d1 = w.clone().requires_grad_(), d.clone().requires_grad_()
    w2, d2 = w.clone().requires_grad_(), d.clone().requires_grad_()
    fast = losses.weight_regularization(w1, d1)
    slow = _brute_weight_reg(w2, d2)
    assert torch.allclose(fast, slow, rtol=1e-12, atol=1e-12)
    fast.backward()
    slow.backward()
    assert torch.allclose(w1.grad, w2.grad, rtol=1e-10, atol=1e-12)
    assert torch.allclose(d1.grad, d2.grad, rtol=1e-10, atol=1e-12)


def test_weight_reg_hand_value() -> None:
    # one ray, weights (0.5, 0.5) at depths 1 and 3: 2 * 0.25 * 2 = 1
    w = torch.tensor([[0.5, 0.5]])
    d = torch.tensor([[1.0, 3.0]])
    assert losses.weight_regularization(w, d).item() == pytest.approx(1.0)
    # a single delta spike has no spread
    w = torch.tensor([[0.0, 1.0, 0.0]])
    d = torch.tensor([[1.0, 2.0, 3.0]])
    assert losses.weight_regularization(w, d).item() == pytest.approx(0.0)


# ----------------------------------------------------------------------------- Eq. 5
def _naive_infonce(q, p, n, tau):
    q, p, n = F.normalize(q, dim=-1), F.normalize(p, dim=-1), F.normalize(n, dim=-1)
    pos = torch.exp((q * p).sum(-1) / tau)
    neg = torch.exp(q @ n.t() / tau).sum(-1)
    return (-torch.log(pos / (pos + neg))).mean()


def test_contrastive_matches_naive_formula() -> None:
    g = torch.Generator().manual_seed(1)
    q = torch.randn(5, 16, generator=g, dtype=torch.float64)
    p = torch.randn(16, generator=g, dtype=torch.float64)
    n = torch.randn(9, 16, generator=g, dtype=torch.float64)
    got = losses.contrastive_loss(q, p, n, tau=0.07)
    assert torch.allclose(got, _naive_infonce(q, p[None], n, 0.07), rtol=1e-10)
    # per-query positives
    pb = torch.randn(5, 16, generator=g, dtype=torch.float64)
    assert torch.allclose(losses.contrastive_loss(q, pb, n, 0.07), _naive_infonce(q, pb, n, 0.07), rtol=1e-10)


def test_contrastive_hand_value() -> None:
    # q == p, one orthogonal negative, tau=1: -log(e / (e + 1))
    q = torch.tensor([[1.0, 0.0]])
    got = losses.contrastive_loss(q, torch.tensor([2.0, 0.0]), torch.tensor([[0.0, 3.0]]), tau=1.0)
    assert got.item() == pytest.approx(-math.log(math.e / (math.e + 1)), rel=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    tau=st.floats(min_value=1e-3, max_value=1.0),
    sign_pos=st.sampled_from([1.0, -1.0]),
    sign_neg=st.sampled_from([1.0, -1.0]),
    m=st.integers(min_value=1, max_value=5),
    seed=st.integers(min_value=0, max_value=1000),
)
def test_contrastive_finite_identical_antipodal(tau, sign_pos, sign_neg, m, seed) -> None:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(3, 8, generator=g).requires_grad_()
    p = sign_pos * q.detach()[0]
    n = sign_neg * q.detach()[:1].repeat(m, 1)
    loss = losses.contrastive_loss(q, p, n, tau=tau)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() >= 0
    assert torch.isfinite(q.grad).all()


def test_contrastive_rejects_bad_tau() -> None:
    with pytest.raises(ConfigError):
        losses.contrastive_loss(torch.ones(1, 2), torch.ones(2), torch.ones(1, 2), tau=0.0)


# ----------------------------------------------------------------------------- Eq. 3 / 4
def test_absolute_clip_hand_values() -> None:
    img = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    txt = torch.tensor([3.0, 0.0])
    # cos = 1 and 0 -> losses 0 and 1 -> mean 0.5
    assert losses.absolute_clip_loss(img, txt).item() == pytest.approx(0.5)


def test_directional_hand_value() -> None:
    src = torch.tensor([[1.0, 0.0, 0.0]])
    img = torch.tensor([[0.0, 1.0, 0.0]])  # direction (-1, 1, 0)
    t_src = torch.tensor([1.0, 0.0, 0.0])
    t_tgt = torch.tensor([0.0, 0.0, 1.0])  # direction (-1, 0, 1)
    # cos = 1 / 2
    assert losses.directional_clip_loss(img, src, t_tgt, t_src).item() == pytest.approx(0.5, abs=1e-6)
    # perfectly aligned direction -> 0
    assert losses.directional_clip_loss(img, src, torch.tensor([0.0, 5.0, 0.0]), t_src).item() == pytest.approx(
        0.0, abs=1e-6
    )


def test_directional_zero_image_direction_finite() -> None:
    g = torch.Generator().manual_seed(2)
    src = torch.randn(4, 16, generator=g)
    img = src.clone().requires_grad_()  # stylized == source (step 0)
    t_src, t_tgt = torch.randn(16, generator=g), torch.randn(16, generator=g)
    loss = losses.directional_clip_loss(img, src, t_tgt, t_src)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() == pytest.approx(1.0)
    assert torch.isfinite(img.grad).all()
    assert img.grad.abs().sum() > 0  # non-degenerate: optimization can start
    # one small gradient step decreases the loss
    with torch.no_grad():
        stepped = img - 1e-6 * img.grad / img.grad.norm()
    assert losses.directional_clip_loss(stepped, src, t_tgt, t_src) < loss


# ----------------------------------------------------------------------------- Eq. 9 / 2 / 8
def test_perceptual_hand_value() -> None:
    a = [torch.zeros(1, 2, 2, 2), torch.zeros(1, 1, 1, 1)]
    b = [torch.ones(1, 2, 2, 2), torch.full((1, 1, 1, 1), 3.0)]
    assert losses.perceptual_loss(a, b).item() == pytest.approx((1 + 9) / 2)
    assert losses.perceptual_loss(a, b, weights=[1.0, 0.0]).item() == pytest.approx(1.0)
    with pytest.raises(ValueError):
        losses.perceptual_loss(a, b[:1])


def test_reconstruction_and_psnr() -> None:
    rgb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    tgt = torch.tensor([[0.1, 0.1, 0.1], [0.0, 0.0, 0.0]])
    assert losses.reconstruction_loss(rgb, tgt).item() == pytest.approx((0.01 + 1.0) / 2)
    mask = torch.tensor([True, False])
    assert losses.reconstruction_loss(rgb, tgt, mask).item() == pytest.approx(0.01)
    assert losses.psnr(rgb, tgt, mask).item() == pytest.approx(20.0)
    assert losses.reconstruction_loss(rgb, tgt, torch.zeros(2)).item() == 0.0
    assert torch.isfinite(losses.psnr(tgt, tgt))


def test_contrastive_loss_is_float32_under_bfloat16_autocast() -> None:
    """trainer.precision=bf16-mixed runs the stylization step under autocast: the negatives' cosines stay
    float32 like the positive's (a bfloat16 matmul shifted the logits by up to 0.01 at tau 0.07)."""
    g = torch.Generator().manual_seed(0)
    q, p, n = torch.randn(13, 512, generator=g), torch.randn(512, generator=g), torch.randn(200, 512, generator=g)
    ref = losses.contrastive_loss(q, p, n)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = losses.contrastive_loss(q, p, n)
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, ref, rtol=1e-6, atol=1e-6)
