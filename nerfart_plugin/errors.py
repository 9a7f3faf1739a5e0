"""The project's own exceptions: each message names the file or setting and the fix."""

from __future__ import annotations


class NerfArtError(Exception):
    """Base class of every error the project raises on purpose."""


class DataError(NerfArtError, ValueError):
    """Input data (images, poses, masks, video) is missing, malformed or inconsistent."""


class ConfigError(NerfArtError, ValueError):
    """A configuration value or name is invalid."""


class WeightsMissingError(NerfArtError, RuntimeError):
    """Pretrained weights (CLIP, VGG) could not be found or loaded."""


class TrainingDivergedError(NerfArtError, RuntimeError):
    """A loss or gradient became NaN/inf during training."""


class CheckpointError(NerfArtError, ValueError):
    """A checkpoint cannot be read safely, or does not fit the configured model."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint whose unpickling would create objects other than tensors and plain data (how a pickle
    runs code): refused as it is, never treated as mere damage."""


class RunLockedError(NerfArtError, RuntimeError):
    """Another process holds the run folder (and did not release it within ``lock_timeout``)."""


class RunInterrupted(NerfArtError):
    """The run was interrupted (Ctrl-C); it resumes from its last checkpoint when started again."""
