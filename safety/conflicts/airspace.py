"""Airspace with its own treatment: pairs established on the same final approach decided with
that volume's minimum and look-ahead, pairs below the en-route floor with the terminal minima
(every other pair with the en-route ones), and pairs both inside one aerodrome zone not predicted
(docs/methods.md, "Conflict prediction (STCA)": "Final-approach volumes", "En-route airspace",
"Aerodrome zones")."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import polars as pl
from numpy.typing import NDArray

from safety.conflicts.config import ConflictConfig, zone_index
from safety.conflicts.pairs import WindowRows, empty_conflicts, pair_rows
from tertiary.core import geo

__all__ = ["approach_membership", "volume_rows"]

def approach_membership(tracks: pl.DataFrame, cfg: ConflictConfig, frame: geo.LocalFrame | None = None
                        ) -> NDArray[np.int64]:
    """Per row, the index in ``cfg.approach_volumes`` of the final it is established on (the first
    that contains it), −1 for none — always −1 in seed mode (docs/methods.md "Final-approach
    volumes")."""
    return _membership(WindowRows(tracks, frame), cfg)


def _membership(rows: "WindowRows", cfg: ConflictConfig) -> NDArray[np.int64]:
    member = np.full(rows.tracks.height, -1, np.int64)
    if cfg.mode != "corrected" or not cfg.approach_volumes or not rows.tracks.height:
        return member
    pos, vel, _, _ = rows.state()
    for k in range(len(cfg.approach_volumes) - 1, -1, -1):
        member[cfg.approach_volumes[k].contains(pos, vel)] = k
    return member


def volume_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
                 ) -> list[pl.DataFrame]:
    """:func:`_airspace_rows` of each setting, without the pairs whose two tracks are both in one
    of its aerodrome zones (docs/methods.md "Aerodrome zones")."""
    outs = _airspace_rows(rows, cfgs, map_)
    member: dict[tuple, NDArray[np.int64]] = {}
    for k, c in enumerate(cfgs):
        if c.aerodrome_zones and rows.tracks.height and outs[k].height:
            if c.aerodrome_zones not in member:
                member[c.aerodrome_zones] = zone_index(rows.state()[0], c.aerodrome_zones)
            if np.any(member[c.aerodrome_zones] >= 0):
                outs[k] = _replaced(outs[k], [], rows, member[c.aerodrome_zones])
    return outs


def _airspace_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
                   ) -> list[pl.DataFrame]:
    """:func:`_approach_rows` of each setting; a setting with an en-route floor decides the pairs
    whose two tracks are both below it with its minima and every other pair with its en-route
    minima (docs/methods.md "En-route airspace")."""
    outs: list[pl.DataFrame | None] = [None] * len(cfgs)
    plain = [k for k, c in enumerate(cfgs) if c.enroute_above_m is None]
    if plain:
        for k, out in zip(plain, _approach_rows(rows, [cfgs[k] for k in plain], map_)):
            outs[k] = out
    floors: dict[float, list[int]] = {}
    for k, c in enumerate(cfgs):
        if c.enroute_above_m is not None:
            floors.setdefault(c.enroute_above_m, []).append(k)
    for floor, ks in floors.items():
        low = rows.state()[0][:, 2] < floor if rows.tracks.height else np.zeros(0, bool)
        if low.all():                            # a terminal area only: the configured minima
            for k, out in zip(ks, _approach_rows(rows, [cfgs[k] for k in ks], map_)):
                outs[k] = out
            continue
        above = _approach_rows(rows, [cfgs[k].enroute() for k in ks], map_)
        below = (_approach_rows(rows.subset(low), [cfgs[k] for k in ks], map_) if low.sum() >= 2
                 else [empty_conflicts() for _ in ks])
        for k, a, b in zip(ks, above, below):
            outs[k] = _replaced(a, [b], rows, np.where(low, 0, -1))
    return outs


def _replaced(base: pl.DataFrame, parts: Sequence[pl.DataFrame], rows: WindowRows, group: NDArray[np.int64]
              ) -> pl.DataFrame:
    """``base`` without its pairs of two rows in one group (``group`` ≥ 0 per row; −1: none), with
    ``parts`` (those pairs, decided otherwise) in their place, in the pair order."""
    key = ["run", "epoch", "method"]
    flag = rows.keys().with_columns(pl.Series("__id", rows.ids()).cast(pl.UInt64), pl.Series("__g", group))
    ga = pl.col("__ga").fill_null(-1)
    kept = (base.join(flag.rename({"__id": "id_a", "__g": "__ga"}), on=[*key, "id_a"], how="left")
            .join(flag.rename({"__id": "id_b", "__g": "__gb"}), on=[*key, "id_b"], how="left")
            .filter(~((ga >= 0) & (ga == pl.col("__gb").fill_null(-2)))).drop("__ga", "__gb"))
    out = [p for p in (kept, *parts) if p.height]   # an empty part has the empty table's extra columns
    return pl.concat(out, how="vertical_relaxed").sort([*key, "id_a", "id_b"]) if out else empty_conflicts()


def _approach_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
                   ) -> list[pl.DataFrame]:
    """:func:`pair_rows` of each setting, with the pairs whose two tracks are established on the
    same final decided by that volume's parameters instead (:class:`ApproachVolume`)."""
    outs = pair_rows(rows, cfgs, map_)
    by_vols: dict[tuple, list[int]] = {}
    for k, c in enumerate(cfgs):
        by_vols.setdefault((c.mode, c.approach_volumes), []).append(k)
    for ks in by_vols.values():
        vols = cfgs[ks[0]].approach_volumes
        member = _membership(rows, cfgs[ks[0]])
        if not np.any(member >= 0):
            continue
        inside: dict[int, list[pl.DataFrame]] = {k: [] for k in ks}
        for kv, v in enumerate(vols):
            mask = member == kv
            if mask.sum() >= 2:
                for k, part in zip(ks, pair_rows(rows.subset(mask), [v.parameters(cfgs[k]) for k in ks], map_)):
                    inside[k].append(part)
        for k in ks:
            outs[k] = _replaced(outs[k], inside[k], rows, member)
    return outs
