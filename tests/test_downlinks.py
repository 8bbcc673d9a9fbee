"""The downlinked registers' noise measured from the replies (tertiary.stages.tracking.downlinks)."""

from __future__ import annotations

import dataclasses
import math
from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario
from tertiary.simulate.ehs import RESOLUTION, EhsConfig
from tertiary.stages.tracking.downlinks import MIN_TRIPLES, DownlinkNoise, downlink_noise, trimmed_sigma, with_noise

T0 = datetime(2021, 10, 7, 8, tzinfo=timezone.utc)


def _replies(sigma=(0.6, 0.25, 0.35), n_aircraft=40, scans=60, period_s=4.0, seed=1, drop=0.0) -> pl.DataFrame:
    """Two radars' replies from aircraft that accelerate, turn at a constant rate across north
    and climb at a constant rate: registers = the aircraft's values + N(0, σ) per reply; a
    fraction ``drop`` of the replies missed."""
    rng = np.random.default_rng(seed)
    rows = []
    for radar, phase in ((1, 0.0), (2, 1.7)):
        for a in range(n_aircraft):
            t = phase + period_s * np.arange(scans)
            speed = 150.0 + a + 0.4 * t                          # a steady acceleration
            track = (170.0 + (1.0 + 0.05 * a) * t + 180.0) % 360.0 - 180.0   # a turn through ±180°
            vrate = 5.0 + 0.2 * a + 0.05 * t                     # a steadily steepening climb
            noisy_track = (track + rng.normal(0, sigma[1], scans) + 180.0) % 360.0 - 180.0
            rows.append(pl.DataFrame({
                "radar_id": np.full(scans, radar), "mode_s": np.full(scans, 0x400000 + a),
                "time": pl.Series(np.round((T0.timestamp() + t) * 1e6).astype(np.int64)).cast(pl.Datetime("us", "UTC")),
                "ehs_gs_mps": speed + rng.normal(0, sigma[0], scans), "ehs_track_deg": noisy_track,
                "ehs_vrate_mps": vrate + rng.normal(0, sigma[2], scans)}))
    out = pl.concat(rows)
    out = out.filter(pl.Series(rng.random(out.height) >= drop))
    return out.sample(fraction=1.0, shuffle=True, seed=seed)     # in no particular order


def test_trimmed_sigma_recovers_the_sigma_of_white_errors_from_their_second_differences():
    e = np.random.default_rng(0).normal(0.0, 0.7, 200_000)
    d2 = e[2:] - 2 * e[1:-1] + e[:-2]
    assert trimmed_sigma(d2) == pytest.approx(0.7, rel=0.01)
    assert math.isnan(trimmed_sigma(np.array([np.nan])))


def test_the_noise_is_measured_through_accelerations_turns_across_north_and_climbs():
    noise = downlink_noise(_replies())
    assert noise.speed_mps == pytest.approx(0.6, rel=0.04)
    assert noise.track_deg == pytest.approx(0.25, rel=0.04)
    assert noise.vrate_mps == pytest.approx(0.35, rel=0.04)
    assert noise.triples["speed"] == 2 * 40 * 58
    # a missed reply leaves unequal intervals, over which a rate of change does not cancel
    gaps = downlink_noise(_replies(drop=0.3))
    assert gaps.speed_mps == pytest.approx(0.6, rel=0.05) and gaps.track_deg == pytest.approx(0.25, rel=0.05)


def test_a_register_missing_or_too_rarely_read_is_not_measured():
    few = _replies(n_aircraft=2, scans=20)
    assert 2 * 2 * 18 < MIN_TRIPLES
    assert downlink_noise(few) == DownlinkNoise(None, None, None, {"speed": 72, "track": 72, "vrate": 72})
    no_vrate = downlink_noise(_replies().drop("ehs_vrate_mps"))
    assert no_vrate.vrate_mps is None and no_vrate.speed_mps is not None
    assert downlink_noise(_replies().drop("mode_s")) == DownlinkNoise(None, None, None, {})


def test_the_measured_sigmas_reach_every_filter_that_weighs_a_register_and_nothing_else():
    cfg = with_noise(PipelineConfig(), DownlinkNoise(0.6, 0.25, 0.35, {"speed": 1000}))
    tr = cfg.tracker
    assert (tr.velocity_speed_sigma_mps, tr.velocity_track_sigma_deg, tr.vertical_rate_sigma_mps) == (0.6, 0.25, 0.35)
    assert tr.altitude.vertical_rate_sigma_mps == cfg.fusion.altitude.vertical_rate_sigma_mps == 0.35
    assert cfg.centralized_cfg.altitude.vertical_rate_sigma_mps == 0.35
    assert not tr.calibrate_downlinks and "ground speed σ 0.6 m/s (1,000 triples)" in tr.measured_downlinks
    base = PipelineConfig()
    kept = with_noise(_measuring(), DownlinkNoise(None, None, None, {}))
    assert kept.tracker == base.tracker


@dataclasses.dataclass
class _Data:
    reports: pl.DataFrame
    scenario: None = None


def _measuring(on: bool = True) -> PipelineConfig:
    base = PipelineConfig()
    return dataclasses.replace(base, tracker=dataclasses.replace(base.tracker, calibrate_downlinks=on))


