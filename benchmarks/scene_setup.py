"""Model only what a scene requires: what do the scene-derived choices save? (issue 5)

For each scene — fern (LLFF, forward-facing, NDC), the shipped head (object with
mattes) and a selfie-video scene (``fangzhou_nature``: frames + COLMAP model +
mattes, at 270x480) — and each variant of the render settings:

* ``auto``: what :func:`~nerfart_plugin.data.setup.decide_setup` picks
  (occupancy grid ``auto``: on except for forward-facing NDC captures; background
  model ``auto``: on only for unbounded captures without masks — off for all three);
* ``occupancy flipped``: the opposite of auto's occupancy choice
  (``render.occupancy.enabled=false`` for head and video, ``true`` for fern);
* ``background flipped``: the opposite of auto's background choice (here: the
  learned environment map forced on);

train ``--warmup`` untimed steps (so the occupancy grid reflects the scene, as it
does for most of a real run), then measure the time and peak memory of a training
step (``reconstruct.batch_rays`` rays, forward + backward + Adam, through the
project's ReconstructionSystem and a Lightning Trainer; mean over ``--steps`` steps,
so the occupancy-grid refreshes every ``update_every`` steps are amortised in) and
of rendering one full held-out view without grad (``render.chunk`` rays at a time),
with that view's PSNR (what the choice costs in quality at equal steps). Each
(scene, variant) runs in a fresh subprocess; memory = peak RSS (VmHWM, reset when
the measurement starts) above the RSS at that moment (``torch.cuda.max_memory_allocated``
on CUDA).

    python -m benchmarks scene_setup
    python -m benchmarks scene_setup --scenes head fern
    python -m benchmarks scene_setup --quick
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.scene_setup")
NAME = "scene_setup"
VARIANTS: dict[str, tuple[str, ...]] = {"auto": (), "occupancy flipped": ("occupancy",),
                                         "background flipped": ("background",)}


def scene_overrides() -> dict[str, list[str]]:
    data = common.shared_data()
    return {
        "fern": ["data=llff", f"data.path={data / 'llff_fern'}", "data.factor=8"],
        "head": ["data=h3ds", "data.resolution=128"],
        "video": ["data=selfie", f"data.path={data / 'fangzhou_nature'}", "data.resolution=480"],
    }


QUICK = {"fern": ["data.resolution=48"], "head": ["data.resolution=32"], "video": ["data.resolution=48"]}
QUICK_OVERRIDES = ["render.num_samples=16", "reconstruct.batch_rays=256", "render.occupancy.resolution=16",
                   "render.occupancy.update_every=2"]


# --------------------------------------------------------------------------- child
def measure(payload: dict[str, Any]) -> dict[str, Any]:
    """One (scene, variant): ``warmup`` untimed training steps (the occupancy grid adapts to the
    scene), ``steps`` timed training steps (time and peak memory), then one held-out view rendered
    without grad (time, peak memory, PSNR against the photo)."""
    import lightning as L
    import torch

    from nerfart_plugin.objectives.evaluation import view_metrics
    from nerfart_plugin.run.factories import build_reconstruction_system, build_scene
    from nerfart_plugin.run.fit import train_steps

    common.quiet_logs()
    scene = build_scene(common.compose(["stage=reconstruct", *payload["overrides"]]))
    dev = scene.device
    flip = payload.get("flip", [])
    if flip:  # the opposite of what decide_setup chose for this scene
        c = dict(scene.plain, render=dict(scene.plain["render"]))
        if "occupancy" in flip:
            c["render"]["occupancy"] = {**c["render"]["occupancy"], "enabled": not scene.setup.occupancy_resolution}
        if "background" in flip:
            c["render"]["background_model"] = not scene.setup.background_model
        scene = scene.with_config(c)
    cuda = dev.type == "cuda"
    torch.manual_seed(0)
    system = build_reconstruction_system(scene)
    system.to(dev)
    info: dict[str, Any] = {"setup": {k: v for k, v in scene.setup.to_dict().items() if k != "reasons"},
                            "image": [scene.scene.width, scene.scene.height]}
    warm, n = int(payload["warmup"]), int(payload["steps"])
    times: list[float] = []
    marks: dict[str, int] = {}

    class Timer(L.Callback):
        """Times steps after the warm-up; resets the peak-memory mark when timing starts."""

        def on_train_batch_start(self, trainer, pl_module, batch: Any, batch_idx: int) -> None:
            if trainer.global_step == warm:
                marks["train_base"] = torch.cuda.memory_allocated(dev) if cuda else common.reset_peak_rss()
                if cuda:
                    torch.cuda.reset_peak_memory_stats(dev)
            self.t = time.perf_counter()

        def on_train_batch_end(self, trainer, pl_module, *a: Any) -> None:
            if cuda:
                torch.cuda.synchronize()
            times.append(time.perf_counter() - self.t)

    train_steps(system, warm + n, dev, scene.cfg.trainer, callbacks=[Timer()])
    peak = (torch.cuda.max_memory_allocated(dev) if cuda else common.peak_rss()) - marks.get("train_base", 0)
    meas = times[warm:] or times
    info.update(train_seconds=statistics.fmean(meas), train_seconds_median=statistics.median(meas),
                steps=len(meas), warmup=warm, train_peak_bytes=int(peak), occupied_fraction=system.occupied_fraction)

    vid = (scene.scene.val_ids or scene.scene.train_ids)[0]
    view = scene.dm.view_batch(vid)
    system.eval()
    gc.collect()
    base = torch.cuda.memory_allocated(dev) if cuda else common.reset_peak_rss()
    if cuda:
        torch.cuda.reset_peak_memory_stats(dev)
    t0 = time.perf_counter()
    with torch.no_grad():
        img = system.render_view(view, chunk=scene.cfg.render.chunk)
    if cuda:
        torch.cuda.synchronize()
    secs = time.perf_counter() - t0
    peak = (torch.cuda.max_memory_allocated(dev) if cuda else common.peak_rss()) - base
    m = view_metrics(img["rgb"], view["rgb"].reshape(img["rgb"].shape).to(dev), view.get("mask"))
    info.update(render_seconds=secs, render_peak_bytes=int(peak), view_id=int(vid),
                psnr=float(m["psnr"]), psnr_masked=float(m["psnr_masked"]) if "psnr_masked" in m else None,
                how="cuda max_memory_allocated" if cuda else "peak RSS")
    return info


# --------------------------------------------------------------------------- parent
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--child"]:
        return common.child_main(measure, argv[1])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=None, choices=["fern", "head", "video"],
                   help="default: fern head video (quick: head)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--steps", type=int, default=None, help="measured training steps (default 32; quick 3)")
    p.add_argument("--warmup", type=int, default=None,
                   help="untimed training steps first, so the occupancy grid fits the scene (default 600; quick 2)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per child process")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every run")
    common.add_common_args(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    q = args.quick
    scenes = args.scenes or (["head"] if q else ["fern", "head", "video"])
    steps = args.steps or (3 if q else 32)
    warm = args.warmup if args.warmup is not None else (2 if q else 600)
    extra = list(args.override) + (QUICK_OVERRIDES if q else [])
    info = common.machine_info()
    sov = scene_overrides()

    results: list[dict[str, Any]] = []
    for scene in scenes:
        for variant in args.variants:
            ov = [*sov[scene], *(QUICK[scene] if q else []), *extra]
            out = common.run_child(Path(__file__), {"overrides": ov, "flip": list(VARIANTS[variant]), "steps": steps,
                                                    "warmup": warm}, args.timeout)
            log.info("%s / %s: %s", scene, variant, {k: v for k, v in out.items() if k not in ("setup", "error")} | (
                {"error": out["error"]} if "error" in out else {}))
            results.append({"scene": scene, "variant": variant, "out": out})

    def cell(r: dict, key: str, f) -> str:
        m = r["out"]
        if m.get("status") != "ok":
            return {"timeout": f"> {args.timeout:g} s"}.get(m.get("status"), "error: " + m.get("error", "?")[:50])
        return f(m[key]) if m.get(key) is not None else "–"

    def rel_to_auto(r: dict, key: str) -> str:
        auto = next((x for x in results if x["scene"] == r["scene"] and x["variant"] == "auto"), None)
        if auto is None or r["variant"] == "auto" or auto["out"].get("status") != "ok" or r["out"].get("status") != "ok":
            return ""
        return f" ({r['out'][key] / max(auto['out'][key], 1e-12):.2f}x)"

    mib = lambda b: f"{b / 2**20:.0f}"
    rows = []
    for r in results:
        setup = r["out"].get("setup") or {}
        img = r["out"].get("image")
        occ = setup.get("occupancy_resolution", 0)
        choice = ((f"occ {occ}^3" if occ else "occ off") + f", bg model {'on' if setup.get('background_model') else 'off'}"
                  + (", NDC" if setup.get("ndc") else "")) if setup else "?"
        rows.append([r["scene"], f"{img[0]}x{img[1]}" if img else "?", r["variant"], choice,
                     cell(r, "occupied_fraction", lambda v: f"{100 * v:.0f}%"),
                     cell(r, "train_seconds", lambda v: f"{v:.3f}") + rel_to_auto(r, "train_seconds"),
                     cell(r, "train_peak_bytes", mib) + rel_to_auto(r, "train_peak_bytes"),
                     cell(r, "render_seconds", lambda v: f"{v:.2f}") + rel_to_auto(r, "render_seconds"),
                     cell(r, "render_peak_bytes", mib) + rel_to_auto(r, "render_peak_bytes"),
                     cell(r, "psnr", lambda v: f"{v:.2f}"), cell(r, "psnr_masked", lambda v: f"{v:.2f}")])
    c = common.compose(["stage=reconstruct", *extra])
    body = [
        f"Default config (backbone={c['backbone']['name']}, encoding={c['encoding']['name']}, "
        f"{c['render']['num_samples']} samples/ray, {c['reconstruct']['batch_rays']} rays/step, occupancy "
        f"{c['render']['occupancy']['resolution']}^3 refreshed every {c['render']['occupancy']['update_every']} steps"
        + (f"; extra overrides {' '.join(extra)}" if extra else "") + "). "
        f"One fresh process per row: {warm} untimed warm-up training steps (so the occupancy grid has adapted to "
        f"the scene), then the training step time = mean over {steps} steps; then one full held-out view rendered "
        "without grad, and its PSNR against the photo after those "
        f"{warm + steps} steps (masked PSNR inside the matte where the scene has mattes). Memory: peak RSS (MiB) "
        "above the RSS when the measurement started (peak mark reset there). In brackets: relative to the "
        "scene's `auto` setup. The number of samples per ray is the same in every variant: the occupancy grid "
        "moves samples into occupied space and rays that cross no occupied cell are not evaluated at all.",
        "",
    ]
    body += common.md_table(["scene", "image", "variant", "setup", "occupied", "train step (s)", "train peak (MiB)",
                             "render view (s)", "render peak (MiB)", "PSNR", "masked PSNR"], rows, "llllrrrrrrr")
    raw = common.raw_path(NAME, q)
    raw.parent.mkdir(parents=True, exist_ok=True)
    raw.write_text(json.dumps(results, indent=1, default=str))
    text = common.section(NAME, "Scene-derived setup: what occupancy grid and background model cost or save",
                          common.command(NAME + ".py", argv), info, body, q)
    common.finish(args, NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
