"""A mixed recording as bytes: radars (CAT048 + CAT034), an MLAT sensor (CAT020), an ADS-B ground
station (CAT021 under its own SAC/SIC), the truth (CAT021 under another SAC/SIC) and another
system's STCA alerts (CAT004) — encoded, imported, run: the MLAT and ADS-B reports are aligned
and fused, the truth keeps the reference quality, the external alerts are scored."""

from __future__ import annotations

import dataclasses
import json
import math
from datetime import datetime, timezone
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import polars as pl
import pytest

from asterix_mutants import mutants
from tertiary.core import geo
from tertiary.core.errors import TertiaryError
from tertiary.core.units import FT
from tertiary.evaluation.reference import ReferenceConfig
from tertiary.io.asterix import codec, dataset, encode

TIME = pl.Datetime("us", "UTC")
T0 = datetime(2024, 3, 1, 10, tzinfo=timezone.utc).timestamp()
WAM, STATION = 7 * 256 + 20, 7 * 256 + 30
SITES = {WAM: (45.0, 16.0, 100.0), STATION: (45.2, 16.3, 50.0)}
N = 12


def _radars(station_kind: str = "adsb") -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": pl.Series([WAM, STATION], dtype=pl.UInt32), "name": ["WAM", "GS"], "kind": ["mlat", station_kind],
        "lat_deg": [SITES[WAM][0], SITES[STATION][0]], "lon_deg": [SITES[WAM][1], SITES[STATION][1]],
        "alt_m": [SITES[WAM][2], SITES[STATION][2]], "sigma_range_m": [20.0, 30.0], "sigma_azimuth_deg": [0.5, 0.5],
        "max_range_m": [2e5, 4e5], "sigma_elevation_deg": [1.0, 1.0], "scan_period_s": [1.0, 1.0]})


def _plots(rid: int, seed: int) -> pl.DataFrame:
    """Reports of one Cartesian sensor: three aircraft, one report a second, plots in its ENU frame."""
    rng = np.random.default_rng(seed)
    site = geo.LocalFrame(*SITES[rid])
    x, y, alt = rng.uniform(-8e4, 8e4, N), rng.uniform(-8e4, 8e4, N), rng.uniform(300.0, 11000.0, N)
    lat, lon, _ = site.to_geodetic(x, y, geo.up_at_height(site, x, y, alt))
    return pl.DataFrame({
        "run": pl.Series([0] * N, dtype=pl.UInt32), "radar_id": pl.Series([rid] * N, dtype=pl.UInt32),
        "time": pl.Series(((T0 + np.arange(N) + rng.uniform(0, 0.5, N)) * 1e6).astype(np.int64)).cast(TIME),
        "local_track_id": pl.Series(np.arange(N) % 3 + 40, dtype=pl.UInt32),
        "range_m": np.hypot(x, y), "azimuth_deg": np.degrees(np.arctan2(x, y)) % 360.0, "altitude_m": alt,
        "mode_s": [f"{0x3c6500 + i % 3:06x}" for i in range(N)], "mode_3a": [f"{1200 + i % 3:04d}" for i in range(N)],
        "callsign": [["DLH4AB", None, "AFR7"][i % 3] for i in range(N)],
        "plot_x_m": x, "plot_y_m": y, "plot_lat_deg": lat, "plot_lon_deg": lon,
        "plot_height_m": pl.Series([None] * N, dtype=pl.Float64),
        "plot_sigma_x_m": rng.uniform(5.0, 80.0, N), "plot_sigma_y_m": rng.uniform(5.0, 80.0, N),
        "plot_sigma_xy_m": rng.uniform(0.0, 4.0, N)})


def _station_reports() -> pl.DataFrame:
    rep = _plots(STATION, 2).with_columns(pl.lit(None, pl.Float64).alias(c) for c in (
        "plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m"))
    return rep.with_columns(pl.Series("adsb_nacp", [9, 10, 8, 11, 7, 3] * 2, dtype=pl.UInt8),
                            pl.Series("adsb_nic", [8, 7, 0, 11, 6, 5] * 2, dtype=pl.UInt8),
                            pl.Series("adsb_sil", [3, 2, 1, 0, 3, 3] * 2, dtype=pl.UInt8))


