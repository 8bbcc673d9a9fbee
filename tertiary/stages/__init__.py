"""The streamed tertiary-processing stages, in pipeline order: alignment (:mod:`.align`),
association (:mod:`.association`), fusion (:mod:`.fusion`), clustering (:mod:`.clustering`),
the secondary trackers (:mod:`.tracking`), with flight-data correlation beside them. Each is a
step function of (state, window) whose state carries across windows."""
