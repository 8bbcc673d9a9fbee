"""The conflict-prediction stage: :func:`conflicts_step` over one time window with the state
carried between windows (:class:`ConflictState`: the m-of-n confirmation and the coast ages),
:func:`predict_conflicts` (one step over all time) and :func:`slim_conflicts` (docs/methods.md,
"Conflict prediction (STCA)": "Windowed processing")."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import polars as pl

from safety.confirmation import confirm_alerts
from safety.conflicts.airspace import volume_rows
from safety.conflicts.config import FT_M, NM_M, ConflictConfig
from safety.conflicts.pairs import CONFLICT_EXTRA, WindowRows
from tertiary.contract import TABLES
from tertiary.core import geo
from tertiary.core.errors import OptionError
from tertiary.core.stage import T_MAX_US, T_MIN_US, Window, check_window

__all__ = ["T_MIN_US", "T_MAX_US", "ConflictState", "init_conflict_state", "conflicts_step", "conflicts_steps",
           "predict_conflicts", "slim_conflicts"]

def _not_coasting(tracks: pl.DataFrame, cfg: ConflictConfig, id_col: str, method_col: str,
                  last: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Drop rows of tracks coasting for more than ``cfg.max_coast_s`` (see the config).

    The coast age of a row is (epoch − the track's last epoch updated with a plot) in seconds,
    inf before its first plot. ``last`` (:data:`_LAST`: run, method, id, last_update_us) carries
    each track's last plot epoch from earlier windows; returns (kept rows, updated ``last``), the
    entries of ``last`` that can no longer keep a row (older than ``max_coast_s`` before this
    window's latest epoch — later windows only hold later epochs) dropped."""
    if cfg.max_coast_s is None or "plot_target_id" not in tracks.columns or not tracks.height:
        return tracks, last
    keys = list(_LAST)[:3]
    e = _epoch_us_expr()
    k = (tracks.select(*_key_exprs(method_col, id_col), e.alias("__e"),
                       pl.when(pl.col("plot_target_id").is_not_null()).then(e).alias("__u"))
         .with_columns(pl.col("__u").forward_fill().over(keys, order_by="__e"))
         .join(last, on=keys, how="left", maintain_order="left"))
    last_u = pl.coalesce("__u", "last_update_us")
    keep = k.select(((pl.col("__e") - last_u) * 1e-6).fill_null(float("inf")) <= cfg.max_coast_s).to_series()
    upd = k.group_by(keys).agg(pl.col("__u").max().alias("last_update_us")).drop_nulls()
    e_max = int(k["__e"].max())
    merged = (pl.concat([last, upd.cast(_LAST)]).group_by(keys).agg(pl.col("last_update_us").max())
              .filter((pl.lit(e_max, pl.Int64) - pl.col("last_update_us")) * 1e-6 <= cfg.max_coast_s)
              .sort(keys))
    return tracks.filter(keep), merged


def _established(tracks: pl.DataFrame, cfg: ConflictConfig) -> pl.DataFrame:
    """Drop tracks whose velocity sigma exceeds ``cfg.max_vel_sigma_mps`` (see the config)."""
    lim = cfg.max_vel_sigma_mps
    if lim is None:
        return tracks
    if "cov" in tracks.columns:
        var = pl.max_horizontal(pl.col("cov").arr.get(21), pl.col("cov").arr.get(28))
    elif "cov_diag" in tracks.columns:
        var = pl.max_horizontal(pl.col("cov_diag").arr.get(3), pl.col("cov_diag").arr.get(4))
    else:
        return tracks
    return tracks.filter(var <= lim * lim)




#: schemas of the carried state (natural keys, absolute int64 µs times)
_GRID = {"run": pl.UInt32, "method": pl.String, "epoch_us": pl.Int64}


_RAW = {"run": pl.UInt32, "method": pl.String, "epoch_us": pl.Int64, "id_a": pl.UInt64, "id_b": pl.UInt64}


_LAST = {"run": pl.UInt32, "method": pl.String, "id": pl.Int64, "last_update_us": pl.Int64}


def _epoch_us_expr() -> pl.Expr:
    """Row epoch as int64 µs since the Unix epoch (absolute, whatever the Datetime unit/zone)."""
    return pl.col("epoch").dt.epoch("us")


def _key_exprs(method_col: str, id_col: str) -> list[pl.Expr]:
    return [pl.col("run").cast(pl.UInt32).alias("run"), pl.col(method_col).cast(pl.String).alias("method"),
            pl.col(id_col).cast(pl.Int64).alias("id")]


