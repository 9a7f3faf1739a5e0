"""The configuration layer: typed settings (:mod:`.types`), the run's sections (:mod:`.schema`) and the
components' sections (:mod:`.sections`), violations as users read them (:mod:`.issues`), the component registry
and third-party plugins (:mod:`.registry`, :mod:`.plugins`), the Hydra glue (:mod:`.compose`,
:mod:`.overrides`) and who decides each ``auto`` setting (:mod:`.auto`)."""
