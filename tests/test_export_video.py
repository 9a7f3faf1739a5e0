"""write_video / side_by_side / save_image_grid."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from nerfart_plugin.errors import DataError
from nerfart_plugin.export.video import write_video
from nerfart_plugin.utils.images import image_grid, save_image_grid, side_by_side, to_uint8


def _frames(n: int, h: int, w: int) -> list[np.ndarray]:
    ys, xs = np.mgrid[0:h, 0:w]
    return [np.stack([(xs + 4 * i) % w / w, ys / h, np.full_like(xs, i / n, dtype=float)], -1) for i in range(n)]


@pytest.mark.slow
@pytest.mark.parametrize("size", [(32, 48), (33, 47)])  # odd sizes padded to even
def test_video_readable_with_right_frame_count(tmp_path, size):
    h, w = size
    frames = _frames(12, h, w)
    path = write_video(frames, tmp_path / "turn.mp4", fps=12)
    assert [p.name for p in tmp_path.iterdir()] == ["turn.mp4"]
    video = iio.imread(path, plugin="pyav")
    assert video.shape == (12, h + h % 2, w + w % 2, 3)
    meta = iio.immeta(path, plugin="pyav")
    assert meta["codec"] == "h264" and meta["fps"] == 12
    # Content survives the lossy codec roughly.
    assert np.abs(video[5, :h, :w].astype(float) - to_uint8(frames[5]).astype(float)).mean() < 8


@pytest.mark.slow
def test_video_uint8_frames_and_errors(tmp_path):
    frames = [np.full((16, 16, 3), v, np.uint8) for v in (0, 128, 255)]
    video = iio.imread(write_video(frames, tmp_path / "a.mp4", fps=24), plugin="pyav")
    assert video.shape[0] == 3 and abs(int(video[1].mean()) - 128) < 4
    with pytest.raises(DataError, match="no frames"):
        write_video([], tmp_path / "b.mp4")
    with pytest.raises(DataError, match="frame 1"):
        write_video([frames[0], np.zeros((8, 8, 3), np.uint8)], tmp_path / "c.mp4")
    assert not (tmp_path / "c.mp4").exists()


def test_side_by_side_and_grid(tmp_path):
    a = np.zeros((40, 30, 3), np.uint8)
    b = np.ones((50, 20, 3), np.float32)
    s = side_by_side(a, b, labels=("source", "stylized"), gap=4)
    assert s.shape == (50, 54, 3) and s.dtype == np.uint8
    assert s[:20, :30].max() > 150  # label text drawn on the black image
    plain = side_by_side(a, b, labels=None)
    assert plain[:40, :30].max() == 0 and plain[:50, 34:].min() == 255
    g = image_grid([a, a, a], ncols=2, gap=2)
    assert g.shape == (82, 62, 3)
    path = save_image_grid([a, b, s], tmp_path / "grid.png")
    assert iio.imread(path).shape[2] == 3
    with pytest.raises(DataError):
        to_uint8(np.zeros((4, 4, 5)))
