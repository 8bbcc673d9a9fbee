"""Conflict prediction as a step function of the windowed engine:
concatenated window outputs equal the whole-run ``predict_conflicts`` (full and slim), whatever
the cut; the carried state is what makes them equal; empty windows leave the state alone; the
input state is never mutated."""

from __future__ import annotations

import dataclasses
from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from safety.conflicts import (STCA_CONFIRMATION, ApproachVolume, ConflictConfig, ConflictState, conflicts_step,
                              conflicts_steps, init_conflict_state,
                              predict_conflicts, slim_conflicts)
from tertiary.pipeline import PipelineConfig, process

KEYS = ["run", "epoch", "method", "id_a", "id_b"]
US = 1_000_000
PIPELINE_CFG = ConflictConfig(confirm_m=STCA_CONFIRMATION[0], confirm_n=STCA_CONFIRMATION[1])
CONFIGS = {
    "pipeline": PIPELINE_CFG,                                       # corrected rule, 3 of 4, coast 10 s
    "seed_2of5": ConflictConfig(mode="seed", confirm_m=2, confirm_n=5, max_coast_s=6.0),
    # the pipeline's rule with the scenario's final-approach volume (runway 27)
    "final_volume": ConflictConfig(confirm_m=STCA_CONFIRMATION[0], confirm_n=STCA_CONFIRMATION[1],
                                   approach_volumes=(ApproachVolume(1500.0, 0.0, 270.0, length_m=38_500.0),)),
}


@pytest.fixture(scope="module")
def scenario(small_terminal):
    """Tracker pictures ("<method>+<filter>", ``track_id``) and the fused picture (``target_id``)
    of the 30-aircraft terminal-area fixture, with the slowest radar scan period."""
    ds = small_terminal
    res = process(ds, PipelineConfig(evaluation=False, methods=("arithmetic", "information"), filters=("singer",),
                                     stca_lookaheads_s=()))
    tracks = res.tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method"))
    fused = res.fused.filter(pl.col("method") != "centralized")
    if "tentative" in fused.columns:
        fused = fused.filter(~pl.col("tentative").fill_null(False))
    return {"tracks": tracks, "fused": fused, "origin": ds.origin,
            "slowest_scan_s": float(ds.radars["scan_period_s"].max())}


def _epochs_us(pic: pl.DataFrame) -> np.ndarray:
    return pic["epoch"].dt.epoch("us").to_numpy()


