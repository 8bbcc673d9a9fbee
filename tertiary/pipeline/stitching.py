"""The slice boundaries of a distributed run (:mod:`tertiary.pipeline.dask_engine`): each time
slice's target, track and cluster ids continued from the previous slice's.

A slice's ids are its own. In the overlap (the warm-up before a slice, whose rows the partition
kept aside) its rows are matched to the previous slice's kept rows: targets by the reports they
share (same report row → same target), tracks by position (same epoch, distance ≤ ``gate_m``),
clusters by lead target; one-to-one (Hungarian, most coinciding epochs first). Each boundary's
matches are a piece of its own, in both slices' own ids (:func:`slice_piece`, run where the
fanout puts it). The client then threads the pieces in time order (:func:`stitch`): a matched id
takes the previous slice's final id, an unmatched one a fresh id above every id of its group so
far; target ids are then renumbered by (run, first epoch, id), the order in which the local
engine creates them. Every partition's parts are relabelled in place (:func:`relabel_partition`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from scipy.optimize import linear_sum_assignment

from tertiary.pipeline.partition_writer import read_part, slice_files
from tertiary.pipeline.stitch_effects import boundary_utc
from tertiary.runtime.fanout import Fanout, serial
from tertiary.store.run_store import write_parquet_atomic

__all__ = ["CLUSTER_GROUP", "TRACK_GROUP", "relabel_partition", "slice_piece", "stitch"]

TRACK_GROUP = ["run", "method", "filter"]
CLUSTER_GROUP = ["run", "method"]


def _assign(pairs: pl.DataFrame, group: list[str]) -> pl.DataFrame:
    """One-to-one matches of (a, b) pairs with ``n`` coinciding epochs and mean distance ``d``:
    per group, the Hungarian assignment maximising coinciding epochs (then closeness)."""
    out = []
    for _key, g in pairs.group_by(group, maintain_order=True) if group else [((), pairs)]:
        ua, ia = np.unique(g["a"].to_numpy(), return_inverse=True)
        ub, ib = np.unique(g["b"].to_numpy(), return_inverse=True)
        score = np.zeros((len(ua), len(ub)))
        # many coinciding epochs first; among equals the nearer (d < gate, so d/gate < 1)
        score[ia, ib] = g["n"].to_numpy() - g["d"].to_numpy() / (1.0 + g["d"].max())
        r, c = linear_sum_assignment(score, maximize=True)
        ok = score[r, c] > 0
        m = pl.DataFrame({"a": ua[r[ok]], "b": ub[c[ok]]}, schema={"a": pl.UInt64, "b": pl.UInt64})
        first = g.row(0, named=True)
        out.append(m.with_columns([pl.lit(first[k], g.schema[k]).alias(k) for k in group]).select(*group, "a", "b"))
    if not out:
        return pairs.select(*group, pl.col("a").cast(pl.UInt64), pl.col("b").cast(pl.UInt64)).clear()
    return pl.concat(out)


def _pairs(prev: pl.DataFrame, cur: pl.DataFrame, on: list[str], group: list[str], id_col: str,
           gate_m: float | None) -> pl.DataFrame:
    """Coinciding (prev id a, cur id b) per group: rows joined on ``on`` (and within ``gate_m``)."""
    cols = ["x_m", "y_m", "z_m"] if gate_m is not None else []
    if gate_m is None:
        j = prev.select(*on, pl.col(id_col).alias("a")).join(cur.select(*on, pl.col(id_col).alias("b")), on=on)
        j = j.with_columns(pl.lit(0.0).alias("d"))
    else:
        # candidates from the 3 x 3 grid cells of side gate_m around each row, not every row of an
        # epoch against every other (quadratic: ~20 GB on a national-peak slice)
        cell = [(pl.col("x_m") // gate_m).cast(pl.Int64).alias("__cx"),
                (pl.col("y_m") // gate_m).cast(pl.Int64).alias("__cy")]
        a = prev.select(*on, pl.col(id_col).alias("a"), *cols).with_columns(cell)
        b = cur.select(*on, pl.col(id_col).alias("b"), *cols).with_columns(cell)
        key = [*on, "__cx", "__cy"]
        j = pl.concat([a.join(b.with_columns(pl.col("__cx") + dx, pl.col("__cy") + dy), on=key, suffix="_b")
                       for dx in (-1, 0, 1) for dy in (-1, 0, 1)]).drop("__cx", "__cy")
        d = ((pl.col("x_m") - pl.col("x_m_b")) ** 2 + (pl.col("y_m") - pl.col("y_m_b")) ** 2
             + (pl.col("z_m") - pl.col("z_m_b")) ** 2).sqrt()
        j = j.with_columns(d.alias("d")).filter(pl.col("d") <= gate_m)
    return j.group_by(*group, "a", "b").agg(pl.len().alias("n"), pl.col("d").mean())


class _IdSpace:
    """Ids handed out per group (e.g. per (run, method, filter) for tracks): a slice's id maps to
    the previous slice's id it matched, else to a fresh id above every id of its group so far."""

    def __init__(self, group: list[str]) -> None:
        self.group = group
        self.top: pl.DataFrame | None = None

    def fresh(self, ids: pl.DataFrame, matched: pl.DataFrame | None, keep: bool = False) -> pl.DataFrame:
        """Map (group…, old, new) of every id in ``ids`` (group…, b); ``matched`` (group…, a, b);
        ``keep``: the ids stay (a run's first slice)."""
        g = self.group
        if keep or matched is None or matched.height == 0:
            m = ids.with_columns((pl.col("b") if keep else pl.lit(None)).cast(pl.UInt64).alias("a"))
        else:
            m = ids.join(matched.select(*g, pl.col("a").cast(pl.UInt64), pl.col("b").cast(ids.schema["b"])),
                         on=[*g, "b"], how="left")
        un = m.filter(pl.col("a").is_null()).sort(*g, "b")
        un = (un.join(self.top, on=g, how="left") if self.top is not None
              else un.with_columns(pl.lit(None, pl.Int64).alias("top")))
        un = un.with_columns((pl.col("top").fill_null(-1) + 1 + pl.int_range(pl.len()).over(g))
                             .cast(pl.UInt64).alias("a")).drop("top")
        mapped = pl.concat([m.filter(pl.col("a").is_not_null()), un.select(m.columns)])
        top = mapped.group_by(g).agg(pl.col("a").max().cast(pl.Int64).alias("top"))
        self.top = top if self.top is None else pl.concat([self.top, top]).group_by(g).agg(pl.col("top").max())
        return mapped.select(*g, pl.col("b").alias("old"), pl.col("a").alias("new"))


