"""What a run folder holds for the tools users open next: TensorBoard events with images, the cameras
for the viewer, meshes in the capture's world frame (saying so), textured OBJ/GLB."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pipeline_helpers import tiny_cfg

from nerfart_plugin.data.datamodule import DEFAULT_SCENE
from nerfart_plugin.run.pipeline import run


@pytest.mark.slow
def test_reconstruction_folder_for_tensorboard_viewer_and_blender(tmp_path: Path) -> None:
    pytest.importorskip("tensorboard")
    pytest.importorskip("xatlas")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = tiny_cfg(tmp_path, DEFAULT_SCENE, "stage=reconstruct", "reconstruct.steps=20", "reconstruct.val_every=10",
                   "logger=tensorboard", "export.texture=true", "export.texture_size=128", "export.formats=[ply,glb]")
    folder = Path(run(cfg)["reconstruction"]["dir"])
    # TensorBoard: the loss curve and the validation grid as an image
    acc = EventAccumulator(str(next((folder / "tb").rglob("events.out.tfevents.*")).parent), size_guidance={"images": 4})
    acc.Reload()
    assert "train/loss_rgb" in acc.Tags()["scalars"] and any(t.startswith("val/") for t in acc.Tags()["images"])
    assert list((folder / "logs").rglob("metrics.csv"))  # the CSV is kept beside it
    # cameras for the viewer, in the frame of the meshes (world by default)
    cams = json.loads((folder / "cameras.json").read_text())
    assert cams["frame"] == "world" and len(cams["c2w"]) == 31 and 0 <= cams["front"] < 31
    # meshes in the capture's world frame: the normalized head fits the unit sphere, the world one is
    # as large as the capture's cameras say (cameras.npz scale_mat), and the file says which frame
    T = np.asarray(cams["normalization"])
    ply = folder / "mesh" / "source.ply"
    head = ply.read_bytes()[:3000].decode(errors="ignore")
    meta = json.loads(next(l for l in head.splitlines() if l.startswith("comment nerfart ")).split(" ", 2)[2])
    assert meta["frame"] == "world"
    world = trimesh.load(ply, process=False)
    back = np.asarray(world.vertices) @ T[:3, :3].T + T[:3, 3]
    assert np.linalg.norm(back, axis=1).max() < 1.05  # mapped back it lies in the unit sphere again
    cam_centres = np.asarray(cams["c2w"])[:, :3, 3]
    assert np.linalg.norm(cam_centres - np.asarray(world.vertices).mean(0), axis=1).min() > np.ptp(world.vertices, 0).max()
    # the textured mesh opens with its texture
    for suffix in (".obj", ".mtl", ".png", ".glb"):
        assert (folder / "mesh" / f"source_textured{suffix}").is_file(), suffix
    obj = trimesh.load(folder / "mesh" / "source_textured.obj", process=False)
    assert isinstance(obj.visual, trimesh.visual.TextureVisuals) and obj.visual.material.image.size == (128, 128)
    assert b'"frame":"world"' in (folder / "mesh" / "source.glb").read_bytes()
