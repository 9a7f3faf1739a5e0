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