def _distinct(frame: pl.DataFrame | None, cols: list[str], id_col: str) -> pl.DataFrame:
    """Distinct (group, id) of a partition's rows ``frame`` (``id_col`` renamed ``b``); no
    column when it has none."""
    if frame is None or id_col not in frame.columns:
        return pl.DataFrame()
    return frame.select(*cols, pl.col(id_col).alias("b")).unique()


def _run_key(p: Any) -> int:
    """The run a partition's ids are numbered in (0 for a dataset without runs)."""
    return 0 if p.run is None else int(p.run)


def _target_ids(firsts: pl.DataFrame, tracks: pl.DataFrame | None, clusters: pl.DataFrame | None) -> pl.DataFrame:
    """A partition's target ids: those of its associations and fused rows (``firsts``), and those
    its tracks and clusters name."""
    parts = [firsts.select(pl.col("target_id").alias("b")), _distinct(tracks, [], "plot_target_id"),
             _distinct(clusters, [], "lead_target_id")]
    parts = [p.cast({"b": pl.UInt64}) for p in parts if p.width]
    return pl.concat(parts).drop_nulls().unique() if parts else pl.DataFrame(schema={"b": pl.UInt64})


def _remap(frame: pl.DataFrame | None, maps: dict[str, pl.DataFrame]) -> pl.DataFrame | None:
    """``frame`` with its target, track and cluster ids through ``maps`` (old → new)."""
    if frame is None or frame.height == 0:
        return frame
    tm = maps["target"]
    old, new = tm["old"], tm["new"]

    def tgt(c: str) -> pl.Expr:
        return pl.col(c).replace_strict(old, new, default=None, return_dtype=pl.UInt64)

    cols = frame.columns
    out = frame
    if "target_id" in cols:
        out = out.with_columns(tgt("target_id"))
    if "plot_target_id" in cols:
        out = out.with_columns(tgt("plot_target_id"))
    if "lead_target_id" in cols:
        out = out.with_columns(tgt("lead_target_id"),
                               pl.col("members").list.eval(pl.element().replace_strict(old, new, default=None,
                                                                                        return_dtype=pl.UInt64)))
    if "cluster_id" in cols and maps.get("cluster") is not None:
        out = _join_map(out, maps["cluster"], CLUSTER_GROUP, "cluster_id")
    if "track_id" in cols and "filter" in cols and maps.get("track") is not None:
        out = _join_map(out, maps["track"], TRACK_GROUP, "track_id")
    if "id_a" in cols:
        out = _remap_conflicts(out, maps)
    return out


