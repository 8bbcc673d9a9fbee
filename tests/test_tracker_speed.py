"""The fast tracker paths give the results of the plain ones.

* ``track_methods`` folds (method, run) into the batch axis (one epoch loop per filter over every
  method's picture). Oracle: the unfolded path — :func:`track` per method, one filter object
  each, concatenated method-major — which is the tracker loop as it was. Expected: identical
  rows, bit for bit where the filter is the same code (``singer``).
* ``imm`` / ``imm_sym`` predict, update and output with compiled per-track kernels. Oracle: the numpy path
  (``compiled=False``). Expected: equal to round-off, ≤ 1e-9 relative to each column's scale.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary import pipeline
from tertiary.filters import make_filter
from tertiary.simulate import load_scenario, simulate
from tertiary.stages.tracking.tracker import track, track_methods

REL = 1e-9


@pytest.fixture(scope="module")
def pictures() -> pl.DataFrame:
    """Every fusion method's picture of a small terminal area, 2 Monte-Carlo runs."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, runs=2,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=20))
    res = pipeline.process(simulate(cfg), pipeline.PipelineConfig(filters=(), safety=False, centralized=False))
    fused = res.fused.filter(pl.col("method") != "centralized")
    assert fused["method"].n_unique() >= 5 and fused["run"].n_unique() == 2
    return fused


def _unfolded(fused: pl.DataFrame, name: str, **params) -> pl.DataFrame:
    """The per-(method, filter) loop the folded path replaces."""
    parts = [track(fused.filter(pl.col("method") == m), make_filter(name, **params))
             for m in sorted(fused["method"].unique().to_list())]
    return pl.concat(parts, how="vertical")


def _floats(s: pl.Series) -> np.ndarray:
    if isinstance(s.dtype, pl.List):
        s = s.explode()
    elif isinstance(s.dtype, pl.Array):
        s = s.arr.explode()
    return s.cast(pl.Float64).to_numpy()


def _is_float(s: pl.Series) -> bool:
    inner = s.dtype.inner if isinstance(s.dtype, (pl.List, pl.Array)) else s.dtype
    return inner.is_float()


def _max_rel(new: pl.DataFrame, ref: pl.DataFrame) -> float:
    """Largest |new − ref| / (|ref| + scale of the column) over the float columns (round-off
    of a near-zero entry is measured against the column's magnitude, e.g. an innovation of
    1e-4 m computed from positions of 1e4 m); every other column must be equal."""
    assert new.columns == ref.columns and new.height == ref.height
    worst = 0.0
    for c in new.columns:
        a, b = new[c], ref[c]
        if not _is_float(b):
            assert a.equals(b), c
            continue
        x, y = _floats(a), _floats(b)
        assert np.array_equal(np.isnan(x), np.isnan(y)), c
        ok = ~np.isnan(y)
        if ok.any():
            scale = np.sqrt(np.mean(y[ok] ** 2))
            worst = max(worst, float((np.abs(x[ok] - y[ok]) / (np.abs(y[ok]) + scale)).max()))
    return worst


def test_folded_singer_is_bit_identical_to_the_per_method_loop(pictures):
    new = track_methods(pictures, ["singer"])
    ref = _unfolded(pictures, "singer")
    assert new.height > 1000
    assert new.equals(ref)


def test_folded_compiled_imm_sym_equals_the_per_method_numpy_loop(pictures):
    new = track_methods(pictures, ["imm_sym"])
    ref = _unfolded(pictures, "imm_sym", compiled=False)
    assert new.height > 1000
    assert _max_rel(new, ref) <= REL


def test_track_ids_stay_per_method_and_run(pictures):
    """The same picture under two method names: both get the tracks (and ids 1, 2, …) of the
    picture tracked alone — folded batch runs never take each other's plots."""
    one = pictures.filter(pl.col("method") == "information")
    twin = pl.concat([one, one.with_columns(pl.lit("zz_twin").alias("method"))])
    out = track_methods(twin, ["singer"])
    alone = track(one, make_filter("singer"))
    a = out.filter(pl.col("method") == "information")
    b = out.filter(pl.col("method") == "zz_twin").with_columns(pl.lit("information").alias("method"))
    assert a.equals(alone) and b.equals(alone)
    first = alone.group_by("run").agg(pl.col("track_id").min())["track_id"].to_list()
    assert first == [1, 1]


@pytest.mark.parametrize("name", ["imm", "imm_sym"])
def test_compiled_imm_prediction_matches_numpy(name):
    rng = np.random.default_rng(7)
    fast, slow = make_filter(name), make_filter(name, compiled=False)
    n = 300
    z = rng.normal(0, 3e4, (n, 3))
    r = rng.uniform(30, 300, (n, 3)) ** 2
    state = fast.init(z, r)
    for k in range(6):
        dt = rng.uniform(0.0, 12.0, n)
        dt[:10] = 0.0                                  # ω·dt = 0: the series branch
        dt[10:20] = 400.0                              # long gaps: |ω·dt| ≫ 0.5
        state, _ = fast.update(fast.predict(state, dt), z + rng.normal(0, 100, (n, 3)) + 300.0 * k, r,
                               rng.random(n) < 0.8)
        a, b = fast.predict(state, dt), slow.predict(state, dt)
        for key in b:
            scale = np.abs(b[key]).max(axis=tuple(range(1, b[key].ndim)), keepdims=True) + 1e-300
            assert np.all(np.abs(a[key] - b[key]) <= REL * scale), (key, k)


