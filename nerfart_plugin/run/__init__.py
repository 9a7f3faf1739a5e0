"""Running stages: the pipeline that runs what ``stage=`` asks for (:mod:`.pipeline`), one module per stage
(:mod:`.stages`), the builders from a config (:mod:`.factories`), the fit skeleton (:mod:`.fit`), run folders
(:mod:`.folders`) and sweeps (:mod:`.sweep`)."""
