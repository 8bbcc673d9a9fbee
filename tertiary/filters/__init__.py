"""Filters vectorised over tracks (and Monte-Carlo runs).

Every tracker filter implements :class:`tertiary.filters.base.TrackFilter` and registers its
name; :func:`make_filter` builds one by name. Importing this package registers them all.
"""

from tertiary.filters import adaptive_r, coupled, ekf, imm, linear, quasi_optimal  # noqa: F401  (registration)
from tertiary.filters.base import REGISTRY, Innovation, Output, TrackFilter, make_filter
from tertiary.filters.singer import SingerModel, singer_phi, singer_q

__all__ = ["singer_phi", "singer_q", "SingerModel", "TrackFilter", "Output", "Innovation", "make_filter", "REGISTRY"]
from tertiary.filters.kinematic import KinematicDynamicRangeChannel, KinematicRangeChannel, make_range_channel  # noqa: E402,F401  (chapter 3 range channels)
