"""The compiled field (``compile``): the same renders and gradients as eager up to float rounding, on every
backbone; the decision (on, off, auto and its reasons); a compiler failure leaves the field eager."""

from __future__ import annotations

import copy
import logging

import pytest
import torch

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields import build_field
from nerfart_plugin.fields import compiled as compiled_mod
from nerfart_plugin.fields.compiled import (MIN_COMPILED_STEPS, compiler_missing, decide_compile, evaluate,
                                            set_compiled)
from nerfart_plugin.rendering import VolumeRenderer

needs_compiler = pytest.mark.skipif(compiler_missing(torch.device("cpu")) is not None,
                                    reason="no C++ compiler for torch.compile on this machine")
SMALL = {"hidden_dim": 16, "color_hidden_dim": 16, "feature_dim": 7}
GRID = {"name": "grid", "resolution": 16, "n_components": 4, "out_features": 8}


def _batch(R: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, -2.5]) + 0.05 * torch.randn(R, 3, generator=g)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.2 * torch.randn(R, 3, generator=g), dim=-1)
    return {"rays_o": o, "rays_d": d, "near": torch.full((R,), 1.0), "far": torch.full((R,), 4.0)}


FREQUENCY = {"name": "frequency", "n_freqs": 4}


def _pair(backbone: str, encoding: dict = GRID, **kw: object) -> tuple[VolumeRenderer, VolumeRenderer]:
    torch.manual_seed(0)
    eager = VolumeRenderer(build_field({"name": backbone, **SMALL, **kw}, encoding, bound=1.0), num_samples=16)
    comp = copy.deepcopy(eager)
    assert set_compiled(comp) == 1 and comp.field.compiled and not eager.field.compiled
    return eager, comp


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
def test_an_analytic_gradient_field_stays_eager(backbone: str) -> None:
    """The frequency encoding's SDF fields take d sdf / dx by autograd inside the query (grad_type=auto ->
    analytic), which compiled graphs do not support: they are not compiled, and train as before."""
    field = build_field({"name": backbone, **SMALL}, FREQUENCY, bound=1.0)
    r = VolumeRenderer(field, num_samples=16)
    assert field.grad_type == "analytic" and set_compiled(r) == 0 and not field.compiled
    r.train()
    out = r(_batch(24), perturb=True)
    (out["rgb"].square().mean() + sum(out["regularizers"].values())).backward()
    assert all(p.grad is not None for p in field.geo_net.parameters())


@needs_compiler
@pytest.mark.parametrize("backbone,encoding", [("nerf", GRID), ("volsdf", GRID), ("neus", GRID), ("nerf", FREQUENCY)])
def test_compiled_renders_and_gradients_equal_eager(backbone: str, encoding: dict) -> None:
    """No-grad renders (two batch sizes: the compile is shape-dynamic), with and without normals, and one
    training step's loss and parameter gradients agree with the eager field's to float rounding."""
    eager, comp = _pair(backbone, encoding)
    with torch.no_grad():
        for R, normals in ((48, True), (37, False)):
            a, b = eager.march(_batch(R), with_normals=normals), comp.march(_batch(R), with_normals=normals)
            for k in ("rgb", "depth", "opacity"):
                torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-5)
    losses = []
    for r in (eager, comp):
        r.train()
        out = r(_batch(40, seed=1), perturb=True, generator=torch.Generator().manual_seed(2))
        loss = out["rgb"].square().mean() + sum(v.sum() for v in out.get("regularizers", {}).values())
        r.zero_grad()
        loss.backward()
        losses.append(float(loss.detach()))
    assert losses[1] == pytest.approx(losses[0], rel=1e-5)
    assert comp.field.compiled and type(comp.field) in compiled_mod._COMPILED  # the compiled query was taken
    for (name, pa), (_, pb) in zip(eager.named_parameters(), comp.named_parameters()):
        if pa.grad is not None:
            torch.testing.assert_close(pb.grad, pa.grad, rtol=1e-3, atol=1e-6, msg=name)


def test_the_decision_and_its_reasons(monkeypatch) -> None:
    cpu = torch.device("cpu")
    least = MIN_COMPILED_STEPS["stylization"]
    assert decide_compile("off", cpu, 10**6, least) == (False, "off")
    monkeypatch.setattr(compiled_mod, "compiler_missing", lambda device: None)
    assert decide_compile("auto", cpu, least, least) == (True, "on")
    assert decide_compile("auto", cpu, None) == (True, "on")  # work that always pays (the viewer)
    on, why = decide_compile("auto", cpu, least - 1, least)
    assert not on and why == f"off ({least - 1} steps < {least}: the compile would not pay)"
    assert decide_compile("auto", cpu, 30, 60, "frames") == (False, "off (30 frames < 60: the compile would not pay)")
    assert decide_compile("on", cpu, 1, least) == (True, "on")  # asked for: compiled however short
    monkeypatch.setattr(compiled_mod, "compiler_missing", lambda device: "no C++ compiler on the PATH")
    assert decide_compile("auto", cpu, 10**6, least) == (False, "off (no C++ compiler on the PATH)")
    with pytest.raises(ConfigError, match=r"compile=on: no C\+\+ compiler on the PATH\. Use compile=auto"):
        decide_compile("on", cpu, 10**6, least)


