"""Run the stages a config asks for: reconstruct -> stylize -> export.

Folders (under ``output_root``, default ``outputs/``):

* ``reconstructions/<data>-<backbone>-<encoding>-<key>/``: keyed by a hash of the
  scene's content hash and every setting that changes the reconstruction, so a
  later stylization of the same data + backbone + settings reuses it and any
  change recomputes it. Holds ``last.ckpt`` (resume point), ``final.ckpt``
  (complete), ``metrics.json``, ``val/`` images, ``mesh/``.
* ``stylizations/<prompt>-<backbone>-<key>/``: keyed by the reconstruction key
  plus the prompt, guidance, experiment and stylization settings. Holds
  ``last.ckpt``, ``final.ckpt``, ``renders/``, ``video*.mp4``, ``metrics.json``, ``mesh/``.

Re-running the same command resumes from ``last.ckpt`` (``resume=true``); a
finished run is not recomputed or overwritten. ``resume=false`` moves an
unfinished folder aside (kept, renamed ``*.abandoned-<time>``) and starts over.

Reliability: the config is validated before anything is loaded (:mod:`nerfart_plugin.schema`),
the output root must be writable, each run folder is locked while a stage works in it
(:mod:`nerfart_plugin.utils.lock`, ``lock_timeout``), Ctrl-C stops at a step boundary with
a checkpoint (:class:`~nerfart_plugin.systems.callbacks.GracefulInterrupt`, exit code 130),
and checkpoints are read without running code and checked against the model
(:mod:`nerfart_plugin.checkpoints`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
import time
from pathlib import Path
from typing import Any, Optional

import lightning as L
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from nerfart_plugin.checkpoints import (META_KEY, allow_project_types, check_fits, checkpoint_meta, load_checkpoint,
                                        prefixed_state)
from nerfart_plugin.errors import ConfigError, NerfArtError, RunInterrupted
from nerfart_plugin.utils.device import pick_device
from nerfart_plugin.utils.io import atomic_path, atomic_write_json, atomic_write_text, check_writable_dir
from nerfart_plugin.utils.lock import run_lock

log = logging.getLogger("nerfart_plugin")

STAGES = ("reconstruct", "stylize", "all", "export")
_OOM_HINT = ("out of memory. Lower one of: render.chunk (rays per no-grad chunk), stylize.patch_size (rays per "
             "patch re-rendered with grad), stylize.resolution, reconstruct.batch_rays, render.num_samples, "
             "export.chunk.")


def config_hash(obj: Any, n: int = 12) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:n]


def slug(text: str, n: int = 40) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")[:n] or "prompt"


def _container(cfg: DictConfig | dict) -> dict:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)


def validate_config(c: dict) -> dict:
    """Every setting checked before anything is loaded (:mod:`nerfart_plugin.schema`: types, ranges,
    choices, unknown keys), then what depends on the stage: multi-device only for the reconstruction,
    a prompt for stylization, an existing ``source_checkpoint``, an available ``device``.

    Returns the config with the values validation converted (``"512"`` -> 512).
    """
    from nerfart_plugin import schema

    c = schema.validate_config(c)
    tc = c.get("trainer", {})
    distributed = tc.get("strategy", "auto") not in ("auto", None) or int(tc.get("num_nodes", 1)) != 1 \
        or tc.get("devices", 1) not in (1, "1")
    if distributed and c["stage"] != "reconstruct":
        raise ConfigError("Multi-device training (trainer.strategy/devices/num_nodes) is supported for "
                          "stage=reconstruct only: the stylization stage optimizes one view per step with several "
                          "backward passes (Section 4.4) on one device. Run stage=reconstruct with DDP, then "
                          "stage=stylize with trainer.strategy=auto trainer.devices=1 trainer.num_nodes=1.")
    if c["stage"] in ("stylize", "all"):
        from nerfart_plugin.guidance import validate_prompt

        if c.get("prompt") is None:
            raise ConfigError("stage=%s needs a style prompt: add +prompt=\"Vincent van Gogh\" (or stage=reconstruct)."
                              % c["stage"])
        validate_prompt(c["prompt"])
    src = c.get("source_checkpoint")
    if src and not Path(src).expanduser().is_file():
        raise ConfigError(f"source_checkpoint={src}: no such file. Point it at the final.ckpt of a reconstruction "
                          "(outputs/reconstructions/<run>/final.ckpt) or leave it out to use the cached one.")
    check_device(str(c.get("device", "auto")), c.get("trainer", {}).get("devices", 1))
    return c


def check_device(device: str, devices: Any = 1) -> None:
    """ConfigError if ``device`` names an accelerator this machine does not have, or ``trainer.devices``
    is a GPU-only form (-1, a list of ids) for a CPU / MPS run."""
    if device.startswith("cuda"):
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = int(device.split(":", 1)[1]) if ":" in device else 0
        if index >= n:
            raise ConfigError(f"device={device}: this machine has {n} CUDA device(s) (torch.cuda.device_count()); "
                              "use device=auto (the best available) or device=cpu.")
    if device == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise ConfigError("device=mps: Apple's Metal backend is not available here; use device=auto or device=cpu.")
    kind = pick_device(device).type
    if kind != "cuda" and not (devices == "auto" or (isinstance(devices, int) and devices >= 1)):
        from nerfart_plugin.schema import show

        raise ConfigError(f"trainer.devices={show(devices)}: on {kind} give a number of processes N >= 1 (or auto); "
                          "-1 and lists of device ids select GPUs (device=cuda).")


def _trainer(run_dir: Path, max_steps: int, device: torch.device, callbacks: list, tc: dict, **kw: Any) -> L.Trainer:
    """A Trainer for one stage; ``tc`` is the ``trainer`` config (precision, log_every_n_steps,
    strategy/devices/num_nodes for Lightning DDP)."""
    from lightning.pytorch.callbacks import TQDMProgressBar
    from lightning.pytorch.loggers import CSVLogger

    accelerator = {"cuda": "gpu", "mps": "mps"}.get(device.type, "cpu")
    devices: Any = tc.get("devices", 1)
    if device.type == "cuda" and device.index is not None and devices == 1:
        devices = [device.index]
    return L.Trainer(
        max_steps=max_steps, accelerator=accelerator, devices=devices, precision=tc.get("precision", "32-true"),
        strategy=tc.get("strategy", "auto"), num_nodes=int(tc.get("num_nodes", 1)), log_every_n_steps=int(tc.get("log_every_n_steps", 10)),
        logger=CSVLogger(str(run_dir), name="logs"), callbacks=[*callbacks, TQDMProgressBar(refresh_rate=10)],
        enable_checkpointing=False, enable_model_summary=False, num_sanity_val_steps=0,
        default_root_dir=str(run_dir), **kw,
    )


def _interrupted(trainer: L.Trainer, stop: Any, run_dir: Optional[Path]) -> str:
    """What an interrupted fit says: the step and how to resume."""
    last = run_dir / "last.ckpt" if run_dir is not None else None
    step = getattr(stop, "stopped_at", None)  # a graceful stop: checkpoint written at this step
    at = f"step {step}"
    if step is None:  # stopped at once (a second Ctrl-C): the last periodic checkpoint is the resume point
        saved = getattr(getattr(stop, "checkpoint", None), "_last_saved", -1)
        at = f"step {trainer.global_step}" + (f" (last checkpoint: step {saved})" if saved >= 0 else "")
    if last is not None and last.exists():
        return f"interrupted at {at}; run the same command again to resume from {last}"
    return f"interrupted at {at}, before the first checkpoint; run the same command again to start it over"


def _prepare_dir(run_dir: Path, resume: bool) -> None:
    if run_dir.exists() and not resume and not (run_dir / "final.ckpt").exists():
        aside = run_dir.with_name(f"{run_dir.name}.abandoned-{time.strftime('%Y%m%d-%H%M%S')}")
        shutil.move(str(run_dir), str(aside))
        log.info("resume=false: moved the unfinished run to %s and starting over", aside)
    run_dir.mkdir(parents=True, exist_ok=True)


_SOURCE_FIX = ("Pass source_checkpoint= the final.ckpt of a reconstruction made with this backbone and encoding, or "
               "leave it out to use (or make) the cached reconstruction of these settings.")


def _renderer_state(ckpt_path: Path) -> dict[str, torch.Tensor]:
    """The renderer tensors of a reconstruction / stylization checkpoint, read without running code."""
    return prefixed_state(load_checkpoint(ckpt_path, fix=_SOURCE_FIX), "renderer.")


class Pipeline:
    """One configured job: loads the scene once and runs the requested stages."""

    def __init__(self, cfg: DictConfig | dict) -> None:
        self.c = validate_config(_container(cfg))
        self.device = pick_device(self.c.get("device", "auto"))
        self.root = check_writable_dir(self.c.get("output_root", "outputs"), "output_root")
        self.lock_timeout: Optional[float] = self.c.get("lock_timeout")
        self.resume = bool(self.c.get("resume", True))
        self.results: dict[str, Any] = {"stage": self.c["stage"]}
        self.guidance = self.perceptual = None

    # ------------------------------------------------------------------ shared pieces
    def prepare_guidance(self) -> None:
        """Build CLIP/VGG (or toy) first, so missing weights fail before any training."""
        from nerfart_plugin.guidance import augment_prompt, build_guidance, build_perceptual, validate_prompt

        g = self.c["guidance"]
        self.guidance = build_guidance(g)
        self.perceptual = build_perceptual(g)
        self.real = bool(self.guidance.is_real and getattr(self.perceptual, "is_real", True))
        self.stamp = self.guidance.output_stamp() or ("" if self.real else f"_UNSTYLED-{g['name']}")
        if not self.real:
            log.warning("guidance is not a real pretrained CLIP (%s): every output is stamped %r",
                        g["name"], self.stamp)
        raw = validate_prompt(self.c["prompt"])
        self.prompt = augment_prompt(raw) if self.c.get("prompt_augment", True) else raw
        if self.prompt != raw:
            log.info("prompt augmented: %r -> %r", raw, self.prompt)
        self.raw_prompt = raw

    def load_data(self) -> None:
        from nerfart_plugin.data.datamodule import SceneDataModule
        from nerfart_plugin.systems.scene_setup import decide_setup

        dcfg = dict(self.c["data"])
        dcfg.setdefault("background_color", self.c["render"].get("background_color"))
        dcfg["seed"] = self.c["seed"]
        dcfg["batch_rays"] = self.c["reconstruct"]["batch_rays"]
        dcfg["cache_root"] = str(self.root / "cache")  # loaders' caches (selfie frames + SfM), never beside the data
        self.dm = SceneDataModule(dcfg)
        self.scene = self.dm.load()
        for note in self.scene.notes:
            log.info("data: %s", note)
        self.setup = decide_setup(self.scene, self.c["render"], ndc=self.dm.ndc)
        data_key = {k: v for k, v in self.c["data"].items() if k != "subject"}  # subject: stylization only
        key_src = {"scene": self.scene.content_hash, "data": data_key, "backbone": self.c["backbone"],
                   "encoding": self.c["encoding"], "render": self.c["render"], "seed": self.c["seed"],
                   "reconstruct": {k: v for k, v in self.c["reconstruct"].items()
                                   if k not in ("val_every", "val_views", "checkpoint_every")}}
        self.recon_key = config_hash(key_src)
        name = f"{self.c['data']['kind']}-{self.c['backbone']['name']}-{self.c['encoding']['name']}-{self.recon_key}"
        self.recon_dir = self.root / "reconstructions" / name

    def _components(self) -> tuple[dict, dict, dict]:
        return self.c["backbone"], self.c["encoding"], self.c["render"]

    # ------------------------------------------------------------------ stage 1
    def reconstruct(self) -> Path:
        """Stage 1 into ``recon_dir`` (locked while it runs); a finished reconstruction is reused."""
        run_dir = self.recon_dir
        if not (run_dir / "final.ckpt").exists():
            with run_lock(run_dir, self.lock_timeout):
                if not (run_dir / "final.ckpt").exists():  # not finished meanwhile by the process we waited for
                    return self._reconstruct(run_dir)
        log.info("reusing the cached reconstruction %s (same data, backbone and settings)", run_dir)
        self.results["reconstruction"] = {"dir": str(run_dir)}  # metrics: run_dir/metrics.json
        return run_dir / "final.ckpt"

    def _reconstruct(self, run_dir: Path) -> Path:
        from nerfart_plugin.systems.callbacks import AtomicCheckpoint, FiniteGradientGuard, GracefulInterrupt
        from nerfart_plugin.systems.reconstruction import ReconstructionSystem

        rc, final = self.c["reconstruct"], run_dir / "final.ckpt"
        _prepare_dir(run_dir, self.resume)
        atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(self.c)))
        self.dm.setup("fit")
        system = ReconstructionSystem(rc, *self._components(), self.setup, train_rays=self.dm.train_rays,
                                      seed=self.c["seed"], out_dir=str(run_dir))
        ckpt = AtomicCheckpoint(run_dir, rc.get("checkpoint_every", 100))
        stop = GracefulInterrupt(ckpt)
        val_every = int(rc.get("val_every", 500))
        val_kw: dict[str, Any] = (dict(val_check_interval=val_every, check_val_every_n_epoch=None,
                                       limit_val_batches=int(rc.get("val_views", 2)) or 1.0)
                                  if val_every > 0 else dict(limit_val_batches=0))  # val_every=0: no validation
        trainer = _trainer(run_dir, int(rc["steps"]), self.device, [ckpt, stop, FiniteGradientGuard()],
                           self.c["trainer"], **val_kw)
        ckpt_path = self._resume_point(run_dir, system, "reconstruction")
        t0 = time.perf_counter()
        self._fit(trainer, system, val=self.dm.val_dataloader() if val_every > 0 else None, ckpt_path=ckpt_path,
                  stop=stop, run_dir=run_dir)
        seconds = time.perf_counter() - t0
        if trainer.global_rank != 0:  # DDP: evaluation and outputs on rank 0 only
            return final
        metrics = self.evaluate_reconstruction(system)
        metrics.update({"train_seconds_this_process": seconds, "steps": int(trainer.global_step),
                        "scene_setup": self.setup.to_dict(), "notes": self.scene.notes,
                        "occupied_fraction": (system.renderer.occupancy.occupied_fraction
                                              if system.renderer.occupancy is not None else None)})
        atomic_write_json(run_dir / "metrics.json", metrics)
        if self.c["export"].get("enabled", True):
            self.export_mesh(system.renderer.field, run_dir / "mesh" / "source")
        with atomic_path(final) as tmp:
            trainer.save_checkpoint(tmp)
        log.info("reconstruction done: held-out PSNR %.2f dB -> %s", metrics.get("psnr", float("nan")), run_dir)
        self.results["reconstruction"] = {"dir": str(run_dir), **{k: metrics[k] for k in metrics
                                                                   if k.startswith(("psnr", "ssim"))}}
        return final

    def _resume_point(self, run_dir: Path, system: L.LightningModule, what: str) -> Optional[str]:
        """``run_dir/last.ckpt`` if there is one (read safely and checked against ``system``), else None."""
        last = run_dir / "last.ckpt"
        if not last.exists():
            return None
        fix = f"Delete {last} (or run with resume=false, which keeps the old folder aside) to start this {what} over."
        ckpt = load_checkpoint(last, fix=fix)
        check_fits(system, ckpt["state_dict"], last, ckpt.get(META_KEY), system.model_meta, fix)
        log.info("resuming the %s from %s (step %s)", what, last, ckpt.get("global_step", "?"))
        return str(last)

    def _fit(self, trainer: L.Trainer, system: L.LightningModule, val: Any = None, ckpt_path: Optional[str] = None,
             stop: Any = None, run_dir: Optional[Path] = None) -> None:
        """``trainer.fit`` on the steps loader; checkpoints are read with ``weights_only=True``.

        Raises:
            RunInterrupted: Ctrl-C (``stop`` is the run's :class:`GracefulInterrupt`), naming the step and the
                checkpoint to resume from.
            NerfArtError: out of memory, naming the settings to lower.
        """
        from nerfart_plugin.systems.base import steps_loader

        try:
            with allow_project_types():
                trainer.fit(system, train_dataloaders=steps_loader(), val_dataloaders=val, ckpt_path=ckpt_path,
                            weights_only=True)
        except torch.OutOfMemoryError as exc:
            raise NerfArtError(_OOM_HINT) from exc
        except RuntimeError as exc:
            if "out of memory" in str(exc).lower():
                raise NerfArtError(_OOM_HINT) from exc
            raise
        except SystemExit:  # Lightning >= 2.5 ends an interrupted fit with sys.exit(1)
            if trainer.interrupted:
                raise RunInterrupted(_interrupted(trainer, stop, run_dir)) from None
            raise
        if trainer.interrupted or (stop is not None and stop.requested):
            raise RunInterrupted(_interrupted(trainer, stop, run_dir))

    @torch.no_grad()
    def evaluate_reconstruction(self, system) -> dict[str, Any]:
        """PSNR / SSIM / masked PSNR over all held-out views."""
        from nerfart_plugin.systems.reconstruction import view_metrics

        system.to(self.device).eval()
        per_view = []
        for batch in self.dm.val_dataloader():
            img = system.render_view(batch, chunk=int(self.c["render"]["chunk"]))
            target = batch["rgb"].reshape(img["rgb"].shape).to(self.device)
            per_view.append(view_metrics(img["rgb"], target, batch.get("mask")))
        keys = set().union(*per_view) if per_view else set()
        out = {k: float(sum(m[k] for m in per_view if k in m) / sum(1 for m in per_view if k in m)) for k in keys}
        out["val_views"] = len(per_view)
        return out

    # ------------------------------------------------------------------ stage 2
    def stylize(self, recon_ckpt: Path) -> Path:
        """Stage 2 into its run folder (locked while it runs); a finished stylization is not redone."""
        from nerfart_plugin.guidance import default_source_prompt

        sc, exp = self.stylize_settings(), self.c["experiment"]
        src_prompt = self.c.get("source_prompt", "auto")
        if src_prompt in (None, "auto"):
            src_prompt = default_source_prompt(self.c["data"].get("subject") or "object")
        key = config_hash({"recon": str(recon_ckpt.resolve()) if self.c.get("source_checkpoint") else self.recon_key,
                           "prompt": self.prompt, "source_prompt": src_prompt, "guidance": self.c["guidance"],
                           "experiment": exp, "seed": self.c["seed"],
                           "stylize": {k: v for k, v in sc.items() if k not in ("render_every", "checkpoint_every",
                                                                                "video_frames", "video_fps")}})
        run_dir = self.root / "stylizations" / f"{slug(self.raw_prompt)}-{self.c['backbone']['name']}-{key}{self.stamp}"
        if not (run_dir / "final.ckpt").exists():
            with run_lock(run_dir, self.lock_timeout):
                if not (run_dir / "final.ckpt").exists():
                    return self._stylize(run_dir, recon_ckpt, src_prompt)
        log.info("this stylization is already complete: %s (not recomputed, not overwritten)", run_dir)
        self.results["stylization"] = {"dir": str(run_dir)}
        return run_dir / "final.ckpt"

    def _source_state(self, ckpt_path: Path) -> dict[str, torch.Tensor]:
        """The renderer tensors of the reconstruction ``ckpt_path``, read safely and checked to fit this run's
        backbone / encoding / scene setup (the error names the file and what differs)."""
        from nerfart_plugin.systems.base import build_renderer

        ckpt = load_checkpoint(ckpt_path, fix=_SOURCE_FIX)
        state = prefixed_state(ckpt, "renderer.")
        probe = build_renderer(*self._components(), self.setup)
        here = checkpoint_meta("reconstruct", self.c["backbone"], self.c["encoding"], self.setup)
        check_fits(probe, state, ckpt_path, ckpt.get(META_KEY), here, _SOURCE_FIX)
        return state

    def _stylize(self, run_dir: Path, recon_ckpt: Path, src_prompt: str) -> Path:
        from nerfart_plugin.guidance import resolve_negatives
        from nerfart_plugin.systems.callbacks import AtomicCheckpoint, GracefulInterrupt
        from nerfart_plugin.systems.stylization import StylizationSystem, style_views

        sc, exp, final = self.stylize_settings(), self.c["experiment"], run_dir / "final.ckpt"
        source_state = self._source_state(recon_ckpt)
        _prepare_dir(run_dir, self.resume)
        atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(self.c)))
        views = style_views(self.scene, self.scene.train_ids, int(sc["resolution"]), self.dm.ndc)
        system = StylizationSystem(sc, exp, *self._components(), self.setup, source_state, views,
                                   self.guidance, self.perceptual, self.prompt, src_prompt,
                                   resolve_negatives(sc.get("negatives", "auto"), self.guidance, self.prompt),
                                   seed=self.c["seed"], out_dir=str(run_dir), stamp=self.stamp,
                                   raw_prompt=self.raw_prompt)
        ckpt = AtomicCheckpoint(run_dir, sc.get("checkpoint_every", 10))
        stop = GracefulInterrupt(ckpt)
        trainer = _trainer(run_dir, int(sc["steps"]), self.device, [ckpt, stop], self.c["trainer"], limit_val_batches=0)
        ckpt_path = self._resume_point(run_dir, system, "stylization")
        t0 = time.perf_counter()
        self._fit(trainer, system, ckpt_path=ckpt_path, stop=stop, run_dir=run_dir)
        seconds = time.perf_counter() - t0
        metrics = self.stylization_outputs(system, run_dir)
        metrics.update({"prompt": self.raw_prompt, "prompt_used": self.prompt, "source_prompt": src_prompt,
                        "guidance": self.c["guidance"]["name"], "guidance_is_real": self.real,
                        "stamp": self.stamp or None, "experiment": exp, "steps": int(trainer.global_step),
                        "train_seconds_this_process": seconds, "last_step_timings_s": system.timings,
                        "negatives_kept": len(system.neg_sampler) if system.neg_sampler is not None else 0,
                        "negatives_excluded": [{"prompt": n, "reason": r} for n, r in system.neg_sampler.excluded]
                        if system.neg_sampler is not None else []})
        if self.stamp.startswith("_VERIFY"):
            metrics["WARNING"] = ("VERIFICATION run: guided by an ImageNet classifier standing in for CLIP, "
                                  "not by CLIP; see the judge block")
        elif not self.real:
            metrics["WARNING"] = "UNSTYLED by a real model: random or toy guidance weights were used"
        atomic_write_json(run_dir / "metrics.json", metrics)
        with atomic_path(final) as tmp:
            trainer.save_checkpoint(tmp)
        log.info("stylization done -> %s", run_dir)
        self.results["stylization"] = {"dir": str(run_dir), **{k: v for k, v in metrics.items()
                                                               if k.startswith(("clip_", "view_", "mesh_"))}}
        return final

    def stylize_settings(self) -> dict[str, Any]:
        """The ``stylize`` config with ``resolution: auto`` (the loaded images' long side, i.e. the
        data resolution policy: 256x256 head, 270x480 selfies) and ``epochs`` (steps = epochs x
        training views, the paper's "4 epochs") resolved."""
        sc = dict(self.c["stylize"])
        if sc.get("resolution") in (None, "auto"):
            sc["resolution"] = max(self.scene.height, self.scene.width)
        if sc.get("epochs"):
            sc["steps"] = int(sc["epochs"]) * len(self.scene.train_ids)
        return sc

    @torch.no_grad()
    def stylization_outputs(self, system, run_dir: Path) -> dict[str, Any]:
        """Metrics on held-out views, the side-by-side video, meshes and their comparison."""
        from nerfart_plugin.evaluation import clip_scores, off_surface_share, silhouette_iou
        from nerfart_plugin.systems.base import to_device
        from nerfart_plugin.systems.stylization import style_views

        system.to(self.device).eval()
        sc = self.stylize_settings()
        ids = self.scene.val_ids or self.scene.train_ids[:4]
        eval_views = style_views(self.scene, ids, int(sc["resolution"]), self.dm.ndc)
        sty_out = [system.render_batch(v) for v in eval_views]
        src_out = [system.render_batch(v, source=True) for v in eval_views]
        sty = torch.stack([o["rgb"].permute(2, 0, 1) for o in sty_out])
        src = torch.stack([o["rgb"].permute(2, 0, 1) for o in src_out])
        metrics: dict[str, Any] = clip_scores(system.guidance, sty.clamp(0, 1), src.clamp(0, 1), system.tgt_txt,
                                              system.src_txt)
        metrics["mean_rgb"] = [float(x) for x in sty.clamp(0, 1).mean((0, 2, 3))]
        metrics["mean_rgb_source"] = [float(x) for x in src.clamp(0, 1).mean((0, 2, 3))]
        metrics["edge_similarity"] = edge_similarity(sty.clamp(0, 1), src.clamp(0, 1))
        metrics["silhouette_iou"] = silhouette_iou(torch.stack([o["opacity"][..., 0] for o in src_out]),
                                                   torch.stack([o["opacity"][..., 0] for o in sty_out]))
        self.save_heldout(run_dir, ids, src, sty)
        metrics["judge"] = self.judge(src.clamp(0, 1), sty.clamp(0, 1), ids)
        metrics["off_surface_weight"] = float(np.mean([off_surface_share(system.renderer, to_device(v, self.device))
                                                       for v in eval_views]))
        metrics["off_surface_weight_source"] = float(np.mean([off_surface_share(system.source, to_device(v, self.device))
                                                              for v in eval_views]))
        metrics.update(self.video_outputs(system, run_dir, eval_views[0]))
        if self.c["export"].get("enabled", True):
            metrics.update(self.compare_meshes(system, run_dir))
        return metrics

    @torch.no_grad()
    def video_outputs(self, system, run_dir: Path, ref: dict[str, Any]) -> dict[str, Any]:
        """The source | stylized orbit video (``stylize.video_frames`` frames at the size of view ``ref``) and the
        view-consistency error along it; nothing with ``stylize.video_frames=0``."""
        from nerfart_plugin.data.camera_path import orbit_path
        from nerfart_plugin.evaluation import view_consistency
        from nerfart_plugin.export.video import side_by_side, write_video
        from nerfart_plugin.systems.stylization import camera_batch, image_to_uint8

        sc = self.c["stylize"]
        n = int(sc.get("video_frames", 24))
        metrics: dict[str, Any] = {"view_consistency_error": None}
        if n <= 0:
            return metrics
        c2ws = orbit_path(self.scene, n)
        K = self.scene.K[0].clone()
        K[0] *= ref["W"] / self.scene.width
        K[1] *= ref["H"] / self.scene.height
        near, far = float(self.scene.near.min()), float(self.scene.far.max())
        frames, sty_frames, src_frames = [], [], []
        for c2w in c2ws:
            b = camera_batch(K, c2w, ref["H"], ref["W"], near, far, self.dm.ndc)
            a, s = system.render_batch(b, source=True), system.render_batch(b)
            src_frames.append(a)
            sty_frames.append(s)
            frames.append(side_by_side(image_to_uint8(a["rgb"]), image_to_uint8(s["rgb"]),
                                       labels=("source", "stylized" + (f" ({self.stamp.strip('_')})" if self.stamp else ""))))
        write_video(frames, run_dir / f"video{self.stamp}.mp4", fps=int(sc.get("video_fps", 12)))
        if not self.dm.ndc:
            Kd = K.to(self.device)
            metrics["view_consistency_error"] = view_consistency(sty_frames, Kd, c2ws)
            metrics["view_consistency_error_source"] = view_consistency(src_frames, Kd, c2ws)
        # NDC: depth is NDC t, warping not implemented: view_consistency_error stays None
        return metrics

    def save_heldout(self, run_dir: Path, ids: list[int], src: torch.Tensor, sty: torch.Tensor) -> None:
        """``heldout/source_<view>.png`` and ``heldout/stylized_<view>.png`` at the stylization resolution."""
        from PIL import Image

        from nerfart_plugin.systems.stylization import image_to_uint8

        for i, a, b in zip(ids, src, sty):
            for name, img in (("source", a), ("stylized", b)):
                with atomic_path(run_dir / "heldout" / f"{name}_{int(i):04d}.png") as tmp:
                    Image.fromarray(image_to_uint8(img.permute(1, 2, 0))).save(tmp, format="PNG")

    def judge(self, src: torch.Tensor, sty: torch.Tensor, ids: list[int]) -> dict[str, Any]:
        """The independent ImageNet judge's verdict on held-out views (see :class:`ImageNetJudge`), or why
        it did not run (the prompt names no ImageNet class, or its weights package is missing)."""
        from nerfart_plugin.errors import WeightsMissingError
        from nerfart_plugin.evaluation import ImageNetJudge, judge_block
        from nerfart_plugin.guidance.imagenet import imagenet_classes

        try:
            target = imagenet_classes().find(self.raw_prompt)
        except ImportError as exc:  # timm missing
            return {"skipped": f"the judge needs timm ({exc}): pip install -e '.[imagenet]'"}
        if target is None:
            return {"skipped": f"the prompt {self.raw_prompt!r} names no ImageNet class"}
        try:
            judge = ImageNetJudge()
        except WeightsMissingError as exc:
            return {"skipped": str(exc)}
        block = judge_block(judge, target, src, sty, ids)
        log.info("judge (%s, held-out views %s): P(%s) %.4f -> %.4f, top-5 %.0f%% -> %.0f%%", block["model"], ids,
                 block["target_class"], block["source"]["mean_target_prob"], block["stylized"]["mean_target_prob"],
                 100 * block["source"]["top5_rate"], 100 * block["stylized"]["top5_rate"])
        return block

    # ------------------------------------------------------------------ meshes
    def export_mesh(self, field, stem: Path):
        from nerfart_plugin.export import MeshExtractor, export_mesh

        ec = self.c["export"]
        ex = MeshExtractor(resolution=int(ec["resolution"]), bound=float(field.bound), chunk=int(ec["chunk"]),
                           level=ec.get("level"), remove_floaters=bool(ec.get("remove_floaters", True)))
        try:
            mesh = ex.extract(field)
        except NerfArtError as exc:
            log.warning("no mesh for %s: %s", stem, exc)
            return None
        for fmt in ec.get("formats", ["ply"]):
            export_mesh(mesh, stem.with_suffix(f".{fmt}"))
        return mesh

    def compare_meshes(self, system, run_dir: Path) -> dict[str, Any]:
        from nerfart_plugin.export.compare import compare_meshes, displacement_mesh, vertex_distances

        src = self.export_mesh(system.source.field, run_dir / "mesh" / "source")
        sty = self.export_mesh(system.renderer.field, run_dir / "mesh" / f"stylized{self.stamp}")
        if src is None or sty is None:
            return {}
        sdf = system.source.field.geometry if system.source.field.is_sdf else None
        m = compare_meshes(sty, src, n_samples=20_000, source_sdf=sdf)
        d = vertex_distances(sty, src, source_sdf=sdf)
        from nerfart_plugin.export import export_mesh

        export_mesh(displacement_mesh(sty, d), run_dir / "mesh" / f"displacement{self.stamp}.ply")
        return {f"mesh_{k}": v for k, v in m.items()}

    def export_stage(self) -> None:
        """``stage=export``: meshes from ``source_checkpoint`` (or the cached reconstruction)."""
        from nerfart_plugin.systems.base import build_renderer

        ckpt = Path(self.c["source_checkpoint"]) if self.c.get("source_checkpoint") else self.recon_dir / "final.ckpt"
        if not ckpt.exists():
            raise NerfArtError(f"stage=export: no checkpoint at {ckpt}. Run stage=reconstruct first or pass "
                               "source_checkpoint=/path/to/final.ckpt.")
        renderer = build_renderer(*self._components(), self.setup)
        renderer.load_state_dict(self._source_state(ckpt))
        renderer.to(self.device).eval()
        stem = ckpt.parent / "mesh" / f"export-{ckpt.stem}-r{self.c['export']['resolution']}"
        mesh = self.export_mesh(renderer.field, stem)
        self.results["export"] = {"mesh": str(stem), "vertices": None if mesh is None else len(mesh.vertices)}

    # ------------------------------------------------------------------ run
    def run(self) -> dict[str, Any]:
        """Run the configured stages.

        Raises:
            RunInterrupted: Ctrl-C, at any point (the message says how to resume).
        """
        try:
            return self._run()
        except KeyboardInterrupt:  # outside training (loading, COLMAP, evaluation, export)
            raise RunInterrupted("interrupted; nothing finished is lost: run the same command again to continue "
                                 "(finished stages are reused, a stage in progress resumes from its last.ckpt)") from None

    def _run(self) -> dict[str, Any]:
        stage = self.c["stage"]
        L.seed_everything(int(self.c["seed"]), workers=True, verbose=False)
        if stage in ("stylize", "all"):
            self.prepare_guidance()
        self.load_data()
        if stage == "export":
            self.export_stage()
            return self.results
        recon = Path(self.c["source_checkpoint"]) if self.c.get("source_checkpoint") else self.recon_dir / "final.ckpt"
        if stage in ("reconstruct", "all") and not self.c.get("source_checkpoint"):
            recon = self.reconstruct()
        if stage in ("stylize", "all"):
            if not recon.exists():
                raise NerfArtError(f"No reconstruction at {recon} for this data + backbone + settings. Run "
                                   "stage=reconstruct (or stage=all) first, or pass source_checkpoint=/path/final.ckpt.")
            self.stylize(recon)
        return self.results


def edge_similarity(a: torch.Tensor, b: torch.Tensor) -> float:
    """Cosine similarity of Sobel edge magnitudes of two image batches [B,3,H,W] (1 = same structure)."""
    import kornia

    ea = kornia.filters.sobel(kornia.color.rgb_to_grayscale(a)).flatten(1)
    eb = kornia.filters.sobel(kornia.color.rgb_to_grayscale(b)).flatten(1)
    return float(torch.nn.functional.cosine_similarity(ea, eb, dim=1).mean())


def run(cfg: DictConfig | dict) -> dict[str, Any]:
    """Entry point used by ``python -m nerfart_plugin``; writes ``result.json`` in Hydra's job folder."""
    results = Pipeline(cfg).run()
    try:
        from hydra.core.hydra_config import HydraConfig

        out = Path(HydraConfig.get().runtime.output_dir)
        atomic_write_json(out / "result.json", results)
    except ValueError:  # not under Hydra
        pass
    return results