def _grid_bounds(pic: pl.DataFrame, width_s: float) -> list[int]:
    """Window edges on an absolute grid (origin: a whole minute before the first epoch)."""
    e = _epochs_us(pic)
    origin = (int(e.min()) // (60 * US) - 1) * 60 * US
    w = int(width_s * US)
    return list(range(origin, int(e.max()) + w + 1, w))


def _irregular_bounds(pic: pl.DataFrame, seed: int = 7) -> list[int]:
    """Random edges (some at an epoch exactly, some between epochs) plus one window that holds
    no row (1 ms just after an epoch; epochs are ≥ 1 s apart)."""
    e = np.unique(_epochs_us(pic))
    rng = np.random.default_rng(seed)
    cuts = set(rng.choice(e[1:-1], 6, replace=False).tolist())                 # at epochs
    cuts |= set((rng.choice(e[1:-1], 6, replace=False) + 1_700_000).tolist())  # between epochs
    k = int(e[len(e) // 2])
    cuts |= {k + 1, k + 1001}                                                  # [k+1 µs, k+1 ms): empty
    return [int(e.min()) - 1] + sorted(cuts) + [int(e.max()) + 1]


def _cuts(pic: pl.DataFrame, slowest_scan_s: float) -> dict[str, list[int]]:
    short = 3.0
    assert short < slowest_scan_s
    return {"60s": _grid_bounds(pic, 60.0), "3s_below_scan": _grid_bounds(pic, short),
            "irregular_with_empty": _irregular_bounds(pic)}


def _windows(pic: pl.DataFrame, bounds: list[int]):
    e = pic["epoch"].dt.epoch("us")
    for t0, t1 in zip(bounds[:-1], bounds[1:]):
        yield pic.filter((e >= t0) & (e < t1)), t0, t1


def _run(pic, bounds, cfg, id_col, frame, slim, reset=None):
    """Concatenated step outputs over the windows; ``reset(state) -> state`` breaks the carry."""
    state, outs, n_empty = init_conflict_state(), [], 0
    for w, t0, t1 in _windows(pic, bounds):
        n_empty += w.height == 0
        if reset is not None and outs:
            state = reset(state)
        out, state = conflicts_step(state, w, cfg, id_col, frame, t0, t1, slim=slim)
        assert out.height == 0 or bool(out["epoch"].dt.epoch("us").is_between(t0, t1 - 1).all())
        outs.append(out)
    return pl.concat(outs).sort(KEYS), n_empty


def _assert_same(a: pl.DataFrame, b: pl.DataFrame) -> None:
    assert_frame_equal(a.sort(KEYS), b.sort(KEYS), check_exact=False, rel_tol=1e-9, abs_tol=1e-9)


@pytest.mark.parametrize("cfg_name", list(CONFIGS))
@pytest.mark.parametrize("cut", ["60s", "3s_below_scan", "irregular_with_empty"])
def test_windows_equal_whole_run_tracks(scenario, cfg_name, cut):
    pic, frame, cfg = scenario["tracks"], scenario["origin"], CONFIGS[cfg_name]
    bounds = _cuts(pic, scenario["slowest_scan_s"])[cut]
    whole = predict_conflicts(pic, cfg, id_col="track_id", frame=frame)
    assert int(whole["alert"].sum()) > 0                 # the designed conflict pairs alert
    full, n_empty = _run(pic, bounds, cfg, "track_id", frame, slim=False)
    _assert_same(full, whole)
    slim, _ = _run(pic, bounds, cfg, "track_id", frame, slim=True)
    _assert_same(slim, slim_conflicts(whole))
    if cut != "60s":
        assert n_empty >= 1


def test_windows_equal_whole_run_fused_picture(scenario):
    pic, frame = scenario["fused"], scenario["origin"]
    whole = predict_conflicts(pic, PIPELINE_CFG, id_col="target_id", frame=frame)
    assert whole.height > 0
    for bounds in _cuts(pic, scenario["slowest_scan_s"]).values():
        full, _ = _run(pic, bounds, PIPELINE_CFG, "target_id", frame, slim=False)
        _assert_same(full, whole)


def test_whole_run_is_one_step(scenario):
    pic, frame = scenario["tracks"], scenario["origin"]
    out, state = conflicts_step(init_conflict_state(), pic, PIPELINE_CFG, "track_id", frame, slim=False)
    assert_frame_equal(out, predict_conflicts(pic, PIPELINE_CFG, frame=frame))
    step_slim, _ = conflicts_step(init_conflict_state(), pic, PIPELINE_CFG, "track_id", frame)
    assert_frame_equal(step_slim, slim_conflicts(out))


def _no_confirmation_carry(s: ConflictState) -> ConflictState:
    e = init_conflict_state()
    return ConflictState(e.grid, e.raw, s.last_update, s.t_us)


def _no_coast_carry(s: ConflictState) -> ConflictState:
    return ConflictState(s.grid, s.raw, init_conflict_state().last_update, s.t_us)


@pytest.mark.parametrize("reset", [lambda s: init_conflict_state(), _no_confirmation_carry, _no_coast_carry],
                         ids=["init_state", "confirmation", "coast_age"])
def test_each_carried_part_matters(scenario, reset):
    """Dropping any part of the state at the window edges changes the answer on 3 s windows:
    the equality tests above can fail, and both carries are exercised by the scenario. (With
    the velocity-sigma limit at 50 m/s: at the default 25 m/s this small scenario has no pair
    whose decision depends on a coast age carried across a 3 s edge.)"""
    pic, frame = scenario["tracks"], scenario["origin"]
    cfg = dataclasses.replace(PIPELINE_CFG, max_vel_sigma_mps=50.0)
    bounds = _cuts(pic, scenario["slowest_scan_s"])["3s_below_scan"]
    whole = predict_conflicts(pic, cfg, frame=frame)
    kept, _ = _run(pic, bounds, cfg, "track_id", frame, slim=False)
    _assert_same(kept, whole)
    broken, _ = _run(pic, bounds, cfg, "track_id", frame, slim=False, reset=reset)
    with pytest.raises(AssertionError):
        _assert_same(broken, whole)


def _state_after(pic, frame, cfg, t_end_s: float):
    e0 = int(_epochs_us(pic).min())
    t1 = e0 + int(t_end_s * US)
    w = pic.filter(pl.col("epoch").dt.epoch("us") < t1)
    _, state = conflicts_step(init_conflict_state(), w, cfg, "track_id", frame, e0, t1)
    return state, t1








def _assert_state_equal(a: ConflictState, b: ConflictState, same_time: bool = True) -> None:
    for name in ("grid", "raw", "last_update"):
        assert_frame_equal(getattr(a, name), getattr(b, name))
    if same_time:
        assert a.t_us == b.t_us


def _many_settings() -> list[ConflictConfig]:
    """Settings whose screens differ: no threshold margin to 2 400 m, covariance and fixed, two
    look-aheads, the final-approach volume; the last one screens and keeps rows on its own
    (bulk quantile, velocity-sigma limit)."""
    base = CONFIGS["final_volume"]
    out = []
    for margin in (base.t_margin_s, base.t_margin_s + 45.0):
        out += [dataclasses.replace(base, threshold_mode="covariance", confidence=c, t_margin_s=margin)
                for c in (0.5, 0.99)]
        out += [dataclasses.replace(base, threshold_mode="fixed", fixed_est_h_m=e, fixed_est_v_m=e / 6.0,
                                    t_margin_s=margin) for e in (0.0, 2400.0)]
    return out + [dataclasses.replace(base, bulk_quantile=0.5, max_vel_sigma_mps=50.0)]


def test_many_settings_in_one_step_equal_each_setting_alone(scenario):
    """``conflicts_steps`` shares the rows, their state and one union KD-tree screen between
    settings: window by window, each setting's rows and state equal its own ``conflicts_step``'s
    (a screen narrower than the widest setting's would lose that setting's distant pairs)."""
    pic, frame, cfgs = scenario["tracks"], scenario["origin"], _many_settings()
    shared = [init_conflict_state() for _ in cfgs]
    alone = [init_conflict_state() for _ in cfgs]
    rows = [0] * len(cfgs)
    for w, t0, t1 in _windows(pic, _cuts(pic, scenario["slowest_scan_s"])["60s"]):
        steps = conflicts_steps(shared, w, cfgs, "track_id", frame, t0, t1, slim=False)
        for k, cfg in enumerate(cfgs):
            out, alone[k] = conflicts_step(alone[k], w, cfg, "track_id", frame, t0, t1, slim=False)
            assert_frame_equal(steps[k][0], out)
            _assert_state_equal(steps[k][1], alone[k])
            rows[k] += out.height
        shared = [state for _, state in steps]
    assert rows[3] > 1.5 * rows[2] > 0          # 2 400 m keeps far more pairs than 0 m: the union matters


def test_the_scored_rows_alone_score_as_every_row(scenario):
    """``scored_only`` keeps the raw alerts and the first row of each picture epoch: window by
    window (the m-of-n confirmation carried across them) the alert scoring's rows
    (:func:`scored_conflicts`) and the states equal those of every row, with fewer rows. Fails
    if a raw alert that did not confirm, or an epoch's first row, is dropped."""
    from safety.alerts.episodes import scored_conflicts
    pic, frame, cfgs = scenario["tracks"], scenario["origin"], _many_settings()
    lean = [init_conflict_state() for _ in cfgs]
    full = [init_conflict_state() for _ in cfgs]
    n_lean = n_full = unconfirmed = 0
    for w, t0, t1 in _windows(pic, _cuts(pic, scenario["slowest_scan_s"])["60s"]):
        a = conflicts_steps(lean, w, cfgs, "track_id", frame, t0, t1, slim=False, scored_only=True)
        b = conflicts_steps(full, w, cfgs, "track_id", frame, t0, t1, slim=False)
        for (out_a, st_a), (out_b, st_b) in zip(a, b):
            assert_frame_equal(scored_conflicts(out_a), scored_conflicts(out_b))
            _assert_state_equal(st_a, st_b)
            n_lean, n_full = n_lean + out_a.height, n_full + out_b.height
            unconfirmed += out_b.filter(pl.col("raw_alert") & ~pl.col("alert")).height
        lean, full = [s for _, s in a], [s for _, s in b]
    assert unconfirmed > 0 and 0 < n_lean < 0.5 * n_full


def test_a_shared_screen_keeps_the_widest_settings_pairs():
    """Two hovering aircraft 9.1 km apart at one height: beyond the 0 m setting's reach (R_h +
    m_h = 7.9 km), within the 2 400 m one's (10.3 km). Screened together, the wide setting
    still keeps the pair — the shared screen is as wide as its widest setting, not its first."""
    narrow = ConflictConfig(threshold_mode="fixed", fixed_est_h_m=0.0, fixed_est_v_m=0.0)
    wide = dataclasses.replace(narrow, fixed_est_h_m=2400.0, fixed_est_v_m=400.0)
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    pic = pl.DataFrame({"track_id": [1, 2] * 3, "x_m": [0.0, 9100.0] * 3, "y_m": 0.0, "z_m": 3000.0, "vx_mps": 0.0,
                        "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": 3000.0, "alt_rate_mps": 0.0,
                        "s": [0, 0, 4, 4, 8, 8]}).select(
        (pl.lit(t0) + pl.duration(seconds=pl.col("s"))).alias("epoch"), pl.exclude("s"))
    alone = [predict_conflicts(pic, c, id_col="track_id") for c in (narrow, wide)]
    assert (alone[0].height, alone[1].height) == (0, 3)
    for order in ((narrow, wide), (wide, narrow)):
        steps = conflicts_steps([init_conflict_state()] * 2, pic, list(order), "track_id", slim=False)
        assert [out.height for out, _ in steps] == [0 if c is narrow else 3 for c in order]


def test_state_stays_small(scenario):
    """The state holds the last n − 1 picture epochs and tracks updated within max_coast_s."""
    pic, frame = scenario["tracks"], scenario["origin"]
    state, _ = _state_after(pic, frame, PIPELINE_CFG, 300.0)
    n_pictures = pic["method"].n_unique()
    assert state.grid.height == n_pictures * (PIPELINE_CFG.confirm_n - 1)
    assert state.raw.join(state.grid, on=["run", "method", "epoch_us"], how="anti").height == 0
    latest = int(state.grid["epoch_us"].max())
    assert ((latest - state.last_update["last_update_us"]) * 1e-6 <= PIPELINE_CFG.max_coast_s).all()


def test_a_window_before_the_state_end_is_refused(scenario):
    pic, frame = scenario["tracks"], scenario["origin"]
    state, t1 = _state_after(pic, frame, PIPELINE_CFG, 60.0)
    with pytest.raises(ValueError, match="starts before"):
        conflicts_step(state, pic.clear(), PIPELINE_CFG, "track_id", frame, t1 - US, t1 + US)
