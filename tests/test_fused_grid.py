"""The fused TensorVM lookup kernel (``fields/fused_grid.py``): the same features and gradients as ATen's
``grid_sample`` path up to float rounding, at the grid's edges too; where it does not serve (points with a
gradient, no compiler) the ATen path answers, with the reason logged; the build is cached; checkpoints keep
their layout-free shape and values."""

from __future__ import annotations

import copy
import logging

import pytest
import torch

from nerfart_plugin.fields import compiled, fused_grid
from nerfart_plugin.fields.encodings import TensorVMGridEncoding

needs_compiler = pytest.mark.skipif(compiled.cxx_compiler() is None, reason="no C++ compiler on this machine")


def _pair(resolution, components: int, out_features=None, dtype=torch.float32, seed: int = 0):
    torch.manual_seed(seed)
    aten = TensorVMGridEncoding({"resolution": resolution, "levels": 1 if isinstance(resolution, list) else 3,
                                 "n_components": components, "out_features": out_features}, bound=1.5).to(dtype)
    fused = copy.deepcopy(aten)
    fused.set_fused(True)
    return aten, fused


def _points(n: int, dtype=torch.float32, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 1.8  # some outside the box: clamped
    edges = torch.tensor([[1.5, 1.5, 1.5], [-1.5, -1.5, -1.5], [1.5, -1.5, 0.0], [0.0, 0.0, 0.0],
                          [1.5 - 1e-7, 1.5, -1.5], [2.0, -3.0, 1.5]], dtype=torch.float64)
    return torch.cat([edges, x]).to(dtype)


@needs_compiler
@pytest.mark.parametrize("resolution,components,dtype", [(16, 8, torch.float32), ([5, 9, 17], 3, torch.float32),
                                                         (12, 4, torch.float64), ([2], 16, torch.float32)])
def test_features_and_gradients_equal_the_aten_path(resolution, components, dtype) -> None:
    aten, fused = _pair(resolution, components, dtype=dtype)
    assert fused.fused and not aten.fused
    x = _points(3000, dtype)
    with torch.no_grad():
        a, b = aten(x), fused(x)
    assert b.shape == a.shape and b.dtype == dtype
    tol = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(b, a, **tol)
    grad = torch.randn_like(a)
    for enc in (aten, fused):
        enc.zero_grad()
        (enc(x) * grad).sum().backward()
    for (name, pa), (_, pb) in zip(aten.named_parameters(), fused.named_parameters()):
        assert pb.grad.shape == pa.grad.shape
        torch.testing.assert_close(pb.grad, pa.grad, rtol=1e-4, atol=1e-5, msg=name)


@needs_compiler
def test_gradcheck_in_double_precision() -> None:
    """The custom op's backward is its forward's derivative (finite differences in float64)."""
    _, fused = _pair([3, 4], 2, dtype=torch.float64)
    x = _points(40, torch.float64) / 1.5
    views = [fused_grid.channel_last(p, ln) for p, ln in zip(fused.planes, fused.lines)]
    planes = [v[0].detach().clone().requires_grad_(True) for v in views]
    lines = [v[1].detach().clone().requires_grad_(True) for v in views]
    assert torch.autograd.gradcheck(lambda *t: fused_grid.tensorvm_features(x.clamp(-1, 1), list(t[:2]), list(t[2:])),
                                    (*planes, *lines))


@needs_compiler
def test_points_with_a_gradient_take_the_aten_path() -> None:
    """An analytic SDF gradient differentiates the lookups with respect to the points: ATen's path serves them."""
    aten, fused = _pair(8, 4, out_features=5)
    x = _points(50).requires_grad_(True)
    assert not fused_grid.serves(x) and fused_grid.serves(x.detach())
    ga = torch.autograd.grad(aten(x).sum(), x)[0]
    gb = torch.autograd.grad(fused(x).sum(), x)[0]
    torch.testing.assert_close(gb, ga)


@needs_compiler
def test_the_layout_changes_neither_shapes_nor_checkpoints() -> None:
    aten, fused = _pair(8, 4, out_features=6)
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in fused.planes)
    fresh = TensorVMGridEncoding({"resolution": 8, "levels": 3, "n_components": 4, "out_features": 6}, bound=1.5)
    fresh.load_state_dict(fused.state_dict())
    x = _points(100)
    with torch.no_grad():
        torch.testing.assert_close(fresh(x), aten(x))
    assert {k: v.shape for k, v in fused.state_dict().items()} == {k: v.shape for k, v in aten.state_dict().items()}


