"""The public Python API: open a finished run and render, mesh or inspect it (notebooks, scripts).

::

    from nerfart_plugin.api import open_run

    run = open_run("outputs/stylizations/<run>")       # a reconstruction or a stylization folder
    run.metrics["judge"], run.config.prompt             # what the run recorded
    img = run.render(0)["rgb"]                           # training camera 0, [H,W,3] uint8
    img = run.render(c2w, channels=("rgb", "depth"))     # any camera: [3,4] / [4,4] OpenCV, world frame
    frames = run.render_path("spiral", frames=60)        # channel -> list of frames
    run.write_render("renders/", path="orbit", channels=("rgb", "side"))   # mp4 (+ PNGs) + camera_path.json
    mesh = run.mesh(resolution=256)                       # trimesh, the capture's world frame
    scene = run.scene()                                   # the photos and cameras again (needs the data)
    half = run.with_strength(0.5)                         # the style at half strength: a Run like any other
    both = mix([run_a, run_b], [0.5, 0.5])                # two stylizations of one source, mixed
    head = Region.box(center=[0, 0.3, 0], half_sizes=[0.3, 0.3, 0.3])   # world units (the capture's frame)
    only = run.with_region(head)                          # the style inside the box, the source elsewhere
    parts = mix([run_a.with_region(head), run_b.with_region(~head)], [1, 1])   # style A here, style B there

``python -m nerfart_plugin stage=render render.run=<folder>`` does the same as :meth:`Run.write_render`.
Nothing here trains: a finished run is only read (its ``final.ckpt``, ``config.yaml``,
``metrics.json`` and ``cameras.json``).
"""

from __future__ import annotations

from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.cameras.path import RenderPath
from nerfart_plugin.regions import Region
from nerfart_plugin.results.run import Run, mix, open_run

__all__ = ["Run", "open_run", "mix", "Region", "RenderPath", "CaptureCameras"]
