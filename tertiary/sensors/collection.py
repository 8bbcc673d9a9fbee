"""Report collection ahead of alignment (monograph §1.4).

The tertiary processor receives the radars' reports over time and processes them one at a
time (``servers`` processors in parallel); a report that cannot be taken at once meets one of
the three queue disciplines the seed names:

* ``"refusals"`` — *with refusals*: a report arriving while every processor is busy is lost
  (the loss system M/G/c/c; for exponential processing times its loss probability is Erlang's
  B formula, :func:`erlang_b`);
* ``"waiting"`` — *with waiting*: it queues first-in first-out and is processed later (no loss
  unless ``queue_places`` bounds the buffer: M/M/1/K, :func:`mm1k_loss`); mean waits
  M/M/1 W_q = ρ/(μ − λ), M/D/1 W_q = ρ D / (2(1 − ρ)) (:func:`mm1_wait`, :func:`md1_wait`);
* ``"limited"`` — *with limited waiting* (the mixed type used in practice): it queues, but a
  report whose wait would exceed ``max_wait_s`` (T_wait) is lost. Under FIFO the wait of a
  report is fixed when it arrives (the work of the reports ahead of it), so the report is
  dropped on arrival and never occupies a processor; for M/M/1 its loss probability is
  P = (1 − ρ) ρ e^{−(μ−λ)T} / (1 − ρ² e^{−(μ−λ)T}) (:func:`mm1_limited_loss`, derived by
  level crossing of the virtual waiting time; T = 0 gives Erlang B, T → ∞ gives 0).

Processing-time model (the seed gives none): ``"exponential"`` with mean ``service_time_s``
(drawn with ``seed``) or ``"deterministic"`` = ``service_time_s``. The arrival time of a report
is its ``arrival_time`` column when present, else its ``time``; each Monte-Carlo ``run`` is an
independent queue. :func:`collect` returns the accepted reports with their waiting and
processing delay and the lost reports with a reason; :func:`collection_stage` turns the lost
ones into ``rejects`` rows (stage ``"collection"``) so that every report is still accounted for.

The queue recursion is sequential (each report's wait depends on the previous ones), so it is
a compiled loop (numba, ``cache=True``), compiled on first use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numba
import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary import contract as schema
from tertiary.core.errors import OptionError

__all__ = [
    "DISCIPLINES", "SERVICE_MODELS", "CollectionConfig", "Collected", "collect", "collection_stage",
    "queue_kernel", "erlang_b", "mm1_wait", "md1_wait", "mm1k_loss", "mm1_limited_loss",
]

DISCIPLINES = ("refusals", "waiting", "limited")
SERVICE_MODELS = ("exponential", "deterministic")

#: outcome codes of :func:`queue_kernel`
ACCEPTED, LOST_BUSY, LOST_WAIT, LOST_BUFFER = 0, 1, 2, 3


@dataclass(frozen=True)
class CollectionConfig:
    """Queue discipline and processing-time model of report collection.

    * ``discipline``: ``"refusals"``, ``"waiting"`` or ``"limited"`` (module docstring);
    * ``service_time_s``: mean processing time of one report (s, > 0);
    * ``service_model``: ``"exponential"`` or ``"deterministic"``;
    * ``max_wait_s``: T_wait of ``"limited"`` (s, ≥ 0; the seed gives no value);
    * ``servers``: processors working in parallel (c ≥ 1);
    * ``queue_places``: waiting places of ``"waiting"``/``"limited"`` (None: unbounded);
    * ``seed``: random processing times (``"exponential"``).
    """

    discipline: str = "limited"
    service_time_s: float = 0.01
    service_model: str = "exponential"
    max_wait_s: float = 0.1
    servers: int = 1
    queue_places: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.discipline not in DISCIPLINES:
            raise OptionError(f"choose {', '.join(DISCIPLINES)}, got {self.discipline!r}", option="--collection")
        if self.service_model not in SERVICE_MODELS:
            raise OptionError(f"choose {', '.join(SERVICE_MODELS)}, got {self.service_model!r}",
                              option="--service-model")
        if not (math.isfinite(self.service_time_s) and self.service_time_s > 0):
            raise OptionError(f"must be finite and > 0, got {self.service_time_s}", option="--service-time")
        if not (math.isfinite(self.max_wait_s) and self.max_wait_s >= 0):
            raise OptionError(f"must be finite and >= 0, got {self.max_wait_s}", option="--max-wait")
        if self.servers < 1:
            raise OptionError(f"must be >= 1, got {self.servers}", option="collection.servers")
        if self.queue_places is not None and self.queue_places < 0:
            raise OptionError(f"must be >= 0, got {self.queue_places}", option="collection.queue_places")


# ---------------------------------------------------------------------------
# closed forms (the references of the tests)
# ---------------------------------------------------------------------------


def erlang_b(servers: int, load: float) -> float:
    """Erlang B: loss probability of M/M/c/c with offered load a = λ/μ, by the stable recursion
    B(0) = 1, B(k) = a B(k−1) / (k + a B(k−1))."""
    b = 1.0
    for k in range(1, servers + 1):
        b = load * b / (k + load * b)
    return b


def mm1_wait(lam: float, mu: float) -> float:
    """Mean FIFO wait in the queue of M/M/1: W_q = ρ / (μ − λ), ρ = λ/μ < 1."""
    return (lam / mu) / (mu - lam)


def md1_wait(lam: float, d: float) -> float:
    """Mean FIFO wait of M/D/1 (Pollaczek–Khinchine with a deterministic service time D):
    W_q = ρ D / (2(1 − ρ)), ρ = λ D < 1."""
    rho = lam * d
    return rho * d / (2.0 * (1.0 - rho))


def mm1k_loss(lam: float, mu: float, capacity: int) -> float:
    """Blocking probability of M/M/1/K (K = places in the system, the one in service included):
    P_K = (1 − ρ) ρ^K / (1 − ρ^{K+1}) (ρ ≠ 1; 1/(K + 1) at ρ = 1)."""
    rho = lam / mu
    if abs(rho - 1.0) < 1e-12:
        return 1.0 / (capacity + 1)
    return (1.0 - rho) * rho ** capacity / (1.0 - rho ** (capacity + 1))


def mm1_limited_loss(lam: float, mu: float, t_wait: float) -> float:
    """Loss probability of M/M/1 with limited waiting T (a report whose FIFO wait would exceed
    T is lost on arrival). Level crossing of the virtual waiting time V: density λP₀e^{−(μ−λ)v}
    for v ≤ T and f(T)e^{−μ(v−T)} beyond; P(loss) = P(V > T) gives
    P = (1 − ρ) ρ e^{−(μ−λ)T} / (1 − ρ² e^{−(μ−λ)T}) (T = 0: Erlang B ρ/(1 + ρ))."""
    rho = lam / mu
    e = math.exp(-(mu - lam) * t_wait)
    if abs(rho - 1.0) < 1e-12:
        return 1.0 / (2.0 + mu * t_wait)
    return (1.0 - rho) * rho * e / (1.0 - rho * rho * e)


# ---------------------------------------------------------------------------
# the queue recursion
# ---------------------------------------------------------------------------


def _queue_py(t, service, seg_starts, mode, max_wait, servers, places):  # noqa: ANN001, ANN202 - numba kernel
    """FIFO c-server queue over arrivals ``t`` (sorted within each segment). mode 0: refusals,
    1: waiting, 2: limited. places < 0: unbounded buffer. Returns (wait, status)."""
    n = t.shape[0]
    wait = np.full(n, np.nan)
    status = np.zeros(n, np.int8)
    starts = np.empty(n)                     # start times of accepted reports (non-decreasing)
    bounds = np.append(seg_starts, n)
    for s in range(bounds.shape[0] - 1):
        free = np.full(servers, -np.inf)     # when each processor becomes free
        n_acc = 0
        head = 0                             # first accepted report not yet started at time t
        for i in range(bounds[s], bounds[s + 1]):
            ti = t[i]
            k = 0
            for j in range(1, servers):
                if free[j] < free[k]:
                    k = j
            w = free[k] - ti
            if w < 0.0:
                w = 0.0
            while head < n_acc and starts[head] <= ti:
                head += 1
            queued = n_acc - head            # reports waiting (accepted, not started) at ti
            if w > 0.0 and mode == 0:
                status[i] = 1
                continue
            if w > 0.0 and places >= 0 and queued >= places:
                status[i] = 3
                continue
            if mode == 2 and w > max_wait:
                status[i] = 2
                continue
            wait[i] = w
            starts[n_acc] = ti + w
            n_acc += 1
            free[k] = ti + w + service[i]
    return wait, status


@cache
def _compiled():
    return numba.njit(cache=True)(_queue_py)


def queue_kernel(t: NDArray[np.float64], service: NDArray[np.float64], seg_starts: NDArray[np.int64],
                 discipline: str, max_wait_s: float = 0.0, servers: int = 1,
                 queue_places: int | None = None) -> tuple[NDArray[np.float64], NDArray[np.int8]]:
    """Waiting time (NaN when lost) and outcome (:data:`ACCEPTED`, :data:`LOST_BUSY`,
    :data:`LOST_WAIT`, :data:`LOST_BUFFER`) of every arrival; ``t`` sorted within each segment
    (``seg_starts``: first index of each independent queue, e.g. Monte-Carlo run)."""
    mode = DISCIPLINES.index(discipline)
    t = np.ascontiguousarray(t, np.float64)
    if len(t) == 0:
        return np.zeros(0), np.zeros(0, np.int8)
    places = -1 if queue_places is None else int(queue_places)
    return _compiled()(t, np.ascontiguousarray(service, np.float64), np.asarray(seg_starts, np.int64),
                       mode, float(max_wait_s), int(servers), places)


# ---------------------------------------------------------------------------
# frame level
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Collected:
    """``accepted``: the accepted reports (input columns, arrival order) with
    ``collection_wait_s`` and ``collection_delay_s`` (wait + processing); ``lost``: ``report_id``,
    ``reason``, ``collection_wait_s`` (the wait it would have had; null for a refusal);
    ``stats``: one row per run — offered, accepted, lost by reason, loss share, mean wait/delay."""

    accepted: pl.DataFrame
    lost: pl.DataFrame
    stats: pl.DataFrame


def _reasons(cfg: CollectionConfig) -> dict[int, str]:
    return {
        LOST_BUSY: f"collection: all {cfg.servers} processor(s) busy on arrival (queue with refusals)",
        LOST_WAIT: f"collection: waiting time would exceed T_wait = {cfg.max_wait_s:g} s (limited waiting)",
        LOST_BUFFER: f"collection: buffer full ({cfg.queue_places} waiting places)",
    }


def _arrival_seconds(reports: pl.DataFrame) -> pl.Expr:
    """Arrival time in seconds from the run's first arrival (integer microseconds are subtracted
    before the conversion: epoch seconds as float64 would keep only ~0.2 µs)."""
    col = "arrival_time" if "arrival_time" in reports.columns else "time"
    if reports.schema[col].is_numeric():
        t = pl.col(col).cast(pl.Float64)
        return t - t.min().over("__run")
    t = pl.col(col).dt.epoch("us")
    return (t - t.min().over("__run")).cast(pl.Float64) * 1e-6


def collect(reports: pl.DataFrame, cfg: CollectionConfig = CollectionConfig()) -> Collected:
    """Pass the reports through the collection queue of ``cfg`` (module docstring)."""
    run = pl.col("run") if "run" in reports.columns else pl.lit(0, pl.UInt32)
    work = reports.with_columns(run.alias("__run")).with_columns(_arrival_seconds(reports).alias("__t")).sort(
        "__run", "__t", maintain_order=True)
    n = work.height
    runs = work["__run"].to_numpy()
    seg = np.flatnonzero(np.r_[True, runs[1:] != runs[:-1]]) if n else np.zeros(0, np.int64)
    t = work["__t"].to_numpy()
    if n and not np.isfinite(t).all():
        raise ValueError("collection: arrival times must be finite")
    rng = np.random.default_rng(cfg.seed)
    service = (rng.exponential(cfg.service_time_s, n) if cfg.service_model == "exponential"
               else np.full(n, cfg.service_time_s))
    wait, status = queue_kernel(t, service, seg, cfg.discipline, cfg.max_wait_s, cfg.servers, cfg.queue_places)
    work = work.with_columns(pl.Series("collection_wait_s", wait).fill_nan(None),
                             pl.Series("__status", status), pl.Series("__service", service))
    acc = work.filter(pl.col("__status") == ACCEPTED).with_columns(
        (pl.col("collection_wait_s") + pl.col("__service")).alias("collection_delay_s"))
    reasons = _reasons(cfg)
    lost = work.filter(pl.col("__status") != ACCEPTED).select(
        "report_id" if "report_id" in work.columns else pl.lit(None, pl.UInt64).alias("report_id"),
        pl.col("__status").replace_strict(reasons, return_dtype=pl.String).alias("reason"),
        pl.col("__t").alias("arrival_s"))
    stats = work.group_by("__run", maintain_order=True).agg(
        pl.len().alias("offered"),
        (pl.col("__status") == ACCEPTED).sum().alias("accepted"),
        (pl.col("__status") == LOST_BUSY).sum().alias("lost_refused"),
        (pl.col("__status") == LOST_WAIT).sum().alias("lost_wait"),
        (pl.col("__status") == LOST_BUFFER).sum().alias("lost_buffer"),
        pl.col("collection_wait_s").mean().alias("mean_wait_s"),
        pl.col("collection_wait_s").max().alias("max_wait_s"),
        (pl.col("collection_wait_s") + pl.col("__service")).mean().alias("mean_delay_s"),
    ).rename({"__run": "run"}).with_columns((1.0 - pl.col("accepted") / pl.col("offered")).alias("loss_share"))
    return Collected(acc.drop("__run", "__t", "__status", "__service"), lost, stats)


def collection_stage(reports: pl.DataFrame, report_rows: pl.DataFrame, cfg: CollectionConfig
                     ) -> tuple[pl.DataFrame, pl.DataFrame, list[str]]:
    """The pipeline step: (accepted reports with the input columns and ``collection_delay_s``
    (waiting + processing: alignment uses a report from time + delay on), in input order; the lost
    ones as ``rejects`` rows, stage ``"collection"``, ``row_index`` from ``report_rows``; notes
    with the counts). ``report_rows``: report_id → row_index of the input table."""
    got = collect(reports, cfg)
    keep = reports.drop("collection_delay_s", strict=False).join(
        got.accepted.select("report_id", "collection_delay_s"), on="report_id", how="inner", maintain_order="left")
    lost = (reports.join(report_rows, on="report_id", how="inner")
            .join(got.lost.select("report_id", "reason"), on="report_id", how="inner").sort(schema.ROW_INDEX))
    rejects = (schema.rejects_table(lost, "reports", "collection") if lost.height
               else schema.empty_frame("rejects", False))
    s = got.stats.select(pl.col("offered", "accepted", "lost_refused", "lost_wait", "lost_buffer").sum(),
                         pl.col("mean_wait_s").mean(), pl.col("max_wait_s").max(), pl.col("mean_delay_s").mean())
    row = s.row(0, named=True) if s.height else {}
    note = (f"collection ({cfg.discipline}, {cfg.service_model} processing {cfg.service_time_s:g} s, "
            f"{cfg.servers} processor(s)" + (f", T_wait {cfg.max_wait_s:g} s" if cfg.discipline == "limited" else "")
            + f"): {row.get('offered', 0):,} reports offered, {row.get('accepted', 0):,} accepted, "
            f"lost {row.get('lost_refused', 0):,} refused + {row.get('lost_wait', 0):,} over T_wait + "
            f"{row.get('lost_buffer', 0):,} buffer full; mean wait {row.get('mean_wait_s') or 0.0:.4g} s, "
            f"max {row.get('max_wait_s') or 0.0:.4g} s, mean delay {row.get('mean_delay_s') or 0.0:.4g} s")
    return keep, rejects, [note]
