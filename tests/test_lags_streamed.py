"""τ's lag sums made as the windows pass (:mod:`tertiary.evaluation.lags_streamed`) against the
end of the run's over every scored row (:func:`tertiary.evaluation.accuracy_streamed.statistic_lags`)."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.core.stage import T_MAX_US, Window
from tertiary.core.units import US
from tertiary.evaluation import lags_streamed as ls
from tertiary.evaluation.accuracy_streamed import SCORED_ROWS, statistic_lags

T0 = int(datetime(2021, 10, 7, 12, tzinfo=timezone.utc).timestamp() * US)


def _scored(seed: int = 5) -> pl.DataFrame:
    """Two pictures' scored rows every 4 s over 20 min: tracks that start and end at random
    times, AR(1) statistics (correlated along each track, so τ > 1), two segment classes."""
    rng = np.random.default_rng(seed)
    rows = []
    for method in ("a", "b+imm_sym"):
        for track in range(40):
            start = int(rng.integers(0, 250))
            n = int(rng.integers(5, 300 - start))
            x = np.empty(n)
            x[0] = rng.chisquare(3)
            for k in range(1, n):
                x[k] = 0.8 * x[k - 1] + 0.2 * rng.chisquare(3)
            t = T0 + (start + np.arange(n)) * 4 * US
            rows.append(pl.DataFrame({"method": method, "run": 0, "epoch": pl.Series(t).cast(pl.Datetime("us", "UTC")),
                                      "truth_id": track % 7, "track_id": track, "seg_class": np.where(
                                          np.arange(n) % 9 < 6, "straight", "turn"),
                                      "nees_pos": x, "nees": 2 * x, "nis": x + 1.0}))
    frame = pl.concat(rows)
    return frame.select(pl.col(c).cast(t) if c in frame.columns else pl.lit(None, t).alias(c)
                        for c, t in SCORED_ROWS.items()).sort("epoch")


def _windows(scored: pl.DataFrame, window_s: float, tmp_path) -> tuple[ls.LagState, list]:
    """lags_step over windows of ``window_s``, each window's rows stored as a part after it."""
    state, files = ls.LagState(), []
    us = pl.col("epoch").dt.epoch("us")
    end = int(scored["epoch"].dt.epoch("us").max()) + 1
    for k, a in enumerate(range(T0, end, int(window_s * US))):
        b = a + int(window_s * US)
        w = Window(k, a, b if b < end else T_MAX_US)
        rows = scored.filter(us.is_between(a, w.t1_us, closed="left"))
        state = ls.lags_step(state, rows, w, lambda: list(files))
        f = tmp_path / f"w={k:06d}.parquet"
        rows.write_parquet(f)
        files.append(f)
    return state, files


@pytest.mark.parametrize("window_s", [30.0, 97.0])
def test_lag_sums_made_in_the_windows_give_the_whole_runs_tau(window_s, tmp_path, monkeypatch):
    """Series retired 120 s after their last scored row, 10 at least at a time, the rest in the
    last window: τ of every statistic, picture and segment equals that of every row at once.
    Fails if a retired series' rows are read from the current window only, or a series is
    retired while still scored."""
    monkeypatch.setattr(ls, "SERIES_BATCH", 10)
    monkeypatch.setattr(ls, "SERIES_DONE_S", 120.0)
    scored = _scored()
    batches: list[int] = []
    monkeypatch.setattr(ls, "_summed", lambda state, due, *a, f=ls._summed: batches.append(due.height)
                        or f(state, due, *a))
    state, _ = _windows(scored, window_s, tmp_path)
    assert state.complete and len(batches) > 2 and state.open.height == 0
    whole = statistic_lags(scored.lazy(), scored.height)
    assert set(state.sums.lags) == set(whole)
    for key, lags in whole.items():
        assert state.sums.lags[key].tau() == pytest.approx(lags.tau(), rel=1e-9), key
        assert state.sums.lags[key].n == lags.n


def test_a_series_scored_again_after_it_was_retired_hands_the_sums_to_the_end(tmp_path, monkeypatch):
    """A track unscored for longer than SERIES_DONE_S and then scored again: its sums would miss
    the lags across the gap, so the state is no longer complete (the end sums every series)."""
    monkeypatch.setattr(ls, "SERIES_BATCH", 1)
    monkeypatch.setattr(ls, "SERIES_DONE_S", 60.0)
    scored = _scored()
    one = scored.filter((pl.col("method") == "a") & (pl.col("track_id") == 3))
    gap = one.with_columns(pl.col("epoch") + pl.duration(seconds=3600))       # the same track an hour on
    state, _ = _windows(pl.concat([scored, gap]).sort("epoch"), 60.0, tmp_path)
    assert not state.complete