def _join_map(frame: pl.DataFrame, m: pl.DataFrame, group: list[str], col: str) -> pl.DataFrame:
    m = m.select(*group, pl.col("old").cast(frame.schema[col]).alias(col), pl.col("new").alias("__new"))
    j = frame.join(m, on=[*group, col], how="left", maintain_order="left")
    return j.with_columns(pl.coalesce("__new", col).cast(frame.schema[col]).alias(col)).drop("__new")


def _remap_conflicts(frame: pl.DataFrame, maps: dict[str, pl.DataFrame]) -> pl.DataFrame:
    """id_a/id_b are track ids where the picture is "<method>+<filter>", else target ids."""
    tm = maps["target"]
    is_track = pl.col("method").str.contains("+", literal=True)
    out = frame.with_columns(pl.col("method").str.split_exact("+", 1).struct.rename_fields(["__m", "__f"])
                             .alias("__mf")).unnest("__mf")
    for c in ("id_a", "id_b"):
        tgt = pl.col(c).replace_strict(tm["old"], tm["new"], default=pl.col(c), return_dtype=pl.UInt64)
        if maps.get("track") is not None:
            m = maps["track"].select(pl.col("run"), pl.col("method").alias("__m"), pl.col("filter").alias("__f"),
                                     pl.col("old").alias(c), pl.col("new").alias("__new"))
            out = out.join(m, on=["run", "__m", "__f", c], how="left", maintain_order="left")
            trk = pl.coalesce("__new", c)
        else:
            out = out.with_columns(pl.lit(None, pl.UInt64).alias("__new"))
            trk = pl.col(c)
        out = out.with_columns(pl.when(is_track).then(trk).otherwise(tgt).cast(pl.UInt64).alias(c)).drop("__new")
    return out.drop("__m", "__f")


def slice_piece(out: str, p: Any, prev: Any | None, gate_m: float) -> dict:
    """A piece of the stitching, in the slices' own ids: partition ``p``'s ids (``ids``: per kind,
    (group…, b)), their first kept epochs (``firsts``: target_id, epoch) and, after a previous
    slice ``prev`` of its run, the overlap's matches (``matched``: per kind, (group…, a = the
    previous slice's id, b))."""
    o = Path(out)
    own = [f for n in ("associations", "fused")
           if (f := read_part(o, p.index, n, columns=["epoch", "target_id"])) is not None and f.height]
    firsts = (pl.concat(own, how="vertical_relaxed").group_by("target_id").agg(pl.col("epoch").min())
              if own else pl.DataFrame(schema={"target_id": pl.UInt64, "epoch": pl.Datetime("us")}))
    # each table read once for its own ids and the target ids it names
    tracks = read_part(o, p.index, "tracks", columns=[*TRACK_GROUP, "track_id", "plot_target_id"])
    clusters = read_part(o, p.index, "clusters", columns=[*CLUSTER_GROUP, "cluster_id", "lead_target_id"])
    ids = {"target": _target_ids(firsts, tracks, clusters), "track": _distinct(tracks, TRACK_GROUP, "track_id"),
           "cluster": _distinct(clusters, CLUSTER_GROUP, "cluster_id")}
    return {"ids": ids, "firsts": firsts, "matched": _matches(o, p, prev, gate_m) if prev is not None else {}}