def _recording(tmp_path: Path, station_kind: str = "adsb") -> tuple[Path, Path, str, pl.DataFrame]:
    reports = pl.concat([_plots(WAM, 1), _station_reports()], how="diagonal_relaxed")
    ds = SimpleNamespace(reports=reports, radars=_radars(station_kind), truth=pl.DataFrame(),
                         origin=geo.LocalFrame(45.1, 16.1, 0.0))
    rec, sites, day = encode.write_recording(ds, tmp_path)
    return rec, sites, day, reports


def _pairs(orig: pl.DataFrame, back: pl.DataFrame, rid: int) -> pl.DataFrame:
    a = orig.filter(pl.col("radar_id") == rid).sort("time")
    b = back.filter(pl.col("radar_id") == rid).sort("time")
    assert a.height == b.height == N
    return pl.concat([a, b.select(pl.all().name.suffix("_b"))], how="horizontal")


def test_mlat_and_adsb_reports_round_trip(tmp_path: Path) -> None:
    """Hand-made MLAT and ADS-B station reports → CAT020 / CAT021 bytes → reports of those two
    sensors, equal within the ASTERIX resolutions; NACp, NIC, SIL and identities exact; one local
    track per ADS-B address. Catches: a station's CAT021 read as truth (no kind in the sites
    file), σ or quality fields misplaced, a lost resolution."""
    rec, sites, day, orig = _recording(tmp_path)
    assert 'kind = "adsb"' in sites.read_text() and 'kind = "mlat"' in sites.read_text()
    res = dataset.import_recordings([rec], sites=sites, date=day)
    assert res.rejects.height == 0 and res.truth.height == 0
    assert dict(res.radars.select("radar_id", "kind").iter_rows()) == {WAM: "mlat", STATION: "adsb"}
    assert res.counts["cat020_reports"] == res.counts["cat021_reports"] == N
    for rid in (WAM, STATION):
        m = _pairs(orig, res.reports, rid)
        assert ((m["time"] - m["time_b"]).dt.total_microseconds().abs() <= 1e6 / 256 + 1).all()   # 1/128 s
        assert ((m["altitude_m"] - m["altitude_m_b"]).abs() <= 25 * FT / 2 + 1e-9).all()       # 1/4 FL
        for c in ("mode_s", "mode_3a", "callsign"):
            assert m[c].fill_null("").to_list() == m[f"{c}_b"].fill_null("").to_list(), c
        site = geo.LocalFrame(*SITES[rid])
        e, n, u = site.from_geodetic(m["plot_lat_deg_b"].to_numpy(), m["plot_lon_deg_b"].to_numpy(),
                                     m["altitude_m_b"].to_numpy())
        rng_b, az_b = np.sqrt(e ** 2 + n ** 2 + u ** 2), np.degrees(np.arctan2(e, n)) % 360
        assert np.allclose(m["range_m_b"].to_numpy(), rng_b, atol=1.0)          # the plot seen from the site
        assert np.allclose(m["azimuth_deg_b"].to_numpy(), az_b, atol=1e-3)
    w = _pairs(orig, res.reports, WAM)
    assert ((w["plot_x_m"] - w["plot_x_m_b"]).abs() <= 0.25 + 1e-9).all()               # I020/042: 0.5 m
    assert ((w["plot_y_m"] - w["plot_y_m_b"]).abs() <= 0.25 + 1e-9).all()
    lsb041 = 180 / 2**25
    assert ((w["plot_lat_deg"] - w["plot_lat_deg_b"]).abs() <= lsb041 / 2 + 1e-12).all()
    assert ((w["plot_lon_deg"] - w["plot_lon_deg_b"]).abs() <= lsb041 / 2 + 1e-12).all()
    for c in ("plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m"):                   # I020/500: 0.25 m
        assert ((w[c] - w[f"{c}_b"]).abs() <= 0.125 + 1e-9).all(), c
    assert w["local_track_id"].to_list() == w["local_track_id_b"].to_list()
    s = _pairs(orig, res.reports, STATION)
    lsb131 = 180 / 2**30
    assert ((s["plot_lat_deg"] - s["plot_lat_deg_b"]).abs() <= lsb131 / 2 + 1e-12).all()
    assert ((s["plot_lon_deg"] - s["plot_lon_deg_b"]).abs() <= lsb131 / 2 + 1e-12).all()
    assert np.hypot(s["plot_x_m"] - s["plot_x_m_b"], s["plot_y_m"] - s["plot_y_m_b"]).max() < 0.1
    for c in ("adsb_nacp", "adsb_nic", "adsb_sil"):
        assert s[c].to_list() == s[f"{c}_b"].to_list(), c
    from tertiary.sensors.adsb import sigma_from_nacp
    assert np.allclose(s["plot_sigma_x_m_b"].to_numpy(), sigma_from_nacp(s["adsb_nacp"].to_numpy()))
    tracks = s.group_by("mode_s_b").agg(pl.col("local_track_id_b").n_unique().alias("k"),
                                         pl.col("local_track_id_b").first())
    assert (tracks["k"] == 1).all() and tracks["local_track_id_b"].n_unique() == 3
    assert tracks.select(pl.col("mode_s_b").str.to_integer(base=16) == pl.col("local_track_id_b")).to_series().all()


