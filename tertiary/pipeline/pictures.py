"""The pictures of a run, read one at a time: each fusion method's confirmed targets, each
tracker picture "<fusion method>+<filter>", and the picture conflict prediction runs on
(:func:`safety_picture`) — from frames in memory or from :class:`OnDiskTable`."""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator

import polars as pl

from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.tables import NOT_SCORED, OnDiskTable, whole_table

__all__ = ["NOT_SCORED", "as_picture", "confirmed_only", "fused_readers", "safety_id_column", "safety_names",
           "safety_picture", "track_readers"]


def safety_id_column(cfg: PipelineConfig) -> str:
    """The id column of the picture conflict prediction runs on: ``track_id`` on the trackers'
    tracks (``safety_picture="tracks"`` with filters and methods), else ``target_id`` on the fused
    pictures. Decided by the configuration, never by the rows: a window without tracks must not
    switch a run's picture."""
    return "track_id" if cfg.safety_picture == "tracks" and cfg.filters and cfg.methods else "target_id"


def confirmed_only(fused: pl.DataFrame) -> pl.DataFrame:
    """Confirmed targets only: clutter-only (tentative) targets are never scored or screened."""
    return fused.filter(~pl.col("tentative").fill_null(False)) if "tentative" in fused.columns else fused




def fused_readers(fused: "pl.DataFrame | OnDiskTable", skip: Collection[str] = (), blocks: bool = False
                    ) -> Iterator[Callable[[], "pl.DataFrame | Iterator[pl.DataFrame]"]]:
    """A reader per fused picture (its confirmed targets), in order of appearance; an on-disk
    picture is read without the columns in ``skip``, and with ``blocks`` as time blocks
    (:meth:`OnDiskTable.blocks`)."""
    if isinstance(fused, OnDiskTable):
        for key in fused.shown:
            if blocks:
                yield lambda key=key: (confirmed_only(b) for b in fused.blocks(key, skip))
            else:
                yield lambda key=key: confirmed_only(fused.picture(key, skip))
        return
    shown = confirmed_only(fused)
    for part in (shown.partition_by("method", maintain_order=True) if shown.height else []):
        yield lambda part=part: part


def as_picture(tracks: pl.DataFrame) -> pl.DataFrame:
    """A tracker picture named "<fusion method>+<filter>" in ``method``."""
    return tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method")).drop("filter")


def track_readers(tracks: "pl.DataFrame | OnDiskTable", skip: Collection[str] = (), blocks: bool = False
                    ) -> Iterator[Callable[[], "pl.DataFrame | Iterator[pl.DataFrame]"]]:
    """A reader per tracker picture, in order of appearance (``skip``, ``blocks``: as for fused)."""
    if isinstance(tracks, OnDiskTable):
        for key in tracks.pictures:
            if blocks:
                yield lambda key=key: (as_picture(b) for b in tracks.blocks(key, skip))
            else:
                yield lambda key=key: as_picture(tracks.picture(key, skip))
        return
    if tracks.height:
        for part in as_picture(tracks).partition_by("method", maintain_order=True):
            yield lambda part=part: part


def safety_picture(cfg: PipelineConfig, fused: "pl.DataFrame | OnDiskTable", tracks: "pl.DataFrame | OnDiskTable",
                   notes: list[str]) -> tuple[pl.DataFrame, str]:
    """The picture conflict prediction runs on, with its id column; every picture is named in
    ``method`` ("<fusion method>+<filter>" for tracks), so every alert names where it came from."""
    if safety_id_column(cfg) == "track_id":
        # tentative tracks are never emitted by the tracker: every row is a confirmed track
        return whole_table(tracks).with_columns(pl.format("{}+{}", "method", "filter").alias("method")), "track_id"
    if cfg.safety_picture == "tracks":
        text = "conflict prediction ran on the fused pictures: no tracker filter was configured"
        if text not in notes:
            notes.append(text)
    return confirmed_only(whole_table(fused)), "target_id"      # clutter-only targets never reach safety


def safety_names(cfg: PipelineConfig, fused: "pl.DataFrame | OnDiskTable", tracks: "pl.DataFrame | OnDiskTable"
                  ) -> tuple[list[str], str]:
    """The sorted picture names of :func:`safety_picture`'s picture and its id column, without
    reading the picture."""
    if safety_id_column(cfg) == "track_id":
        if isinstance(tracks, OnDiskTable):
            return sorted({f"{m}+{f}" for m, f in tracks.pictures}), "track_id"
        return sorted(as_picture(tracks)["method"].unique().to_list()), "track_id"
    if isinstance(fused, OnDiskTable):
        return sorted({m for (m,) in fused.shown}), "target_id"
    return sorted(confirmed_only(fused)["method"].unique().to_list()), "target_id"
