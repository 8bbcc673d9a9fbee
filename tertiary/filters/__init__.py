"""Filters vectorised over tracks (and Monte-Carlo runs): the estimators of the radars' own local
trackers (:mod:`tertiary.sensors`) and of the secondary trackers (:mod:`tertiary.stages.tracking`),
so they sit below both.

Every tracker filter implements :class:`tertiary.filters.base.TrackFilter` and registers its
name; :func:`make_filter` builds one by name (the only way to get one). Importing this package
registers them all. The chapter 3 range channels (:mod:`.kinematic`) are exported too.
"""

from tertiary.filters import adaptive_r, coupled, ekf, imm, linear, manoeuvring, quasi_optimal, turn  # noqa: F401  (registration)
from tertiary.filters.base import REGISTRY, Innovation, Output, TrackFilter, make_filter
from tertiary.filters.kinematic import KinematicDynamicRangeChannel, KinematicRangeChannel, make_range_channel
from tertiary.filters.singer import SingerModel, singer_phi, singer_q

__all__ = ["singer_phi", "singer_q", "SingerModel", "TrackFilter", "Output", "Innovation", "make_filter", "REGISTRY",
           "KinematicDynamicRangeChannel", "KinematicRangeChannel", "make_range_channel"]