def test_compiler_missing_names_what_to_install(monkeypatch) -> None:
    monkeypatch.setattr(compiled_mod.shutil, "which", lambda name: None)
    monkeypatch.delenv("CXX", raising=False)
    assert "install g++ or clang++" in compiler_missing(torch.device("cpu"))
    assert compiler_missing(torch.device("mps")) == "inductor does not compile for mps"


def test_a_compiler_failure_leaves_the_field_eager_and_says_why(monkeypatch, caplog) -> None:
    eager, comp = _pair("volsdf")

    def failing(cls):
        def call(*args, **kwargs):
            raise torch._dynamo.exc.TorchDynamoException("backend failed: no kernel")
        return call

    monkeypatch.setattr(compiled_mod, "compiled_query", failing)
    x = torch.rand(20, 3) - 0.5
    d = torch.nn.functional.normalize(torch.rand(20, 3), dim=-1)
    with torch.no_grad(), caplog.at_level(logging.WARNING, logger="nerfart_plugin"):
        out = evaluate(comp.field, x, d, with_normal=False)
        ref = eager.field.query(x, d, with_normal=False)
    torch.testing.assert_close(out["rgb"], ref["rgb"])
    assert not comp.field.compiled
    assert "VolSDFField is evaluated uncompiled: the compiler failed (TorchDynamoException: backend failed" in caplog.text


def test_the_compile_cache_lives_where_the_docs_say(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    monkeypatch.setenv(compiled_mod.CACHE_ENV, str(tmp_path / "kernels"))
    assert compiled_mod.use_cache_dir() == tmp_path / "kernels" and (tmp_path / "kernels").is_dir()
    monkeypatch.delenv(compiled_mod.CACHE_ENV)
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR")
    assert compiled_mod.cache_dir() == compiled_mod.Path.home() / ".cache" / "nerfart_plugin" / "inductor"


@needs_compiler
def test_short_work_stays_uncompiled_but_takes_the_fused_lookups() -> None:
    """Below the compile's threshold the grid's lookups still take the fused kernel (no per-run cost), and the
    choice says so; compile=off leaves ATen's lookups; a field without a grid has nothing to fuse."""
    cpu = torch.device("cpu")
    least = MIN_COMPILED_STEPS["stylization"]
    eager, r = _pair("volsdf")
    set_compiled(r, False)
    choice = compiled_mod.apply_compile(r, "auto", cpu, 10, least)
    assert choice == f"off (10 steps < {least}: the compile would not pay); grid lookups fused"
    assert not r.field.compiled and r.field.encoding.fused
    with torch.no_grad():
        torch.testing.assert_close(r.march(_batch(30))["rgb"], eager.march(_batch(30))["rgb"], rtol=1e-5, atol=1e-6)
    assert compiled_mod.apply_compile(r, "off", cpu, 10**6, least) == "off" and not r.field.encoding.fused
    assert compiled_mod.apply_compile(r, "auto", cpu, least, least) == "on" and r.field.encoding.fused
    freq = VolumeRenderer(build_field({"name": "nerf", **SMALL}, FREQUENCY, bound=1.0), num_samples=8)
    assert compiled_mod.apply_compile(freq, "auto", cpu, 10, least) == f"off (10 steps < {least}: the compile would not pay)"


@needs_compiler
def test_the_compiled_occupancy_sampler_places_the_same_sections() -> None:
    """With the fields compiled, the occupancy grid's lookups along the rays and the sections it places run
    compiled too (``set_compiled`` sets the grid's flag): the same cells, sections equal to float rounding."""
    from nerfart_plugin.fields.occupancy import OccupancyGrid
    from nerfart_plugin.rendering import occupancy_samples

    torch.manual_seed(0)
    grid = OccupancyGrid(resolution=24, bound=1.0)
    grid.occupied.copy_(torch.rand(grid.occupied.shape) > 0.7)
    r = VolumeRenderer(build_field({"name": "volsdf", **SMALL}, GRID, bound=1.0), num_samples=16, occupancy=grid)
    b = _batch(57, seed=4)
    b["rays_o"][:5] += torch.tensor([6.0, 0.0, 0.0])  # rays that miss the box
    eager = [occupancy_samples(b["rays_o"], b["rays_d"], b["near"], b["far"], grid, 16, 96, dilate=d) for d in (0, 2)]
    assert set_compiled(r) == 1 and grid.compiled
    t = torch.rand(57, 40, generator=torch.Generator().manual_seed(1)) * 4
    assert torch.equal(grid.query_rays(b["rays_o"], b["rays_d"], t), grid.at(grid.ray_cells(b["rays_o"], b["rays_d"], t)))
    for d, ref in zip((0, 2), eager):
        out = occupancy_samples(b["rays_o"], b["rays_d"], b["near"], b["far"], grid, 16, 96, dilate=d)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    set_compiled(r, False)
    assert not grid.compiled