def stitch(out: Path, parts: list[Any], gate_m: float, fanout: Fanout = serial
           ) -> tuple[dict[int, dict], pl.DataFrame]:
    """Id maps of every partition (per kind, old → new) and, per slice boundary, what stitching did
    (ids matched and given fresh ids). The pieces (:func:`slice_piece`) are independent; threading
    them is sequential over the partitions (a slice's final ids are its previous slice's)."""
    by_index = {p.index: p for p in parts}
    prevs = [by_index.get(p.index - 1) if p.slice > 0 else None for p in parts]
    pieces = list(fanout(slice_piece, [(str(out), p, prev, gate_m) for p, prev in zip(parts, prevs)]))
    spaces = {"target": _IdSpace(["__all"]), "track": _IdSpace(TRACK_GROUP), "cluster": _IdSpace(CLUSTER_GROUP)}
    maps: dict[int, dict] = {}
    report = []
    for p, prev, piece in zip(parts, prevs, pieces):
        maps[p.index], row = _thread(p, prev, piece, maps.get(p.index - 1), spaces)
        if row:
            report.append(row)
    _canonical_targets(parts, pieces, maps)
    return maps, pl.DataFrame(report) if report else pl.DataFrame()


def _in_final_ids(matched: dict[str, pl.DataFrame], prev_maps: dict) -> dict[str, pl.DataFrame]:
    """The overlap's matches with ``a`` in the previous slice's final ids."""
    groups = {"target": [], "track": TRACK_GROUP, "cluster": CLUSTER_GROUP}
    got = {}
    for kind, m in matched.items():
        g, pm = groups[kind], prev_maps.get(kind)
        if pm is None:
            continue
        pm = pm.select(*g, pl.col("old").cast(m.schema["a"]).alias("a"), pl.col("new").alias("__new"))
        got[kind] = m.join(pm, on=[*g, "a"], how="inner", maintain_order="left").with_columns(
            pl.col("__new").alias("a")).drop("__new")
    return got


def _thread(p: Any, prev: Any | None, piece: dict, prev_maps: dict | None, spaces: dict[str, "_IdSpace"]
            ) -> tuple[dict, dict]:
    # target ids are numbered per run (tertiary.stages.association.associate), like track and cluster ids; a
    # partition holds one run, so its target space is that run's
    ids = dict(piece["ids"])
    ids["target"] = ids["target"].with_columns(__all=pl.lit(_run_key(p)))
    got = _in_final_ids(piece["matched"], prev_maps or {}) if prev is not None else {}
    if "target" in got:
        got["target"] = got["target"].with_columns(__all=pl.lit(_run_key(p)))
    maps: dict[str, pl.DataFrame | None] = {}
    for kind, space in spaces.items():
        if ids[kind].width == 0:
            maps[kind] = None
            continue
        # a run's first slice keeps its track and cluster ids (numbered per run, like the local engine)
        maps[kind] = space.fresh(ids[kind], got.get(kind), keep=prev is None)
    maps["target"] = maps["target"].drop("__all") if maps["target"] is not None else \
        pl.DataFrame(schema={"old": pl.UInt64, "new": pl.UInt64})
    row: dict = {}
    if prev is not None:
        row = {"partition": p.index, "run": p.run, "boundary_utc": boundary_utc(p.t0_us)}
        for kind in spaces:
            m = maps[kind]
            row[f"{kind}s"] = m.height if m is not None else 0
            # kept ids that continue an id of the previous slice (the others got fresh ids)
            row[f"{kind}s_continued"] = (m.join(got[kind].select(pl.col("b").alias("old")).unique(), on="old",
                                               how="semi").height if kind in got and m is not None else 0)
    return maps, row


