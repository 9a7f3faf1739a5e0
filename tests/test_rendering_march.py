"""Early ray termination (``VolumeRenderer.march``): the dense render's image within ``stop_transmittance``,
fewer field evaluations, and ``t_samples`` that re-render the same pixels."""

from __future__ import annotations

import pytest
import torch
from render_helpers import front_view, tiny_renderer

from nerfart_plugin.rendering.two_pass import render_fixed_samples

#: backbones made opaque at init (a sharp sphere, a dense fog), so rays terminate
OPAQUE = {
    "nerf": {"density_bias": 4.0},
    "volsdf": {"beta_init": 0.003},
    "neus-sections": {"init_variance": 0.8, "alpha_mode": "sections"},
    "neus-gradient": {"init_variance": 0.8, "alpha_mode": "gradient"},
}


def _renderer(name: str, occupancy: int, samples: int = 32) -> torch.nn.Module:
    torch.manual_seed(0)
    r = tiny_renderer(name.split("-")[0], occupancy, samples, **OPAQUE[name])
    if r.occupancy is not None:
        r.occupancy.update(r.field, 0, force=True)
    return r.eval()


@pytest.mark.parametrize("name", list(OPAQUE))
@pytest.mark.parametrize("occupancy", [0, 8])
def test_march_matches_the_dense_render_within_the_stop(name: str, occupancy: int) -> None:
    r = _renderer(name, occupancy)
    view = front_view(20, 16, 80.0)  # the sphere (radius 0.5) fills the view
    with torch.no_grad():
        dense = r(view, perturb=True, generator=torch.Generator().manual_seed(1))
        m = r.march(view, t_samples=dense["t_samples"])
    eps = r.stop_transmittance
    assert float((m["rgb"] - dense["rgb"]).abs().max()) <= eps + 1e-5
    assert float((m["opacity"] - dense["opacity"]).abs().max()) <= eps + 1e-5
    solid = dense["opacity"] > 0.5
    assert bool(solid.any()), "the fixture should show an opaque object"
    assert float((m["depth"] - dense["depth"])[solid].abs().max()) <= 1e-3
    if "normal" in dense:
        assert float((m["normal"] - dense["normal"]).abs().max()) <= 1e-3
    dense_evaluations = int((dense["deltas"] > 0).sum())
    assert int(m["samples_evaluated"]) < 0.8 * dense_evaluations, "opaque rays should stop early"


@pytest.mark.parametrize("name", list(OPAQUE))
def test_marched_samples_re_render_the_same_pixels(name: str) -> None:
    """Pass 2 of the two-pass backprop re-renders at the returned t_samples: same image, fewer sections."""
    r = _renderer(name, 8)
    view = front_view(20, 16, 20.0)
    first = render_fixed_samples(r, view, chunk=97, perturb=True, generator=torch.Generator().manual_seed(2))
    again = r(view, perturb=False, t_samples=first["t_samples"])
    torch.testing.assert_close(again["rgb"].detach(), first["rgb"], rtol=0, atol=2e-6)
    kept = int((again["deltas"] > 0).sum())
    full = r(view, perturb=True, generator=torch.Generator().manual_seed(2))
    assert kept < int((full["deltas"] > 0).sum())


def test_zero_stop_is_the_dense_render() -> None:
    r = _renderer("volsdf", 8)
    r.stop_transmittance = 0.0
    view = front_view(12, 10, 12.0)
    with torch.no_grad():
        dense = r(view, perturb=False)
        m = r.march(view, t_samples=dense["t_samples"])
    torch.testing.assert_close(m["rgb"], dense["rgb"], rtol=0, atol=0)
    torch.testing.assert_close(m["t_samples"], dense["t_samples"], rtol=0, atol=0)
    assert int(m["samples_evaluated"]) == int((dense["deltas"] > 0).sum())


def test_rays_that_miss_the_grid_are_never_evaluated() -> None:
    r = _renderer("volsdf", 8)
    view = front_view(12, 10, 12.0)
    view["rays_o"] = view["rays_o"] + torch.tensor([5.0, 0.0, 0.0])  # the camera looks past the box
    with torch.no_grad():
        m = r.march(view)
    assert int(m["samples_evaluated"]) == 0
    torch.testing.assert_close(m["rgb"], torch.ones_like(m["rgb"]))  # the white background
    assert float(m["opacity"].abs().max()) == 0.0
    # a chunk of missing rays still has every output (a full view concatenates chunks)
    assert m["normal"].shape == (view["rays_o"].shape[0], 3) and float(m["normal"].abs().max()) == 0.0
    view["H"], view["W"] = 12, 10
    full = r.render_chunked(view, chunk=7)
    assert {k: tuple(v.shape) for k, v in full.items() if torch.is_tensor(v)} == {
        "rgb": (120, 3), "depth": (120,), "opacity": (120,), "normal": (120, 3)}