@dataclass(frozen=True)
class ConflictState:
    """What conflict prediction carries from one time window to the next; every
    time is int64 µs since the Unix epoch, every key natural. Picklable, never mutated.

    * ``grid`` (run, method, epoch_us): the last ``confirm_n − 1`` epochs of each picture's
      epoch grid (the epochs at which the picture has any row, established or not) — the m-of-n
      alert confirmation counts picture epochs, not seconds, so a window boundary must not
      restart the count;
    * ``raw`` (run, method, epoch_us, id_a, id_b): the pairs whose raw alert condition
      (``raw_alert``) held at those epochs;
    * ``last_update`` (run, method, id, last_update_us): the last epoch at which each
      established track (``max_vel_sigma_mps``) was updated with a plot — the coast age of
      ``max_coast_s``; an entry is dropped once it is more than ``max_coast_s`` older than the
      latest epoch seen (it could no longer keep a row);
    * ``t_us``: the end of the last window processed (None before the first).

    Nothing else spans epochs: ``max_vel_sigma_mps`` is a per-row test, and pairs never span
    (run, epoch, method) groups, so the screening and the pair geometry are window-local."""

    grid: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_GRID))
    raw: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_RAW))
    last_update: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_LAST))
    t_us: int | None = None


def init_conflict_state() -> ConflictState:
    """The empty state (before the first window)."""
    return ConflictState()


def _normalise(picture: pl.DataFrame, id_col: str, method_col: str, default_method: str) -> pl.DataFrame:
    """Check the key columns; add ``run`` (0) and ``method_col`` (``default_method``) if absent."""
    for c in ("epoch", id_col):
        if c not in picture.columns:
            raise ValueError(f"tracks: missing column {c!r}")
    if not isinstance(picture.schema["epoch"], pl.Datetime):
        raise ValueError(f"tracks: column 'epoch' must be a Datetime, got {picture.schema['epoch']}")
    if "run" not in picture.columns:
        picture = picture.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    if method_col not in picture.columns:
        picture = picture.with_columns(pl.lit(default_method, pl.String).alias(method_col))
    return picture


def _epoch_grid(carried: pl.DataFrame, picture: pl.DataFrame, method_col: str) -> pl.DataFrame:
    """(run, method, epoch_us, epoch_k) of the carried grid tail and this window's epochs: the
    rank of each epoch in its picture's grid (an offset of :func:`epoch_index`'s; only
    differences matter to the confirmation)."""
    win = picture.select(pl.col("run").cast(pl.UInt32), pl.col(method_col).cast(pl.String).alias("method"),
                         _epoch_us_expr().alias("epoch_us"))
    return (pl.concat([carried, win]).unique().sort("run", "method", "epoch_us")
            .with_columns(pl.int_range(pl.len()).over("run", "method").cast(pl.Int64).alias("epoch_k")))


def _confirm(out: pl.DataFrame, grid: pl.DataFrame, carried: pl.DataFrame, cfg: ConflictConfig) -> pl.DataFrame:
    """:func:`confirm_alerts` of this window's rows, with the raw alerts of the carried epochs
    prepended so that the m-of-n count runs across the window boundary."""
    if cfg.confirm_m == 1 or not out.height:
        return confirm_alerts(out, grid, cfg.confirm_m, cfg.confirm_n)
    rows = out.select("run", "method", _epoch_us_expr().alias("epoch_us"), "id_a", "id_b", "alert")
    mini = pl.concat([carried.with_columns(pl.lit(True).alias("alert")), rows]).rename({"epoch_us": "epoch"})
    conf = confirm_alerts(mini, grid.rename({"epoch_us": "epoch"}), cfg.confirm_m, cfg.confirm_n)["alert"]
    return out.with_columns(pl.col("alert").alias("raw_alert"), conf.tail(out.height).alias("alert"))


