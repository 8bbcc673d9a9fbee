"""Alert confirmation: an STCA alert is shown only when the conflict condition has held on
``m`` of the pair's last ``n`` picture epochs (the epoch itself included).

A real STCA does not alert on one cycle's prediction: one noisy velocity estimate at a track's
start, or one cycle of a turn extrapolated as a straight line, would otherwise raise an alert
that is gone four seconds later. Confirmation costs at most (m − 1) update intervals of
warning time.

The state is explicit so that a streaming engine carries it from one window to the next:
:class:`ConfirmState` holds, for every pair that raised the condition in the last ``n``
epochs, the bit history of the condition (bit 0 = the latest epoch). :func:`confirm_step`
advances it by one picture epoch; :func:`confirm_alerts` is the same rule over a whole
``conflicts`` table at once (vectorised), and a test checks that the two agree.

Rule at epoch k of the picture's epoch grid (the epochs at which the picture has a track, per
(run, method)): ``alert_k = raw_k ∧ #{raw_j : k − n < j ≤ k} ≥ m``. A pair absent from the
conflict rows at an epoch did not raise the condition there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import NDArray

__all__ = ["ConfirmState", "confirm_step", "confirm_alerts", "epoch_index"]

_PAIR = ["run", "method", "id_a", "id_b"]


@dataclass(frozen=True)
class ConfirmState:
    """Condition history of the pairs seen in the last ``n`` epochs: ``pairs`` (run, method,
    id_a, id_b) and ``bits`` (UInt64; bit 0 = the latest epoch processed)."""

    pairs: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(
        schema={"run": pl.UInt32, "method": pl.String, "id_a": pl.UInt64, "id_b": pl.UInt64, "bits": pl.UInt64}))


def _popcount(x: NDArray[np.uint64]) -> NDArray[np.int64]:
    return np.unpackbits(x.astype("<u8").view(np.uint8).reshape(-1, 8), axis=1).sum(axis=1).astype(np.int64)


def confirm_step(state: ConfirmState, raw: pl.DataFrame, m: int, n: int) -> tuple[ConfirmState, pl.Series]:
    """One picture epoch: ``raw`` holds this epoch's (run, method, id_a, id_b, raw_alert) rows
    (every pair evaluated, or only those raising the condition). Returns the new state and
    the confirmed alert flag of each ``raw`` row, in ``raw``'s order."""
    if not 1 <= m <= n <= 63:
        raise ValueError(f"confirmation needs 1 <= m <= n <= 63, got m={m}, n={n}")
    window = np.uint64((1 << n) - 1)
    prev = state.pairs.with_columns((pl.col("bits") * 2) & pl.lit(window, pl.UInt64))   # shift one epoch
    now = raw.select(*_PAIR, pl.col("raw_alert").cast(pl.UInt64).alias("__new"))
    joined = now.join(prev, on=_PAIR, how="left").with_columns(pl.col("bits").fill_null(0) | pl.col("__new"))
    bits = joined["bits"].to_numpy()
    confirmed = (joined["__new"].to_numpy() == 1) & (_popcount(bits) >= m)
    carried = prev.join(now, on=_PAIR, how="anti")
    pairs = (pl.concat([carried, joined.select(*_PAIR, "bits")], how="vertical_relaxed")
             .filter(pl.col("bits") != 0))
    return ConfirmState(pairs), pl.Series("alert", confirmed)


def epoch_index(picture: pl.DataFrame, method_col: str = "method") -> pl.DataFrame:
    """(run, method, epoch, epoch_k): the rank of each epoch in its picture's epoch grid."""
    return (picture.select(pl.col("run").cast(pl.UInt32), pl.col(method_col).cast(pl.String).alias("method"), "epoch")
            .unique().sort("run", "method", "epoch")
            .with_columns(pl.int_range(pl.len()).over("run", "method").cast(pl.Int64).alias("epoch_k")))


def confirm_alerts(conflicts: pl.DataFrame, grid: pl.DataFrame, m: int, n: int) -> pl.DataFrame:
    """``conflicts`` with ``alert`` replaced by the confirmed alert and the unconfirmed
    condition kept as ``raw_alert``; ``grid`` is :func:`epoch_index` of the picture. m = n = 1
    leaves the alerts as they are."""
    if not 1 <= m <= n <= 63:
        raise ValueError(f"confirmation needs 1 <= m <= n <= 63, got m={m}, n={n}")
    out = conflicts.with_columns(pl.col("alert").alias("raw_alert"))
    if m == 1 or out.height == 0:
        return out
    k = out.join(grid, on=["run", "method", "epoch"], how="left")["epoch_k"]
    if k.null_count():
        raise ValueError("conflicts: an epoch is missing from the picture's epoch grid")
    raw = out["raw_alert"].to_numpy()
    idx = np.flatnonzero(raw)
    sub = out[idx].select(pl.struct(_PAIR).rank("dense").cast(pl.Int64).alias("p"))["p"].to_numpy()
    kk = k.to_numpy()[idx].astype(np.int64)
    span = int(kk.max()) + n + 1 if len(kk) else 1
    key = sub * span + kk                     # pairs are disjoint blocks of width span > any window
    order = np.argsort(key, kind="stable")
    ks = key[order]
    count = np.empty(len(ks), np.int64)
    count[order] = np.arange(len(ks)) - np.searchsorted(ks, ks - n, side="right") + 1
    alert = np.zeros(out.height, bool)
    alert[idx] = count >= m
    return out.with_columns(pl.Series("alert", alert))
