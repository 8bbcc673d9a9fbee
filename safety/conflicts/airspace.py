"""Airspace with its own treatment: pairs established on the same final approach decided with
that volume's minimum and look-ahead, pairs below the en-route floor with the terminal minima
(every other pair with the en-route ones), and pairs both inside one aerodrome zone not predicted
(docs/methods.md, "Conflict prediction (STCA)": "Final-approach volumes", "En-route airspace",
"Aerodrome zones")."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence

import numpy as np
import polars as pl
from numpy.typing import NDArray

from safety.conflicts.config import ConflictConfig, zone_index
from safety.conflicts.pairs import Groups, WindowRows, empty_conflicts, pair_rows
from tertiary.core import geo

__all__ = ["approach_membership", "volume_rows"]

#: :func:`pair_rows` with the caller's options: (rows, settings, skip=) -> each setting's rows
Predict = Callable[..., list[pl.DataFrame]]


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


def volume_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map,
                scored_only: bool = False) -> list[pl.DataFrame]:
    """:func:`_airspace_rows` of each setting, without the pairs whose two tracks are both in one
    of its aerodrome zones (docs/methods.md "Aerodrome zones"); ``scored_only``: as for
    :func:`pair_rows`."""
    zones: dict[tuple, NDArray[np.int64]] = {}
    skip: list[Groups] = []
    for c in cfgs:
        if c.aerodrome_zones and rows.tracks.height and c.aerodrome_zones not in zones:
            zones[c.aerodrome_zones] = zone_index(rows.state()[0], c.aerodrome_zones)
        member = zones.get(c.aerodrome_zones) if c.aerodrome_zones else None
        skip.append((member,) if member is not None and np.any(member >= 0) else ())
    return _airspace_rows(rows, cfgs, functools.partial(pair_rows, map_=map_, scored_only=scored_only), skip)


def _airspace_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], predict: Predict,
                   skip: Sequence[Groups]) -> list[pl.DataFrame]:
    """:func:`_approach_rows` of each setting; a setting with an en-route floor decides the pairs
    whose two tracks are both below it with its minima and every other pair with its en-route
    minima (docs/methods.md "En-route airspace"). ``predict``: :func:`pair_rows` with its options;
    ``skip``: as for :func:`pair_rows`."""
    outs: list[pl.DataFrame | None] = [None] * len(cfgs)
    plain = [k for k, c in enumerate(cfgs) if c.enroute_above_m is None]
    if plain:
        for k, out in zip(plain, _approach_rows(rows, [cfgs[k] for k in plain], predict, [skip[k] for k in plain])):
            outs[k] = out
    floors: dict[float, list[int]] = {}
    for k, c in enumerate(cfgs):
        if c.enroute_above_m is not None:
            floors.setdefault(c.enroute_above_m, []).append(k)
    for floor, ks in floors.items():
        low = rows.state()[0][:, 2] < floor if rows.tracks.height else np.zeros(0, bool)
        if low.all():                            # a terminal area only: the configured minima
            for k, out in zip(ks, _approach_rows(rows, [cfgs[k] for k in ks], predict, [skip[k] for k in ks])):
                outs[k] = out
            continue
        # the pairs of two rows below the floor are predicted once, by the terminal minima below
        below_floor = np.where(low, 0, -1)
        above = _approach_rows(rows, [cfgs[k].enroute() for k in ks], predict, [(*skip[k], below_floor) for k in ks])
        below = (_approach_rows(rows.subset(low), [cfgs[k] for k in ks], predict,
                                [tuple(g[low] for g in skip[k]) for k in ks]) if low.sum() >= 2
                 else [empty_conflicts() for _ in ks])
        for k, a, b in zip(ks, above, below):
            outs[k] = _joined(a, [b])
    return outs


def _joined(base: pl.DataFrame, parts: Sequence[pl.DataFrame]) -> pl.DataFrame:
    """``base`` with ``parts`` (pairs it left to another prediction), in the pair order."""
    out = [p for p in (base, *parts) if p.height]   # an empty part has the empty table's extra columns
    if len(out) == 1 and out[0] is base:
        return base
    return pl.concat(out, how="vertical_relaxed").sort("run", "epoch", "method", "id_a", "id_b") if out \
        else empty_conflicts()


def _approach_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], predict: Predict,
                   skip: Sequence[Groups]) -> list[pl.DataFrame]:
    """:func:`pair_rows` of each setting, with the pairs whose two tracks are established on the
    same final decided by that volume's parameters instead (:class:`ApproachVolume`).
    ``skip``: as for :func:`pair_rows`."""
    by_vols: dict[tuple, list[int]] = {}
    for k, c in enumerate(cfgs):
        by_vols.setdefault((c.mode, c.approach_volumes), []).append(k)
    members = {key: _membership(rows, cfgs[ks[0]]) for key, ks in by_vols.items()}
    members = {key: m for key, m in members.items() if np.any(m >= 0)}
    # the pairs on one final are predicted once, by that volume's parameters below
    keys = [(c.mode, c.approach_volumes) for c in cfgs]
    outs = predict(rows, cfgs, skip=[(*skip[k], members[key]) if key in members else tuple(skip[k])
                                     for k, key in enumerate(keys)])
    for key, member in members.items():
        ks = by_vols[key]
        inside: dict[int, list[pl.DataFrame]] = {k: [] for k in ks}
        vols = cfgs[ks[0]].approach_volumes
        counts = np.bincount(member[member >= 0], minlength=len(vols))
        # the volumes of equal parameters in one prediction, pairs within one volume: a call per
        # volume is a few rows each, and its fixed cost outweighs that work
        same: dict[tuple[float, float], list[int]] = {}
        for kv, v in enumerate(vols):
            if counts[kv] >= 2:
                same.setdefault((v.dr_h_m, v.t_thr_s), []).append(kv)
        for kvs in same.values():
            mask = np.isin(member, kvs)
            got = predict(rows.subset(mask), [vols[kvs[0]].parameters(cfgs[k]) for k in ks],
                          skip=[tuple(g[mask] for g in skip[k]) for k in ks], within=member[mask])
            for k, part in zip(ks, got):
                inside[k].append(part)
        for k in ks:
            outs[k] = _joined(outs[k], inside[k])
    return outs
