"""Finished runs: a run folder opened for rendering (:mod:`.run`: ``Run``, ``open_run``, ``mix``) and the
strength dial and mixing (:mod:`.blend`). Nothing here trains."""
