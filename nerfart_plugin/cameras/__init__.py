"""Cameras: a capture's cameras and frames (:mod:`.capture`), video paths around them (:mod:`.orbits`), and
nerfstudio ``camera_path.json`` files and named paths (:mod:`.path`)."""
