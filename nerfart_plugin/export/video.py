"""The video writer (atomic).

Frames are images as :func:`nerfart_plugin.utils.images.to_uint8` takes them. Videos are H.264 (libx264,
yuv420p) MP4 through imageio-ffmpeg's bundled ffmpeg; odd sizes are padded to
even by replicating the last row/column (yuv420p needs even sizes).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from nerfart_plugin.errors import DataError, NerfArtError
from nerfart_plugin.utils.images import pad_to_even, to_uint8
from nerfart_plugin.utils.io import atomic_path

log = logging.getLogger(__name__)


def write_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: int = 24, quality: int = 18) -> Path:
    """Write frames to an H.264 MP4 at ``path`` atomically; returns the path.

    ``quality`` is libx264's CRF (lower = better, 18 ~ visually lossless).
    All frames must share one size.
    """
    import imageio_ffmpeg

    path = Path(path)
    if len(frames) == 0:
        raise DataError(f"write_video({path}): no frames given; render at least one frame.")
    first = pad_to_even(to_uint8(frames[0]))
    h, w = first.shape[:2]
    try:
        with atomic_path(path) as tmp:
            writer = imageio_ffmpeg.write_frames(
                str(tmp),
                (w, h),
                fps=fps,
                codec="libx264",
                pix_fmt_in="rgb24",
                pix_fmt_out="yuv420p",
                macro_block_size=1,
                output_params=["-crf", str(int(quality)), "-f", "mp4", "-movflags", "+faststart"],
                ffmpeg_log_level="error",
            )
            writer.send(None)
            try:
                for i, f in enumerate(frames):
                    f = pad_to_even(to_uint8(f))
                    if f.shape[:2] != (h, w):
                        raise DataError(
                            f"write_video({path}): frame {i} is {f.shape[1]}x{f.shape[0]} but frame 0 is "
                            f"{w}x{h}; resize frames to one size first."
                        )
                    writer.send(np.ascontiguousarray(f))
            finally:
                writer.close()
    except OSError as exc:
        raise NerfArtError(f"Could not write video {path}: {exc}. Check the folder is writable.") from exc
    log.info("Wrote %s (%d frames, %dx%d, %d fps)", path, len(frames), w, h, fps)
    return path
