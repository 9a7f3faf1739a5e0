"""Pieces shared by the loaders: hold-out split, hashing, Scene assembly."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from nerfart_plugin.data.normalize import near_far
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.errors import DataError
from nerfart_plugin.utils.io import hash_files

log = logging.getLogger(__name__)


def split_ids(n: int, holdout_every: int = 8) -> tuple[list[int], list[int]]:
    """``val = ids[::holdout_every]``, train = the rest (all views when ``holdout_every <= 0``
    or there would be no training view)."""
    ids = list(range(n))
    if not holdout_every or holdout_every <= 0 or n < 2:
        return ids, []
    val = ids[::holdout_every]
    train = [i for i in ids if i not in set(val)]
    return train, val


def require_dir(path: Any, what: str = "scene folder") -> Path:
    """Path of an existing, non-empty folder or a DataError naming it."""
    if path is None:
        raise DataError(f"No {what} given: set data.path=/path/to/scene.")
    p = Path(path).expanduser()
    if not p.exists():
        raise DataError(f"{what.capitalize()} {p} does not exist: check data.path (absolute paths are safest).")
    if p.is_dir() and not any(p.iterdir()):
        raise DataError(f"{what.capitalize()} {p} is empty: copy the scene's images and cameras into it.")
    return p


def options_key(**opts: Any) -> str:
    """Stable string of the loading options, hashed along with the files."""
    return json.dumps(opts, sort_keys=True, default=str)


def make_scene(
    *,
    images: np.ndarray,
    masks: Optional[np.ndarray],
    c2w: np.ndarray,
    K: np.ndarray,
    names: Sequence[str],
    normalization: np.ndarray,
    capture: str,
    source: Path,
    notes: list[str],
    hash_paths: Sequence[Path],
    opts: dict,
    holdout_every: int = 8,
    split: Optional[tuple[Sequence[int], Sequence[int]]] = None,
    bounds: Optional[np.ndarray] = None,
) -> Scene:
    """Build, hash and validate a :class:`Scene` from numpy arrays (``c2w`` already normalized by
    ``normalization``); the ray ranges follow the one near/far policy
    (:func:`~nerfart_plugin.data.normalize.near_far`) from the capture and the depth ``bounds`` [N,2]
    of the files, if any.

    ``split`` = (train ids, val ids) given by the files (e.g. Blender's
    ``transforms_{train,val}.json``); otherwise every ``holdout_every``-th view is held out.
    """

    near, far = near_far(capture, c2w, bounds, normalization)
    n = len(images)
    train, val = split_ids(n, holdout_every) if split is None else ([int(i) for i in split[0]], [int(i) for i in split[1]])
    f32 = lambda a: torch.from_numpy(np.array(a, dtype=np.float32))  # noqa: E731
    near = np.broadcast_to(np.asarray(near, dtype=np.float64), (n,))
    far = np.broadcast_to(np.asarray(far, dtype=np.float64), (n,))
    scene = Scene(
        images=f32(images),
        masks=None if masks is None else f32(masks),
        c2w=f32(c2w[:, :3, :4]),
        K=f32(K),
        near=f32(near),
        far=f32(far),
        image_names=[str(x) for x in names],
        train_ids=train,
        val_ids=val,
        normalization=f32(normalization),
        capture=capture,  # type: ignore[arg-type]
        source=Path(source),
        notes=list(notes),
        content_hash=hash_files([Path(p) for p in hash_paths], extra=options_key(**opts)),
    )
    for note in notes:
        log.info("%s: %s", source, note)
    return scene.validate()