@pytest.mark.parametrize("name", ["imm", "imm_sym"])
def test_compiled_imm_update_matches_numpy(name):
    """Full R with an E–N correlation, plots missing (mask) and invalid (NaN)."""
    rng = np.random.default_rng(3)
    fast, slow = make_filter(name), make_filter(name, compiled=False)
    n = 300
    z = rng.normal(0, 3e4, (n, 3))
    var = rng.uniform(30, 300, (n, 3)) ** 2
    r = np.zeros((n, 3, 3))
    r[:, [0, 1, 2], [0, 1, 2]] = var
    r[:, 0, 1] = r[:, 1, 0] = 0.4 * np.sqrt(var[:, 0] * var[:, 1])
    state = slow.init(z, r)
    for k in range(6):
        pred = slow.predict(state, rng.uniform(0.5, 12.0, n))
        zk = z + rng.normal(0, 100, (n, 3)) + 300.0 * k
        zk[:5] = np.nan
        mask = rng.random(n) < 0.8
        (a, ia), (b, ib) = fast.update(pred, zk, r, mask), slow.update(pred, zk, r, mask)
        for key in b:
            scale = np.abs(b[key]).max(axis=tuple(range(1, b[key].ndim)), keepdims=True) + 1e-300
            assert np.all(np.abs(a[key] - b[key]) <= REL * scale), (key, k)
        for f in ("nu", "s", "nis"):
            x, y = getattr(ia, f), getattr(ib, f)
            assert np.array_equal(np.isnan(x), np.isnan(y)), f
            ok = ~np.isnan(y)
            assert np.all(np.abs(x[ok] - y[ok]) <= REL * (np.abs(y[ok]) + np.abs(y[ok]).max())), f
        state = b


@pytest.mark.parametrize("name", ["imm", "imm_sym"])
def test_compiled_imm_velocity_update_matches_numpy(name):
    """A downlinked ground velocity of correlated R, velocities missing (mask), invalid (NaN)
    and of invalid covariance (NaN)."""
    rng = np.random.default_rng(5)
    fast, slow = make_filter(name), make_filter(name, compiled=False)
    n = 300
    z = rng.normal(0, 3e4, (n, 3))
    state = slow.init(z, np.full((n, 3), 1e4))
    for k in range(6):
        pred = slow.predict(state, rng.uniform(0.5, 12.0, n))
        v = rng.normal(0, 150, (n, 2))
        sd = rng.uniform(0.3, 3.0, (n, 2))
        r = np.einsum("bi,bj->bij", sd, sd) * np.array([[1.0, 0.3], [0.3, 1.0]])
        v[:5] = np.nan
        r[5:9, 0, 0] = np.nan
        mask = rng.random(n) < 0.8
        a, b = fast.observe_velocity(pred, v, r, mask), slow.observe_velocity(pred, v, r, mask)
        assert not np.array_equal(b["x"], pred["x"])
        for key in b:
            scale = np.abs(b[key]).max(axis=tuple(range(1, b[key].ndim)), keepdims=True) + 1e-300
            assert np.all(np.abs(a[key] - b[key]) <= REL * scale), (key, k)
        state = b


@pytest.mark.parametrize("name", ["imm", "imm_sym"])
def test_compiled_imm_output_matches_numpy(name):
    """The combined estimate and its 6 × 6 covariance (horizontal block moment-matched, vertical
    channel beside it, no cross terms between them), from states whose models disagree."""
    rng = np.random.default_rng(11)
    fast, slow = make_filter(name), make_filter(name, compiled=False)
    assert fast.compiled and not slow.compiled
    n = 300
    z = rng.normal(0, 3e4, (n, 3))
    r = rng.uniform(30, 300, (n, 3)) ** 2
    state = slow.init(z, r)
    for k in range(6):
        pred = slow.predict(state, rng.uniform(0.5, 12.0, n))
        state, _ = slow.update(pred, z + rng.normal(0, 300, (n, 3)) + 900.0 * k, r, rng.random(n) < 0.8)
        a, b = fast.output(state), slow.output(state)
        assert np.ptp(state["x"][:, :, 1], axis=1).max() > 1.0      # the models' spread enters P
        for f in ("x", "var", "probs", "cov"):
            u, v = getattr(a, f), getattr(b, f)
            scale = np.abs(v).max(axis=tuple(range(1, v.ndim)), keepdims=True) + 1e-300
            assert u.shape == v.shape and np.all(np.abs(u - v) <= REL * scale), (f, k)
    assert fast.output(slow.init(z[:0], r[:0])).cov.shape == (0, 6, 6)


def test_anisotropic_q_keeps_the_numpy_path():
    """The compiled kernel has the isotropic closed form only; (q_x ≠ q_y) must not use it."""
    filt = make_filter("imm", q=(1.0, 4.0))
    ref = make_filter("imm", q=(1.0, 4.0), compiled=False)
    z, r = np.array([[1e4, 2e4, 3e3]]), np.full((1, 3), 1e4)
    s = filt.init(z, r)
    a, b = filt.predict(s, np.array([5.0])), ref.predict(s, np.array([5.0]))
    for key in b:
        assert np.array_equal(a[key], b[key])
    (ua, ia), (ub, ib) = (f.update(b, np.array([[1.1e4, 2e4, 3e3]]), r, np.ones(1, bool)) for f in (filt, ref))
    for key in ub:
        assert np.array_equal(ua[key], ub[key])