@needs_compiler
def test_the_build_is_cached_by_content(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("NERFART_COMPILE_CACHE", str(tmp_path))
    cxx = compiled.cxx_compiler()
    path = fused_grid.library_path(cxx)
    assert path.parent == tmp_path / "nerfart_kernels" and path.name.startswith("tensorvm-")
    fused_grid._build(cxx, path)
    assert path.is_file() and [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary left
    monkeypatch.setattr(fused_grid, "FLAGS", (*fused_grid.FLAGS, "-DNERFART_OTHER"))
    assert fused_grid.library_path(cxx) != path  # other flags, another build


def test_without_a_compiler_the_aten_path_answers_and_says_why(monkeypatch, caplog) -> None:
    monkeypatch.setattr(fused_grid, "_library", None)
    monkeypatch.setattr(fused_grid, "_unavailable", None)
    monkeypatch.setattr(compiled, "cxx_compiler", lambda: None)
    torch.manual_seed(0)
    enc = TensorVMGridEncoding({"resolution": 8, "levels": 2, "n_components": 4, "out_features": 6})
    ref = copy.deepcopy(enc)
    with caplog.at_level(logging.WARNING, logger="nerfart_plugin"):
        enc.set_fused(True)
    assert "the grid's lookups stay ATen's: no C++ compiler on the PATH (install g++ or clang++" in caplog.text
    assert fused_grid.unavailable() and not fused_grid.serves(torch.zeros(4, 3))
    assert not enc.planes[0].is_contiguous(memory_format=torch.channels_last)  # layout untouched
    x = _points(64)
    with torch.no_grad():
        torch.testing.assert_close(enc(x), ref(x))


def test_a_failed_build_names_the_compiler_and_the_source(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(fused_grid, "SOURCE", tmp_path / "broken.cpp")
    (tmp_path / "broken.cpp").write_text("this is not C++\n")
    cxx = compiled.cxx_compiler()
    if cxx is None:
        pytest.skip("no C++ compiler on this machine")
    with pytest.raises(RuntimeError, match=r"failed on .*broken\.cpp"):
        fused_grid._build(cxx, tmp_path / "out" / "k.so")
    assert not any((tmp_path / "out").iterdir())  # nothing half-written left


@needs_compiler
def test_a_nan_point_is_nan_and_scatters_nothing() -> None:
    """A NaN coordinate (the clamp lets it through) reads no memory outside the planes: its features are NaN,
    as ATen's. Its backward adds nothing to the planes' gradients, even with a zero gradient (ATen's writes NaN
    into some cells then): every finite entry equals ATen's."""
    aten, fused = _pair(8, 4)
    x = _points(20)
    x[3, 1] = float("nan")
    with torch.no_grad():
        a, b = aten(x), fused(x)
    assert torch.isnan(b[3]).all() and torch.isnan(a[3]).all()
    torch.testing.assert_close(b[~torch.isnan(a).any(1)], a[~torch.isnan(a).any(1)])
    grad = torch.ones_like(a)
    grad[3] = 0.0
    for enc in (aten, fused):
        enc.zero_grad()
        out = enc(x)
        (torch.nan_to_num(out) * grad).sum().backward()
    for (name, pa), (_, pb) in zip(aten.named_parameters(), fused.named_parameters()):
        assert torch.isfinite(pb.grad).all(), name
        finite = torch.isfinite(pa.grad)
        torch.testing.assert_close(pb.grad[finite], pa.grad[finite], rtol=1e-4, atol=1e-5, msg=name)


@needs_compiler
def test_the_threads_split_the_points_and_sum_their_gradients() -> None:
    """Several threads (each with its own gradient buffer, summed at the end) give one thread's result."""
    aten, fused = _pair([6, 11, 23], 8)
    x = _points(30000)
    grad = torch.randn(x.shape[0], 72, generator=torch.Generator().manual_seed(3))
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            fused.zero_grad()
            out = fused(x)
            (out * grad).sum().backward()
            results.append((out.detach(), [p.grad.clone() for p in fused.parameters()]))
    finally:
        torch.set_num_threads(before)
    torch.testing.assert_close(results[1][0], results[0][0], rtol=0, atol=0)  # forward: the same arithmetic
    for g3, g1 in zip(results[1][1], results[0][1]):
        torch.testing.assert_close(g3, g1, rtol=1e-5, atol=1e-5)
    aten.zero_grad()
    (aten(x) * grad).sum().backward()
    for pa, g1 in zip(aten.parameters(), results[0][1]):
        torch.testing.assert_close(g1, pa.grad, rtol=1e-4, atol=1e-4)
