"""Model only what a scene requires: what do the scene-derived choices save? (issue 5)

For each scene — fern (LLFF, forward-facing, NDC), the shipped head (object with
mattes) and a selfie-video scene (``fangzhou_nature``: frames + COLMAP model +
mattes, at 270x480) — and each variant of the render settings:

* ``auto``: what :func:`~nerfart_plugin.systems.scene_setup.decide_setup` picks
  (occupancy grid on, background model ``auto``: on only for unbounded captures
  without masks — off for all three scenes);
* ``no occupancy``: ``render.occupancy.enabled=false`` (uniform stratified samples);
* ``background model``: ``render.background_model=true`` (learned environment map forced on);

measure the time and peak memory of a training step (``reconstruct.batch_rays``
rays, forward + backward + Adam, through the project's ReconstructionSystem and a
Lightning Trainer; mean over ``--steps`` steps after ``--warmup`` steps, so the
occupancy-grid refreshes every ``update_every`` steps are amortised in) and of
rendering one full held-out view without grad (``render.chunk`` rays at a time).
Each (scene, variant, training|rendering) runs in a fresh subprocess; memory = peak
RSS (VmHWM, reset after loading the scene and building the model) above the RSS at that moment
(``torch.cuda.max_memory_allocated`` on CUDA).

    python benchmarks/scene_setup.py
    python benchmarks/scene_setup.py --scenes head fern
    python benchmarks/scene_setup.py --quick
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
sys.path.insert(0, str(ROOT))

from benchmarks import common  # noqa: E402

log = logging.getLogger("bench.scene_setup")
NAME = "scene_setup"
VARIANTS = {
    "auto": [],
    "no occupancy": ["render.occupancy.enabled=false"],
    "background model": ["render.background_model=true"],
}


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
    import lightning as L
    import torch

    from nerfart_plugin.pipeline import Pipeline
    from nerfart_plugin.systems.base import steps_loader
    from nerfart_plugin.systems.reconstruction import ReconstructionSystem

    common.quiet_logs()
    p = Pipeline(common.compose(["stage=reconstruct", *payload["overrides"]]))
    p.load_data()
    mode = payload["mode"]
    if mode == "train":
        p.dm.setup("fit")
    c = p.c
    torch.manual_seed(0)
    system = ReconstructionSystem(c["reconstruct"], c["backbone"], c["encoding"], c["render"], p.setup,
                                  train_rays=p.dm.train_rays if mode == "train" else None, seed=int(c["seed"]))
    system.to(p.device)
    info = {"setup": {k: v for k, v in p.setup.to_dict().items() if k != "reasons"},
            "image": [p.scene.width, p.scene.height], "rays_per_view": p.scene.width * p.scene.height}
    cuda = p.device.type == "cuda"
    if mode == "render":  # warm-up on a few rays: lazy initialisation is not part of the measurement
        view = p.dm.view_batch((p.scene.val_ids or p.scene.train_ids)[0])
        with torch.no_grad():
            system.eval().renderer.render_chunked({k: (v[:64] if torch.is_tensor(v) and v.dim() else v)
                                                   for k, v in view.items()}, chunk=64)
    gc.collect()
    base = torch.cuda.memory_allocated(p.device) if cuda else common.reset_peak_rss()
    if cuda:
        torch.cuda.reset_peak_memory_stats(p.device)
    if mode == "render":
        t0 = time.perf_counter()
        system.eval()
        with torch.no_grad():
            system.render_view(view, chunk=int(c["render"]["chunk"]))
        if cuda:
            torch.cuda.synchronize()
        secs = time.perf_counter() - t0
        info.update(seconds=secs)
    else:
        warm, n = int(payload["warmup"]), int(payload["steps"])
        times: list[float] = []

        class Timer(L.Callback):
            def on_train_batch_start(self, trainer, pl_module, *a: Any) -> None:
                self.t = time.perf_counter()

            def on_train_batch_end(self, trainer, pl_module, *a: Any) -> None:
                if cuda:
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - self.t)

        dev = p.device
        trainer = L.Trainer(max_steps=warm + n, accelerator={"cuda": "gpu"}.get(dev.type, "cpu"), devices=1,
                            logger=False, callbacks=[Timer()], enable_checkpointing=False, enable_model_summary=False,
                            enable_progress_bar=False, num_sanity_val_steps=0, limit_val_batches=0)
        trainer.fit(system, train_dataloaders=steps_loader())
        meas = times[warm:] or times
        info.update(seconds=statistics.fmean(meas), seconds_median=statistics.median(meas), steps=len(meas),
                    occupied_fraction=(system.renderer.occupancy.occupied_fraction
                                       if system.renderer.occupancy is not None else None))
    peak = torch.cuda.max_memory_allocated(p.device) - base if cuda else common.peak_rss() - base
    info.update(peak_bytes=int(peak), how="cuda max_memory_allocated" if cuda else "peak RSS")
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
    p.add_argument("--warmup", type=int, default=None, help="training steps before measuring (default 8; quick 2)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per child process")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every run")
    common.add_common_args(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    q = args.quick
    scenes = args.scenes or (["head"] if q else ["fern", "head", "video"])
    steps = args.steps or (3 if q else 32)
    warm = args.warmup if args.warmup is not None else (2 if q else 8)
    extra = list(args.override) + (QUICK_OVERRIDES if q else [])
    info = common.machine_info()
    sov = scene_overrides()

    results: list[dict[str, Any]] = []
    for scene in scenes:
        for variant in args.variants:
            row: dict[str, Any] = {"scene": scene, "variant": variant}
            for mode in ("train", "render"):
                ov = [*sov[scene], *(QUICK[scene] if q else []), *VARIANTS[variant], *extra]
                out = common.run_child(Path(__file__), {"overrides": ov, "mode": mode, "steps": steps,
                                                        "warmup": warm}, args.timeout)
                log.info("%s / %s / %s: %s", scene, variant, mode,
                         {k: v for k, v in out.items() if k not in ("setup", "error")} | (
                             {"error": out["error"]} if "error" in out else {}))
                row[mode] = out
            results.append(row)

    def cell(r: dict, mode: str, key: str, f) -> str:
        m = r[mode]
        if m.get("status") != "ok":
            return {"timeout": f"> {args.timeout:g} s"}.get(m.get("status"), "error: " + m.get("error", "?")[:50])
        return f(m[key])

    def rel_to_auto(r: dict, mode: str, key: str) -> str:
        auto = next((x for x in results if x["scene"] == r["scene"] and x["variant"] == "auto"), None)
        if auto is None or r["variant"] == "auto" or auto[mode].get("status") != "ok" or r[mode].get("status") != "ok":
            return ""
        return f" ({r[mode][key] / max(auto[mode][key], 1e-12):.2f}x)"

    mib = lambda b: f"{b / 2**20:.0f}"
    rows = []
    for r in results:
        setup = r["train"].get("setup") or r["render"].get("setup") or {}
        img = r["render"].get("image") or r["train"].get("image")
        occ = setup.get("occupancy_resolution", 0)
        choice = ((f"occ {occ}^3" if occ else "occ off") + f", bg model {'on' if setup.get('background_model') else 'off'}"
                  + (", NDC" if setup.get("ndc") else "")) if setup else "?"
        rows.append([r["scene"], f"{img[0]}x{img[1]}" if img else "?", r["variant"], choice,
                     cell(r, "train", "seconds", lambda v: f"{v:.3f}") + rel_to_auto(r, "train", "seconds"),
                     cell(r, "train", "peak_bytes", mib) + rel_to_auto(r, "train", "peak_bytes"),
                     cell(r, "render", "seconds", lambda v: f"{v:.2f}") + rel_to_auto(r, "render", "seconds"),
                     cell(r, "render", "peak_bytes", mib) + rel_to_auto(r, "render", "peak_bytes")])
    c = common.compose(["stage=reconstruct", *extra])
    body = [
        f"Default config (backbone={c['backbone']['name']}, encoding={c['encoding']['name']}, "
        f"{c['render']['num_samples']} samples/ray, {c['reconstruct']['batch_rays']} rays/step, occupancy "
        f"{c['render']['occupancy']['resolution']}^3 refreshed every {c['render']['occupancy']['update_every']} steps"
        + (f"; extra overrides {' '.join(extra)}" if extra else "") + "). "
        f"Training step: mean over {steps} steps after {warm} warm-up steps (untrained field). View: one full held-out "
        "view, no grad. Memory: peak RSS (MiB) above the child's RSS after loading the scene and building the model (peak mark reset there), "
        "one fresh process per cell. In brackets: relative to the scene's `auto` setup. The number of samples per ray "
        "is the same in every variant: the occupancy grid moves samples to occupied space (quality per sample), it "
        "does not remove samples.",
        "",
    ]
    body += common.md_table(["scene", "image", "variant", "setup", "train step (s)", "train peak (MiB)",
                             "render view (s)", "render peak (MiB)"], rows, "lllrrrrr")
    raw = (common.QUICK_OUT.parent if q else ROOT / "outputs" / "benchmarks") / f"{NAME}.json"
    raw.parent.mkdir(parents=True, exist_ok=True)
    raw.write_text(json.dumps(results, indent=1, default=str))
    text = common.section(NAME, "Scene-derived setup: what occupancy grid and background model cost or save",
                          common.command(NAME + ".py", argv), info, body, q)
    common.finish(args, NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
