"""The secondary trackers that smooth each fused picture: the tracker stage, the altitude channel
and the filters behind one registry (:mod:`.filters`)."""
