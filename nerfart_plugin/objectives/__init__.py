"""What is optimized and what is measured: the NeRF-Art losses as pure functions (:mod:`.losses`, Eq. 2-9) and
every metric of a run (:mod:`.evaluation`)."""