def test_a_run_is_adapted_once_from_the_whole_recording_and_a_slice_keeps_it():
    whole = _Data(_replies())
    cfg = adapt_to_scenario(_measuring(), whole)
    assert cfg.tracker.velocity_speed_sigma_mps == pytest.approx(0.6, rel=0.04)
    noisier = _Data(_replies(sigma=(2.0, 1.0, 1.0)))
    assert adapt_to_scenario(cfg, noisier) == cfg                      # a slice of the run: unchanged
    assert adapt_to_scenario(PipelineConfig(), whole) == PipelineConfig()     # off by default


def test_on_simulated_traffic_the_measure_is_the_simulators_noise_with_its_quantisation(tmp_path):
    from tertiary.simulate import load_scenario, simulate
    scen = load_scenario("terminal-area")
    ds = simulate(dataclasses.replace(scen, duration_s=600.0, runs=1,
                                      traffic=dataclasses.replace(scen.traffic, aircraft=40)))
    noise = downlink_noise(ds.reports)
    ehs = EhsConfig()
    # independent: the sensor's σ and the register's rounding (uniform, LSB²/12) add
    expect = {f: math.hypot(s, RESOLUTION[c][0] / math.sqrt(12.0)) for f, s, c in (
        ("speed_mps", ehs.ground_speed_mps, "ground_speed_mps"), ("track_deg", ehs.true_track_deg, "true_track_deg"),
        ("vrate_mps", ehs.vertical_rate_mps, "vertical_rate_mps"))}
    for field, value in expect.items():
        assert getattr(noise, field) == pytest.approx(value, rel=0.08), field


def test_a_run_asked_to_measure_weighs_the_registers_by_the_measure_and_says_so(tmp_path):
    from tertiary.pipeline import process
    from tests.golden import small_dataset
    ds = small_dataset()
    notes: list[str] = []
    cfg = dataclasses.replace(_measuring(), methods=("information",), filters=("imm_sym",))
    res = process(ds, cfg, notes=notes)
    noise = downlink_noise(ds.reports)
    assert noise.speed_mps is not None
    [note] = [n for n in notes if n.startswith("tracker: downlinked registers' noise")]
    assert f"ground speed σ {noise.speed_mps:.3g} m/s" in note
    plain = process(ds, dataclasses.replace(cfg, tracker=PipelineConfig().tracker))
    # the IMM weighs the downlinked velocity: its tracks move with the σ it is given
    a, b = (r.tracks.sort("run", "epoch", "track_id")["vx_mps"] for r in (res, plain))
    assert a.len() == b.len() and (a - b).abs().max() > 1e-3


def test_the_cli_option_asks_the_run_to_measure(tmp_path, monkeypatch):
    from typer.testing import CliRunner
    from tertiary.cli import run as cli_run
    from tertiary.cli.commands import app

    class Stop(Exception):
        pass

    def run_job(cfg, **_kw):
        seen.append(cfg)
        raise Stop

    monkeypatch.setattr(cli_run, "run_job", run_job)
    for flag, want in (("--measure-downlinks", True), ("--no-measure-downlinks", False), (None, False)):
        seen: list = []
        CliRunner().invoke(app, ["run", str(tmp_path), *([flag] if flag else []), "--no-report"])
        assert seen and seen[0].tracker.calibrate_downlinks is want


def test_a_distributed_run_hands_every_partition_the_whole_recordings_measure(tmp_path, monkeypatch):
    from tertiary.io.dataset import write_dataset
    from tertiary.pipeline import dask_engine
    from tests.golden import small_dataset
    ds = small_dataset()
    write_dataset(ds, tmp_path / "ds")
    seen: list = []

    class Stop(Exception):
        pass

    def distribute(_c, _d, _o, _parts, cfg, *_a, **_k):
        seen.append(cfg)
        raise Stop

    monkeypatch.setattr(dask_engine, "_client", lambda *_a: (None, lambda: None))
    monkeypatch.setattr(dask_engine, "_distribute", distribute)
    with pytest.raises(Stop):
        dask_engine.run_dask_detailed(tmp_path / "ds", tmp_path / "out", _measuring(), window_s=60.0, slice_s=120.0)
    want = downlink_noise(ds.reports)
    assert seen[0].tracker.velocity_speed_sigma_mps == pytest.approx(want.speed_mps)
    assert not seen[0].tracker.calibrate_downlinks          # a partition does not measure its slice again


def test_unvalidated_input_measures_what_it_can_and_never_raises():
    """The measure reads the input before validation: a register sent as text is read where it
    is a number, a time column that is not a time leaves every σ as configured."""
    good = _replies()
    texts = good.with_columns(pl.col("ehs_gs_mps").cast(pl.String).str.replace(r"^1", "x"))
    noise = downlink_noise(texts)
    assert noise.speed_mps is not None and noise.triples["speed"] < 2 * 40 * 58
    assert noise.track_deg == pytest.approx(downlink_noise(good).track_deg, rel=0.2)
    assert downlink_noise(good.with_columns(pl.col("time").cast(pl.String))) == DownlinkNoise(None, None, None, {})
