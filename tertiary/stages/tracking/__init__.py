"""The secondary trackers that smooth each fused picture, the last stage before evaluation: the
tracker (:mod:`.tracker`: track management around a batched filter, windowed by
:func:`track_step`; its gating and assignment in :mod:`.gating`, its epoch loop in :mod:`.banks`),
the altitude channel (:mod:`.altitude`), the vertical intent a track publishes (:mod:`.intent`)
and the filters behind one registry (:mod:`tertiary.filters`, :func:`make_filter`)."""

from tertiary.stages.tracking.altitude import ALT_COLUMNS, AltitudeConfig, AltState, FilterCarry, filter_tracks_carry
from tertiary.stages.tracking.config import STATUS, TRACK_COLUMNS, TrackerConfig
from tertiary.filters import REGISTRY, TrackFilter, make_filter
from tertiary.stages.tracking.tracker import (Filters, TrackState, filter_dict, init_track_state, track, track_methods,
                                              track_step)

__all__ = ["ALT_COLUMNS", "AltitudeConfig", "AltState", "FilterCarry", "filter_tracks_carry", "STATUS",
           "TRACK_COLUMNS", "TrackerConfig", "REGISTRY", "TrackFilter", "make_filter", "Filters", "TrackState",
           "filter_dict", "init_track_state", "track", "track_methods", "track_step"]