def _matches(out: Path, p: Any, prev: Any, gate_m: float) -> dict[str, pl.DataFrame]:
    """Matches (group…, a = the previous slice's id, b = this slice's id) in the overlap."""
    lo = p.t0_us - p.warm_us

    def before(name: str) -> pl.DataFrame | None:
        files = slice_files(out, prev.index, "kept", name)
        if not files:
            return None
        return pl.concat([pl.scan_parquet(x).filter(pl.col("epoch").dt.epoch("us") >= lo).collect() for x in files],
                         how="vertical_relaxed")

    got: dict[str, pl.DataFrame] = {}
    a0, a1 = before("associations"), read_part(out, p.index, "associations", sub="overlap")
    if a0 is not None and a1 is not None and a0.height and a1.height:
        key = ["run", "epoch", "radar_id", "local_track_id", "report_id"]
        got["target"] = _assign(_pairs(a0, a1, key, [], "target_id", None), [])
    t0, t1 = before("tracks"), read_part(out, p.index, "tracks", sub="overlap")
    if t0 is not None and t1 is not None and t0.height and t1.height:
        got["track"] = _assign(_pairs(t0, t1, [*TRACK_GROUP, "epoch"], TRACK_GROUP, "track_id", gate_m),
                               TRACK_GROUP)
    c0, c1 = before("clusters"), read_part(out, p.index, "clusters", sub="overlap")
    if c0 is not None and c1 is not None and c0.height and c1.height and "target" in got:
        # the warm-up clusters' leads in the previous slice's ids (unmatched leads become null)
        tm = got["target"].select(pl.col("b").alias("old"), pl.col("a").alias("new"))
        c1 = _remap(c1, {"target": tm})
        got["cluster"] = _assign(_pairs(c0, c1, [*CLUSTER_GROUP, "epoch", "lead_target_id"], CLUSTER_GROUP,
                                        "cluster_id", None), CLUSTER_GROUP)
    return got


def _canonical_targets(parts: list[Any], pieces: list[dict], maps: dict[int, dict]) -> None:
    """Target ids renumbered by (first kept epoch, run, stitched id): the local engine's creation order."""
    firsts = [piece["firsts"].join(maps[p.index]["target"], left_on="target_id", right_on="old")
              .select("new", "epoch").with_columns(run=pl.lit(_run_key(p), pl.Int64))
              for p, piece in zip(parts, pieces) if piece["firsts"].height]
    if not firsts:
        return
    order = (pl.concat(firsts).group_by("run", "new").agg(pl.col("epoch").min())
             .sort("run", "epoch", "new").with_columns(canon=pl.int_range(pl.len()).over("run")))
    for p in parts:
        m = maps[p.index]["target"].with_columns(run=pl.lit(_run_key(p), pl.Int64))
        maps[p.index]["target"] = (m.join(order.select("run", "new", "canon"), on=["run", "new"], how="left")
                                   .select("old", pl.coalesce("canon", "new").cast(pl.UInt64).alias("new")))


def relabel_partition(out_dir: str, index: int, maps: dict) -> int:
    """Rewrite a partition's kept parts with the stitched ids (a task; atomic per file)."""
    n = 0
    for name in ("associations", "fused", "clusters", "tracks", "conflicts", "curve_rows"):
        for f in slice_files(Path(out_dir), index, "kept", name):
            frame = pl.read_parquet(f)
            new = _remap(frame, maps)
            for c in ("target_id", "plot_target_id", "lead_target_id"):
                if c in frame.columns and new[c].null_count() > frame[c].null_count():
                    raise RuntimeError(f"stitching lost {c} values in {f}")
            write_parquet_atomic(new, f, compression="zstd")
            n += frame.height
    return n
