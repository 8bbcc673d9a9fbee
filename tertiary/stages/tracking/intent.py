"""The vertical intent a track publishes: a level its aircraft has left is withheld.

A track carries its aircraft's latest downlinked selected level (Mode S BDS 4,0,
``selected_alt_m``) and its cleared level from flight data (``cleared_alt_m``). Conflict
prediction stops a climb or descent at that level, and holds level a track up to 100 ft on the
wrong side of it: the capture of a level-off, where the tracked height passes the level while
its rate decays (docs/methods.md, "Selected level").

The first seconds of an aircraft *leaving* its level look the same from one row: the height a
few metres past the level, a rate away from it. A new selection is read by each radar once a
scan, so the crew's new level and the onset of the climb or descent can fall between two
reads; a level bust has no new selection at all. Held at the level it is leaving, the aircraft
is predicted level while it climbs or descends. The two are told apart by the track's history:

* a track has *reached* a level once a row with that level was within ``band_m`` of it with
  |ḣ| ≤ ``rate_mps`` (level flight, |ḣ| ≤ 200 ft/min by default);
* a later row with the same level that moves away from it, (h − L)·ḣ ≥ 0 with |ḣ| > ``rate_mps``,
  has left it: the level is withheld from that row (null), and the prediction follows the motion;
* a new level value starts over (not reached); a row moving back towards the level publishes it.

A capture is not affected: until the track has been level at the value, nothing is withheld.
The rule reads only the track's own rows up to the row, so it gives the same rows whatever the
processing window: :func:`withhold_left_levels` carries, per track, each level's last value and
whether it was reached.
"""

from __future__ import annotations

from collections.abc import Sequence

import polars as pl

from tertiary.core.units import FT

__all__ = ["LEVEL_BAND_M", "LEVEL_RATE_MPS", "reached_column", "withhold_left_levels"]

#: a track within this of a level is at it (the level-off capture tolerance of the prediction)
LEVEL_BAND_M = 100.0 * FT

#: a track whose vertical rate is at most this is level (200 ft/min; climbs and descents fly
#: 500 ft/min and more, and a level track's rate is known to a few cm/s)
LEVEL_RATE_MPS = 1.0


def reached_column(level: str) -> str:
    """The carried state's column saying whether a track has been level at its ``level``."""
    return f"{level}_reached"


def withhold_left_levels(tracks: pl.DataFrame, last: pl.DataFrame, keys: Sequence[str], levels: Sequence[str],
                         band_m: float = LEVEL_BAND_M, rate_mps: float = LEVEL_RATE_MPS
                         ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(``tracks`` with each of ``levels`` withheld where the track has left it, per track
    ``keys`` its last row's level values and reached flags). ``tracks``: the window's rows with
    the levels as carried (each track's latest known), ``alt_m`` and ``alt_rate_mps``; ``last``:
    the previous windows' state (``keys``, the levels, their :func:`reached_column`; absent
    columns: nothing carried)."""
    keys = list(keys)
    if tracks.height == 0 or not {"alt_m", "alt_rate_mps"} <= set(tracks.columns):
        levels = []
    levels = [c for c in levels if c in tracks.columns]
    if not levels:
        return tracks, tracks.select(*keys).clear()
    h, rate = pl.col("alt_m"), pl.col("alt_rate_mps")
    prev = last.select(*keys, *(pl.col(c).alias(f"__prev_{c}") if c in last.columns
                               else pl.lit(None, pl.Float64).alias(f"__prev_{c}") for c in levels),
                       *(pl.col(reached_column(c)).alias(f"__seed_{c}") if reached_column(c) in last.columns
                         else pl.lit(None, pl.Boolean).alias(f"__seed_{c}") for c in levels))
    t = tracks.join(prev, on=keys, how="left", maintain_order="left")
    by = {"partition_by": keys, "order_by": "epoch"}
    for c in levels:
        lvl = pl.col(c)
        # a track's first row in the window continues from its last value of the earlier windows
        first = pl.col("epoch") == pl.col("epoch").min().over(keys)
        before = pl.when(first).then(pl.col(f"__prev_{c}")).otherwise(lvl.shift(1).over(**by))
        seg = lvl.ne_missing(before).cast(pl.UInt32).cum_sum().over(**by)
        t = t.with_columns(seg.alias("__seg"))
        carried = (pl.col("__seg") == 0) & pl.col(f"__seed_{c}").fill_null(False)
        at = (lvl.is_not_null() & ((h - lvl).abs() <= band_m) & (rate.abs() <= rate_mps)).fill_null(False)
        reached = ((at | carried).cast(pl.UInt32).cum_sum().over(partition_by=[*keys, "__seg"], order_by="epoch")
                   > 0)
        away = ((rate.abs() > rate_mps) & ((h - lvl) * rate >= 0)).fill_null(False)
        t = t.with_columns(reached.alias(f"__reached_{c}"))
        t = t.with_columns(pl.when(pl.col(f"__reached_{c}") & away).then(None).otherwise(lvl).alias(f"__pub_{c}"))
    state = (t.sort("epoch", maintain_order=True).group_by(keys, maintain_order=True)
             .agg(*(pl.col(c).last() for c in levels),
                  *(pl.col(f"__reached_{c}").last().alias(reached_column(c)) for c in levels)))
    out = t.with_columns(pl.col(f"__pub_{c}").alias(c) for c in levels).select(tracks.columns)
    return out, state