def test_extreme_density_stays_finite() -> None:
    """A density of ~3e6 (trunc_exp's cap) stops every ray at its first sample, with finite outputs."""
    r = _renderer("nerf", 0)
    r.field.density_bias = 40.0
    view = front_view(8, 8, 8.0)
    with torch.no_grad():
        m = r.march(view)
    assert all(bool(torch.isfinite(m[k]).all()) for k in ("rgb", "depth", "opacity"))
    assert int(m["samples_evaluated"]) <= view["rays_o"].shape[0] * r.march_block


@pytest.mark.parametrize("block", [1, 3, 64])
def test_block_size_does_not_change_the_image(block: int) -> None:
    r = _renderer("neus-sections", 8)
    view = front_view(12, 10, 12.0)
    with torch.no_grad():
        ref = r.march(view)
        r.march_block = block
        m = r.march(view, t_samples=ref["t_samples"])
    assert float((m["rgb"] - ref["rgb"]).abs().max()) <= 2 * r.stop_transmittance


def test_full_views_render_with_view_samples() -> None:
    """render_chunked (validation, evaluation, videos) samples render.view_samples per ray, not num_samples."""
    r = _renderer("volsdf", 8, samples=32)
    view = {**front_view(12, 10, 12.0), "H": 12, "W": 10}
    r.view_samples = 6
    with torch.no_grad():
        full = r.render_chunked(view, chunk=50, with_normals=False)
        six = r.march(view, num_samples=6, with_normals=False)
        thirty_two = r.march(view, with_normals=False)
    torch.testing.assert_close(full["rgb"], six["rgb"], rtol=0, atol=1e-6)
    assert float((full["rgb"] - thirty_two["rgb"]).abs().max()) > 1e-4
    assert six["t_samples"].shape[1] == 6 and thirty_two["t_samples"].shape[1] == 32


def test_few_view_samples_only_where_an_occupancy_grid_places_them() -> None:
    """render.view_samples (and stylize.num_samples) apply where the occupancy grid puts the samples at the
    surface; without a grid (NDC captures: uniform samples over the frustum) full views keep num_samples,
    the density the field was trained with."""
    from render_helpers import SceneSetup, build_renderer

    view = {**front_view(12, 10, 12.0), "H": 12, "W": 10}
    for occupancy, want in ((8, 6), (0, 32)):
        torch.manual_seed(0)
        setup = SceneSetup("object", 1.0, False, [1.0, 1.0, 1.0], False, occupancy, 32, True)
        r = build_renderer({"backbone": {"name": "volsdf"}, "encoding": {"name": "grid", "resolution": 16},
                            "render": {"view_samples": 6, "occupancy": {"warmup_steps": 0}}}, setup).eval()
        assert r.view_samples == (6 if occupancy else None) and r.guided_samples(6) == (6 if occupancy else None)
        with torch.no_grad():
            full = r.render_chunked(view, chunk=50, with_normals=False)
            ref = r.march(view, num_samples=want, with_normals=False)
        torch.testing.assert_close(full["rgb"], ref["rgb"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", list(OPAQUE))
def test_the_off_surface_share_needs_no_normals(name: str) -> None:
    """The evaluation's off-surface share (``metrics.json``'s ``off_surface_weight``) renders without a graph
    and without the normals (an SDF field's gradient costs a backward pass per sample), and reads the same weights
    as a render with both (NeuS' gradient opacity too)."""
    from nerfart_plugin.objectives.evaluation import off_surface_share, off_surface_weight

    r = _renderer(name, 8)
    view = front_view(20, 16, 60.0)
    full = r(view)  # with a graph and the normals
    off, total = off_surface_weight(full["weights"].detach(), full["t"], full["deltas"], view["rays_d"].norm(dim=-1),
                                    0.05)
    calls: list[tuple[bool, bool]] = []

    def spy(batch: dict, with_normals: bool = True) -> dict:
        calls.append((torch.is_grad_enabled(), with_normals))
        return r(batch, with_normals=with_normals)

    share = off_surface_share(spy, view, chunk=97)
    assert calls and set(calls) == {(False, False)}
    assert share == pytest.approx(float(off.sum()) / float(total.sum()), rel=1e-5, abs=1e-7)
    assert 0.0 < float(total.sum())
