"""The seed metrics stepped window by window (:mod:`tertiary.evaluation.accuracy_streamed`) are
those of picture_accuracy on the whole picture: the same metrics rows, per-epoch accuracy and
scored samples, however the epochs are cut into windows and whichever pictures a window has."""

from __future__ import annotations

from datetime import timedelta

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from test_accuracy_buckets import CFGS, T0, _hand_picture
from tertiary.evaluation.accuracy import AccuracyConfig, picture_accuracy, row_scores, scored_samples
from tertiary.evaluation.accuracy_streamed import (EPOCH_SUMS, SeedState, Walk, seed_rows, seed_step, seed_tables,
                                                   statistic_lags, walk_step, with_epoch_sums)

pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered in det:RuntimeWarning")


def _stepped(matched: pl.DataFrame, observed: pl.DataFrame, cfg: AccuracyConfig, cuts: list[int]
             ) -> tuple[SeedState, Walk, pl.DataFrame]:
    """The state and walk after the windows cut at epoch indices ``cuts`` with the per-epoch
    sums the windows wrote, and the scored rows. The carried state never holds per-epoch sums."""
    edges = [T0 - timedelta(seconds=1), *(T0 + timedelta(seconds=4 * k) for k in cuts), T0 + timedelta(days=1)]
    rows = seed_rows(row_scores(matched), "track_id")
    state, walk, scored, written = SeedState(), Walk(), [], {}
    for a, b in zip(edges[:-1], edges[1:]):
        walk_rows, walk = walk_step(walk, observed.filter(pl.col("epoch").is_between(a, b, closed="left")))
        window = rows.filter(pl.col("epoch").is_between(a, b, closed="left"))
        if window.height:
            out, epochs, state = seed_step(state, window, walk_rows, walk, cfg)
            assert not set(EPOCH_SUMS) & set(state.sums.tables) and set(epochs) <= set(EPOCH_SUMS.values())
            for table, frame in epochs.items():
                written.setdefault(table, []).append(frame)
            scored.append(out)
    state = with_epoch_sums(state, lambda t: pl.concat(written[t]) if t in written else None)
    return state, walk, pl.concat(scored)


def _finished(state: SeedState, walk: Walk, scored: pl.DataFrame, method: str, cfg: AccuracyConfig
              ) -> tuple[pl.DataFrame, ...]:
    lags = statistic_lags(scored.lazy(), scored.height)
    metrics, by_epoch = seed_tables(state, walk, "tracker", cfg, lags)
    metrics, by_epoch = (t.filter(pl.col("method") == method) for t in (metrics, by_epoch))
    return metrics, by_epoch, scored_samples(scored.filter(pl.col("method") == method))


def _assert_same(got: tuple[pl.DataFrame, ...], want: tuple[pl.DataFrame, ...]) -> None:
    """Metrics and per-epoch accuracy in order; the samples in window order, the picture's in
    its rows' (the same rows: a sum over them is what reads them)."""
    for g, w in zip(got[:2], want[:2], strict=True):
        assert_frame_equal(g, w, check_exact=False, rel_tol=1e-9, abs_tol=1e-12)
    def rows(f: pl.DataFrame) -> pl.DataFrame:
        return f.with_columns(pl.col("method", "seg_class").cast(pl.String)).sort(pl.all(), nulls_last=True)
    assert_frame_equal(rows(got[2]), rows(want[2]))


@pytest.mark.parametrize("cov", ["cov", "cov_diag", "none"])
@pytest.mark.parametrize("cuts", [[], [1], [5, 6, 20], list(range(1, 36, 3)), list(range(1, 40))],
                         ids=["one", "first-epoch", "uneven", "every-3", "every-epoch"])
def test_windows_equal_the_whole_picture(cov, cuts):
    """Two pictures and two runs stepped together: swaps, spurious tracks, breaks across
    windows, thin (pooled) epochs, straight/turn segments, an aircraft matched before its first
    report, the transient cut in a later window than the track's first epoch."""
    matched, observed = _hand_picture(3, cov)
    for cfg in CFGS:
        state, walk, scored = _stepped(matched, observed, cfg, cuts)
        for method in ("a", "b"):
            want = picture_accuracy(matched.filter(pl.col("method") == method), "tracker", cfg, observed)
            _assert_same(_finished(state, walk, scored, method, cfg), want)
            names = set(want[0]["metric"])
            assert {"completeness", "breaks", "swaps", "spurious_tracks", "nis_band_lo"} <= names
            assert ("potential_pos_m" in names) == (cov != "none")


def test_a_picture_absent_from_early_windows_walks_them_uncovered():
    """A picture whose first row comes late: the aircraft-epochs the windows before it walked
    count in its completeness (and a gap across windows is a break)."""
    matched, observed = _hand_picture(8, "cov_diag", methods=("a", "b"), runs=(0,))
    late = matched.filter((pl.col("method") == "a") | (pl.col("epoch") >= T0 + timedelta(seconds=4 * 12)))
    cfg = AccuracyConfig()
    state, walk, scored = _stepped(late, observed, cfg, [4, 8, 12, 16, 25])
    for method in ("a", "b"):
        want = picture_accuracy(late.filter(pl.col("method") == method), "tracker", cfg, observed)
        _assert_same(_finished(state, walk, scored, method, cfg), want)
    b = want[0].filter(pl.col("metric") == "completeness")["value"][0]
    assert 0 < b < 0.7


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_random_windows(seed):
    rng = np.random.default_rng(seed)
    matched, observed = _hand_picture(seed, ["cov", "cov_diag", "none"][seed % 3])
    cuts = sorted(set(rng.integers(1, 36, int(rng.integers(1, 12))).tolist()))
    cfg = CFGS[seed % len(CFGS)]
    state, walk, scored = _stepped(matched, observed, cfg, cuts)
    for method in ("a", "b"):
        want = picture_accuracy(matched.filter(pl.col("method") == method), "tracker", cfg, observed)
        _assert_same(_finished(state, walk, scored, method, cfg), want)


@pytest.mark.parametrize("bucket_rows", [50, 211])
def test_lag_sums_read_in_buckets_of_tracks_equal_one_read(monkeypatch, bucket_rows):
    """Scored rows beyond one bucket: τ from the per-lag sums of buckets of whole tracks is the
    whole picture's."""
    from tertiary.evaluation import accuracy_streamed
    matched, observed = _hand_picture(9, "cov")
    cfg = AccuracyConfig()
    state, walk, scored = _stepped(matched, observed, cfg, [7, 19, 30])
    monkeypatch.setattr(accuracy_streamed, "LAG_BUCKET_ROWS", bucket_rows)
    assert scored.height > 2 * bucket_rows
    for method in ("a", "b"):
        want = picture_accuracy(matched.filter(pl.col("method") == method), "tracker", cfg, observed)
        _assert_same(_finished(state, walk, scored, method, cfg), want)
