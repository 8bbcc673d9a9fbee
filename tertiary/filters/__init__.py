"""Filters vectorised over tracks (and Monte-Carlo runs)."""

from tertiary.filters.singer import singer_phi, singer_q, SingerModel

__all__ = ["singer_phi", "singer_q", "SingerModel"]