def test_a_stations_cat021_without_kind_adsb_is_truth(tmp_path: Path) -> None:
    """The same bytes with the station not of kind adsb in the sites file: its CAT021 goes the
    truth's way (the routing is by the sites file, not by the bytes), where a record without
    geometric height is refused."""
    rec, sites, day, _ = _recording(tmp_path)
    sites.write_text(sites.read_text().replace('kind = "adsb"\n', ""))
    res = dataset.import_recordings([rec], sites=sites, date=day, origin=(45.1, 16.1, 0.0))
    assert res.reports["radar_id"].unique().to_list() == [WAM] and "cat021_reports" not in res.counts
    assert res.counts["cat021_truth_records"] == N
    assert res.rejects["reason"].to_list() == ["CAT021 without address, time, position or geometric height"] * N


def _truth_rows(nacp: list[int | None]) -> pl.DataFrame:
    n = len(nacp)
    rng = np.random.default_rng(4)
    return pl.DataFrame({
        "truth_id": pl.Series(np.arange(n) % 4, dtype=pl.Int64),
        "time": pl.Series(((T0 + np.arange(n) // 4) * 1e6).astype(np.int64)).cast(TIME),
        "x_m": rng.uniform(-5e4, 5e4, n), "y_m": rng.uniform(-5e4, 5e4, n), "z_m": rng.uniform(500, 9000, n),
        "vx_mps": rng.uniform(-200, 200, n), "vy_mps": rng.uniform(-200, 200, n), "vz_mps": np.zeros(n),
        "alt_m": rng.uniform(500, 9000, n), "icao24": [f"{0x4ca000 + i % 4:06x}" for i in range(n)],
        "nacp": pl.Series(nacp, dtype=pl.Int64), "nic": pl.Series([7] * n, dtype=pl.Int64)})


def test_truth_below_the_reference_quality_goes_to_rejects(tmp_path: Path) -> None:
    """Truth CAT021 with NACp 3…11 (and one without I021/090): the points below the reference's
    NACp bound are rejects with the reason, the rest are truth, and the notes say the filter and
    the count. Catches: the quality filter left out, or NACp read from the wrong bits."""
    bound = ReferenceConfig().min_nacp
    nacp = [11, 10, 9, 8, 7, 6, 3, None, 9, 6, 8, 10]
    system = geo.LocalFrame(45.0, 16.0, 0.0)
    recs = [r for _, r in encode.cat021(_truth_rows(nacp), system)]
    f = tmp_path / "truth.ast"
    f.write_bytes(b"".join(codec.datablock(21, recs[i:i + 4]) for i in range(0, len(recs), 4)))
    res = dataset.import_recordings([f], date="2024-03-01", origin=(45.0, 16.0, 0.0))
    low = [q for q in nacp if q is not None and q < bound]
    reasons = res.rejects["reason"].to_list()
    assert sorted(reasons) == sorted(f"declared quality below the reference bound (NACp {q} < {bound})" for q in low)
    assert res.truth.height == len(nacp) - len(low)
    assert sorted(json.loads(d)["nacp"] for d in res.rejects["detail"]) == sorted(low)
    assert res.counts["truth_below_quality"] == len(low)
    note = [n for n in res.notes if n.startswith("truth (CAT021)")]
    assert len(note) == 1 and f"NACp >= {bound}" in note[0] and f"{len(low)} point(s)" in note[0]


def test_mutated_cat020_and_cat021_never_raise(tmp_path: Path) -> None:
    """Flipped, cut and deleted bytes of the CAT020 and station CAT021 blocks: the import ends
    with rejects (each with a reason) or a clear TertiaryError, and every report it keeps is a
    whole plot (time, position, sensor). Catches: a record without I021/131 or I021/080 kept as a
    report, a traceback from a malformed record."""
    rec, sites, day, orig = _recording(tmp_path)
    ds = SimpleNamespace(radars=_radars())
    wam = [codec.datablock(20, [r for _, r in encode.cat020(orig.filter(pl.col("radar_id") == WAM))][i:i + 3])
           for i in range(0, N, 3)]
    st = [codec.datablock(21, [r for _, r in encode.cat021_reports(orig.filter(pl.col("radar_id") == STATION),
                                                                     ds.radars)][i:i + 3]) for i in range(0, N, 3)]
    # hand-cut records: a station report without position, one without address
    s21 = codec.spec(21).cv_record
    holes = codec.datablock(21, [s21.create({"010": (("SAC", 7), ("SIC", 30)), "071": 36000.0, "080": 0x3c6501}),
                                 s21.create({"010": (("SAC", 7), ("SIC", 30)), "071": 36001.0,
                                             "131": (("LAT", 45.1), ("LON", 16.2))})])
    rng = np.random.default_rng(11)
    seen = 0
    for i in range(12):
        f = tmp_path / f"m{i}.ast"
        f.write_bytes(b"".join([holes, *mutants(wam, rng, 3), *mutants(st, rng, 3), *wam[:1], *st[:1]]))
        try:
            res = dataset.import_recordings([f], sites=sites, date=day, skip_unknown=True)
        except TertiaryError:
            continue
        seen += 1
        assert (res.rejects["reason"].str.len_chars() > 0).all()
        assert res.rejects["reason"].str.contains("no I021/131 or I021/130 (position)", literal=True).any()
        assert res.rejects["reason"].str.contains("no I021/080 (target address)", literal=True).any()
        rep = res.reports
        assert rep.height >= 2 * 3
        for c in ("time", "radar_id", "plot_x_m", "plot_y_m", "plot_lat_deg", "range_m", "azimuth_deg"):
            assert rep[c].null_count() == 0, c
        assert rep.filter(pl.col("radar_id") == STATION)["mode_s"].null_count() == 0
    assert seen >= 6


# --------------------------------------------------------------------------- the scenario end to end


@pytest.fixture(scope="module")
def mixed(tmp_path_factory: pytest.TempPathFactory):
    """terminal-area-mixed (two radars, the WAM, the ADS-B station; 12 aircraft, 180 s) simulated,
    written as a recording, another system's STCA alerts of its losses of separation as CAT004
    beside it, both imported and run."""
    import tertiary
    from safety.alerts import AlertConfig, loss_of_separation
    from tertiary.io.dataset import read_dataset
    from tertiary.simulate import load_scenario, simulate
    cfg = load_scenario("terminal-area-mixed")
    cfg = dataclasses.replace(cfg, radars=cfg.radars[:2], duration_s=180.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=12, conflict_pairs=2,
                                                          near_miss_pairs=0))
    ds = simulate(cfg)
    out = tmp_path_factory.mktemp("mixed")
    rec, sites, day = encode.write_recording(ds, out)
    los = loss_of_separation(ds.truth, AlertConfig(), ds.origin)
    assert los.height >= 1
    calls = dict(ds.truth.unique("truth_id").select("truth_id", "callsign").iter_rows())
    # one STCA episode per loss: from 20 s before it for 25 s (start and end message < 30 s apart)
    start = (pl.col("t_start") - pl.duration(seconds=20)).clip(lower_bound=ds.truth["time"].min())
    alerts = los.select(start.alias("t_start"), (start + pl.duration(seconds=25)).alias("t_end"),
                        pl.col("truth_a").alias("id_a"), pl.col("truth_b").alias("id_b"),
                        pl.col("truth_a").replace_strict(calls).alias("callsign_a"),
                        pl.col("truth_b").replace_strict(calls).alias("callsign_b"))
    stca = out / "stca.ast"
    encode.export_alerts(alerts, stca, sac=0, sic=200)
    res = dataset.import_recordings([rec, stca], sites=sites, date=day, origin=ds.scenario.origin)
    back = read_dataset(dataset.write_import(res, out / "ds", "mixed"))
    run = tertiary.process(back, tertiary.PipelineConfig(methods=("information",), filters=("singer",)))
    return ds, res, back, run, los


def _ids(ds: object, kind: str) -> int:
    return int(ds.radars.filter(pl.col("kind") == kind)["radar_id"].item())  # type: ignore[attr-defined]


def test_mixed_recording_imports_every_source(mixed) -> None:
    """Every report of run 0 comes back as a report of its own sensor (CAT048, CAT020, station
    CAT021), the truth CAT021 as truth, the CAT004 as an alert list."""
    ds, res, back, _, los = mixed
    sim = ds.reports.filter(pl.col("run") == 0).group_by("radar_id").len().sort("radar_id")
    got = res.reports.group_by("radar_id").len().sort("radar_id")
    assert sim.rows() == got.rows()
    assert dict(back.radars.select("radar_id", "kind").iter_rows()) == dict(ds.radars.select("radar_id", "kind")
                                                                             .iter_rows())
    assert res.truth["truth_id"].n_unique() == ds.truth["truth_id"].n_unique()
    assert res.rejects.height == 0 and back.external_alerts.height == los.height
    adsb = res.reports.filter(pl.col("radar_id") == _ids(ds, "adsb"))
    assert adsb["adsb_nacp"].null_count() == 0 and adsb["truth_id"].null_count() == 0


def test_mlat_and_adsb_are_aligned_fused_and_evaluated(mixed) -> None:
    """The WAM's and the station's reports are aligned, the fused targets take both among their
    sources, and the per-sensor evaluation sees both with their detections and identities."""
    from tertiary.evaluation.radar_eval import radar_metrics
    ds, _, back, run, _ = mixed
    fused = run.fused.filter(pl.col("method") == "information")
    per = radar_metrics(back.reports, back.radars, back.truth, back.origin).filter(pl.col("segment") == "all")
    for kind in ("mlat", "adsb"):
        rid = _ids(ds, kind)
        rep = back.reports.filter(pl.col("radar_id") == rid)
        aligned = run.aligned.filter(pl.col("radar_id") == rid)["report_id"].n_unique()
        assert aligned >= 0.8 * rep.height, (kind, aligned, rep.height)
        assert fused["radar_ids"].list.contains(rid).mean() > 0.3, kind
        m = dict(per.filter(pl.col("method") == str(rid)).select("metric", "value").iter_rows())
        assert m["n_reports"] >= 0.8 * rep.height and m["mode_s_correct_frac"] > 0.99, (kind, m)


def test_the_external_alerts_are_scored_beside_ours(mixed) -> None:
    """The CAT004 list is scored on the imported truth: every loss of separation it was built
    from is alerted, with its aircraft identified; our own pictures are scored beside it."""
    _, _, _, run, los = mixed
    safety = run.metrics.filter((pl.col("stage") == "safety") & (pl.col("segment") == "all"))
    ext = dict(safety.filter(pl.col("method") == "external:0/200").select("metric", "value").iter_rows())
    assert ext["alerted_los"] == ext["los_episodes"] == los.height
    assert ext["unidentified_alerts"] == 0 and ext["genuine_alerts"] >= los.height
    assert safety.filter(~pl.col("method").str.starts_with("external:"))["method"].n_unique() >= 1
    assert math.isfinite(ext["warning_p05_s"])