def _carry_confirmation(grid: pl.DataFrame, carried: pl.DataFrame, out: pl.DataFrame, n: int
                        ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The new (grid, raw) of :class:`ConflictState`: the last n − 1 epochs of each picture and
    the raw alerts at them."""
    tail = (grid.filter(pl.col("epoch_k") > pl.col("epoch_k").max().over("run", "method") - n + 1)
            .select(list(_GRID)))
    raw_now = (out.filter(pl.col("raw_alert")).select("run", "method", _epoch_us_expr().alias("epoch_us"),
                                                      "id_a", "id_b")
               if out.height else pl.DataFrame(schema=_RAW))
    raw = (pl.concat([carried, raw_now.cast(_RAW)]).join(tail, on=list(_GRID), how="semi")
           .sort(list(_RAW)))
    return tail, raw


def conflicts_step(state: ConflictState, picture: pl.DataFrame, cfg: ConflictConfig = ConflictConfig(),
                   id_col: str = "track_id", frame: geo.LocalFrame | None = None,
                   t0_us: int = T_MIN_US, t1_us: int = T_MAX_US, *, method_col: str = "method",
                   default_method: str = "none", slim: bool = True, scored_only: bool = False
                   ) -> tuple[pl.DataFrame, ConflictState]:
    """One time window [t0_us, t1_us) of conflict prediction (the stage step contract).

    ``picture``: the picture's rows with epoch in [t0_us, t1_us) (every row of those epochs,
    tentative/coasting ones included — they count in the confirmation's epoch grid), same
    columns as :func:`predict_conflicts`; no margin before or after the window is needed, the
    history lives in ``state`` (:class:`ConflictState`). Returns (the window's ``conflicts`` —
    :func:`slim_conflicts` of :func:`predict_conflicts`'s rows when ``slim``, every screened
    row otherwise —, the new state). Over consecutive windows the concatenated outputs equal
    ``predict_conflicts`` (then ``slim_conflicts``) of the whole picture. Pure: ``state`` is
    not modified. Raises ValueError for rows outside the window or a window that starts before
    the previous one ended. ``scored_only``: as for :func:`conflicts_steps`."""
    return conflicts_steps([state], picture, [cfg], id_col, frame, t0_us, t1_us, method_col=method_col,
                           default_method=default_method, slim=slim, scored_only=scored_only)[0]


def conflicts_steps(states: Sequence[ConflictState], picture: pl.DataFrame, cfgs: Sequence[ConflictConfig],
                    id_col: str = "track_id", frame: geo.LocalFrame | None = None,
                    t0_us: int = T_MIN_US, t1_us: int = T_MAX_US, *, method_col: str = "method",
                    default_method: str = "none", slim: bool = True,
                    map_: Callable[..., Iterable] = map, scored_only: bool = False
                    ) -> list[tuple[pl.DataFrame, ConflictState]]:
    """:func:`conflicts_step` of one window under several settings at once, ``states[k]`` the
    state of ``cfgs[k]``: element k equals ``conflicts_step(states[k], picture, cfgs[k], …)``.
    What does not depend on the thresholds is done once — the rows kept, their state on height,
    covariance terms, and the KD-tree screen (one union screen, :func:`union_screen`, for the
    settings that share the screen's other inputs: the output set is decided per setting by the
    exact tests, so a wider screen changes no row). ``map_`` (e.g. a thread pool's ``map``)
    runs the per-setting work. ``scored_only``: each window's rows only where an alert scoring
    reads them (raw alerts and the first row of each picture epoch; the state is the same):
    :func:`safety.alerts.episodes.scored_conflicts` of them is that of every row."""
    if len(states) != len(cfgs):
        raise ValueError("conflicts_steps: one state per configuration")
    tracks = _normalise(picture, id_col, method_col, default_method)
    for state in states:
        if not t0_us < t1_us:       # a conflict window holds at least one epoch
            raise OptionError(f"conflicts_step: empty or reversed window [{t0_us}, {t1_us}) µs", option="window")
        check_window(tracks, Window(0, t0_us, t1_us), after_us=state.t_us, table="tracks")
    grids = _shared([s.grid for s in states], lambda carried: _epoch_grid(carried, tracks, method_col))
    kept: list[tuple[pl.DataFrame, pl.DataFrame]] = []
    memo: list[tuple[tuple, pl.DataFrame, tuple[pl.DataFrame, pl.DataFrame]]] = []
    for state, cfg in zip(states, cfgs):
        key = (cfg.max_vel_sigma_mps, cfg.max_coast_s)
        hit = next((v for k, last, v in memo if k == key and _same(last, state.last_update)), None)
        if hit is None:
            hit = _not_coasting(_established(tracks, cfg), cfg, id_col, method_col, state.last_update)
            memo.append((key, state.last_update, hit))
        kept.append(hit)
    pair_rows: list[pl.DataFrame | None] = [None] * len(cfgs)
    for table in {id(k[0]): k[0] for k in kept}.values():
        ks = [k for k in range(len(cfgs)) if kept[k][0] is table]
        rows = WindowRows(table, frame, id_col, method_col)
        for k, out in zip(ks, volume_rows(rows, [cfgs[k] for k in ks], map_, scored_only)):
            pair_rows[k] = out
    spec = {**TABLES["conflicts"].required, **CONFLICT_EXTRA}

    def finish(k: int) -> tuple[pl.DataFrame, ConflictState]:
        state, cfg = states[k], cfgs[k]
        out = _confirm(pair_rows[k], grids[k], state.raw, cfg).select(list(spec)).cast(spec)
        g_tail, raw = _carry_confirmation(grids[k], state.raw, out, cfg.confirm_n)
        new = ConflictState(g_tail, raw, kept[k][1], t1_us if state.t_us is None else max(state.t_us, t1_us))
        return (slim_conflicts(out) if slim else out), new
    return list(map_(finish, range(len(cfgs))))


def _same(a: pl.DataFrame, b: pl.DataFrame) -> bool:
    return a is b or (a.schema == b.schema and a.equals(b))


def _shared(frames: Sequence[pl.DataFrame], fn: Callable[[pl.DataFrame], pl.DataFrame]) -> list[pl.DataFrame]:
    """``[fn(f) for f in frames]``, computed once per distinct (equal) frame."""
    done: list[tuple[pl.DataFrame, pl.DataFrame]] = []
    out = []
    for f in frames:
        hit = next((v for k, v in done if _same(k, f)), None)
        if hit is None:
            hit = fn(f)
            done.append((f, hit))
        out.append(hit)
    return out


def predict_conflicts(tracks: pl.DataFrame, cfg: ConflictConfig = ConflictConfig(), id_col: str = "track_id",
                      method_col: str = "method", default_method: str = "none",
                      frame: geo.LocalFrame | None = None) -> pl.DataFrame:
    """Predicted conflicts of an air picture — (5.10)–(5.17), rule ``cfg.mode``.

    ``tracks``: any track table with ``run``, ``epoch``, ``id_col`` (``track_id``; fused
    tables: ``target_id``), the system-frame ENU state ``x_m … vz_mps``, optionally the height
    channel :data:`ALT_COLUMNS` and, for ``threshold_mode="covariance"``, ``cov`` (row-major
    6×6) or ``cov_diag``. Heights: ``alt_m`` where present, else the geodetic height of the ENU
    position in ``frame`` (the system origin; None: spherical fallback, see
    :func:`height_and_rate`) — never ENU z. Pairs are formed within each (run, epoch,
    ``method_col``) group; without a method column the label is ``default_method``. Returns
    the ``conflicts`` table plus :data:`CONFLICT_EXTRA` (``t_in_s``: start of the predicted
    same-time conflict interval, NaN if none; ``near``; ``raw_alert``), id_a < id_b, sorted by
    (run, epoch, method, id_a, id_b). The whole run is one :func:`conflicts_step` over
    (−∞, +∞) from :func:`init_conflict_state`.
    """
    out, _ = conflicts_step(init_conflict_state(), tracks, cfg, id_col, frame, method_col=method_col,
                            default_method=default_method, slim=False)
    return out


def slim_conflicts(conflicts: pl.DataFrame, margin_h_m: float | None = None, margin_v_m: float | None = None
                   ) -> pl.DataFrame:
    """The output diet: rows that alert or are *near* — within the near margins of both
    thresholds at the same predicted time (column ``near`` of :func:`predict_conflicts`, with
    the margins of its ``ConflictConfig``). Explicit margins (or a table without ``near``)
    use the stored geometry instead: keep alert | (r_min ≤ r_thr + m_h ∧ dz_min ≤ z_thr + m_v
    ∧ T_min ≤ t_thr)."""
    if margin_h_m is None and margin_v_m is None and "near" in conflicts.columns:
        return conflicts.filter(pl.col("alert") | pl.col("near"))
    mh = NM_M if margin_h_m is None else float(margin_h_m)
    mv = 300.0 * FT_M if margin_v_m is None else float(margin_v_m)
    near = ((pl.col("r_min_m") <= pl.col("r_thr_m") + mh) & (pl.col("dz_min_m") <= pl.col("z_thr_m") + mv)
            & (pl.col("t_min_s") <= pl.col("t_thr_s")))
    return conflicts.filter(pl.col("alert") | near)
