"""ASTERIX import/export: the real recording, round trips, time handling, sites registry, CLI."""

from __future__ import annotations

import json
import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from tertiary.evaluation.external import match_external, score_import
from tertiary.core import geo
from tertiary.io.asterix import capture, codec, dataset, encode, importer
from tertiary.io.asterix.sites import read_sites, sites_toml
from tertiary.cli.commands import app

DATA = Path(__file__).parent / "data"
PCAP = DATA / "cat_034_048.pcap"
CODES = [(25, 11), (25, 12), (25, 13), (25, 14), (25, 201), (25, 204), (25, 205)]
NM = 1852.0


def _sites(path: Path, codes=CODES, scan: float | None = 4.0) -> Path:
    """A registry for the real recording (positions are placeholders: the file does not give them)."""
    rows = [{"sac": a, "sic": b, "radar_id": a * 256 + b, "name": f"{a}-{b}", "lat_deg": 45.0 + i * 0.1,
             "lon_deg": 16.0, "alt_m": 100.0, "sigma_range_m": 70.0, "sigma_azimuth_deg": 0.08, "max_range_m": 463000.0,
             "sigma_elevation_deg": 1.0, "scan_period_s": math.nan if scan is None else scan}
            for i, (a, b) in enumerate(codes)]
    path.write_text(sites_toml(pl.DataFrame(rows)))
    return path


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> dataset.ImportResult:
    sites = _sites(tmp_path_factory.mktemp("sites") / "sites.toml", scan=None)
    # 25/201 and 25/204 send one distinct CAT034 message each: no period to measure, give it
    text = sites.read_text().replace("scan_period_s = nan", "scan_period_s = 4.0")
    sites.write_text(text)
    return dataset.import_recordings([PCAP], sites=sites)


# --------------------------------------------------------------------------- the real recording


def test_real_recording_counts(real: dataset.ImportResult) -> None:
    c = real.counts
    assert c["radars"] == 7 and real.radars.height == 7
    assert c["cat048_records"] == 128 and c["duplicates"] == 64 and c["distinct"] == 64
    assert c["cat034_messages"] == 34 and c["cat034_distinct"] == 17
    # the one distinct record without I048/040 (a track-end report, also the stale one) is a reject
    assert real.reports.height == 63 and real.rejects.height == 1
    assert real.rejects["reason"][0].startswith("no I048/040 (measured position); stale")


def test_real_first_record_equals_libasterix(real: dataset.ImportResult) -> None:
    grams = capture.read_recording(PCAP)
    blocks = capture.split_blocks(grams)
    first = codec.parse_block(blocks.data[0])[0]
    rep = real.reports.row(0, named=True)
    assert (rep["sac"], rep["sic"]) == (codec.sub_uint(first, "010", "SAC"), codec.sub_uint(first, "010", "SIC"))
    assert rep["range_m"] == pytest.approx(codec.sub_qty(first, "040", "RHO", "NM") * NM, abs=1e-9)
    assert rep["azimuth_deg"] == pytest.approx(codec.sub_qty(first, "040", "THETA", "°"), abs=1e-12)
    assert rep["flight_level"] == codec.sub_qty(first, "090", "FL", "FL")
    assert rep["altitude_m"] == pytest.approx(rep["flight_level"] * 100 * 0.3048)
    assert rep["mode_3a"] == first.get_item("070").variation.get_item("MODE3A").variation.content.as_string()
    assert rep["mode_s"] == f"{codec.uint(first, '220'):06x}"
    assert rep["callsign"] == codec.text(first, "240").rstrip()
    assert rep["local_track_id"] == codec.sub_uint(first, "161", "TRN")
    assert rep["ground_speed_mps"] == pytest.approx(codec.sub_qty(first, "200", "GSP", "NM/s") * NM)
    tod = codec.qty(first, "140", "s")
    cap = grams.capture_s[0]
    day = math.floor(cap / 86400) * 86400
    assert rep["time"] == datetime.fromtimestamp(day + tod, timezone.utc)
    assert rep["latency_s"] == pytest.approx(cap - (day + tod), abs=1e-6)
    # the decoded values themselves (DLH65A at FL330, I048/040 = c5af f1e0)
    assert (rep["callsign"], rep["mode_s"], rep["mode_3a"]) == ("DLH65A", "3c660c", "1000")
    assert rep["range_m"] == 0xC5AF / 256 * NM and rep["azimuth_deg"] == 0xF1E0 * 360 / 65536


def test_real_latency_and_timing(real: dataset.ImportResult) -> None:
    lat = real.latency.sort("sac", "sic")
    assert lat.select("sac", "sic").rows() == CODES
    # two transport paths: the SIC 1x radars ~0.5-0.7 s, the SIC 20x radars ~1.9 s
    med = dict(zip(lat["sic"], lat["latency_median_s"]))
    assert all(0.4 < med[s] < 0.8 for s in (11, 12, 13, 14)) and all(1.8 < med[s] < 2.0 for s in (201, 204, 205))
    assert lat.filter(pl.col("sic") == 13)["stale"][0] == 1 and lat["stale"].sum() == 1
    timing = dict(zip(real.antenna["sic"], real.antenna["scan_period_s"]))
    assert timing[12] == pytest.approx(4.9453125)        # I034/041 sent by 25/12
    assert 4.5 < timing[13] < 5.5                         # from sector crossings
    assert real.reports["time"].is_between(datetime(2016, 5, 5, 7, 35, tzinfo=timezone.utc),
                                           datetime(2016, 5, 5, 7, 37, tzinfo=timezone.utc)).all()


def test_redundant_line_copies_are_the_same_bytes() -> None:
    """The de-duplication key is the record bytes: both lines carry each record once."""
    grams = capture.read_recording(PCAP)
    assert len({line.split(">")[1].split(".")[1] for line in grams.line}) == 2   # 232.1.x / 232.2.x
    blocks = capture.split_blocks(grams)
    recs = [r.unparse().to_bytes() for d, c in zip(blocks.data, blocks.cat) if c == 48 for r in codec.parse_block(d)]
    assert len(recs) == 128 and len(set(recs)) == 64


# --------------------------------------------------------------------------- time


def test_absolute_time_midnight_rollover() -> None:
    day = datetime(2024, 3, 1, tzinfo=timezone.utc).timestamp()
    tod = np.array([86399.5, 86399.9, 0.2, 86399.95, 1.0])      # crosses midnight, one late report
    t = importer.absolute_time(tod, np.full(5, np.nan), day)
    assert np.allclose(t - day, [86399.5, 86399.9, 86400.2, 86399.95, 86401.0])
    cap = day + np.array([86399.6, 86400.1, 86400.3, 86400.4, 86401.2])   # capture stamps decide the day
    t2 = importer.absolute_time(tod, cap, None)
    assert np.allclose(t2 - day, [86399.5, 86399.9, 86400.2, 86399.95, 86401.0])


def test_raw_file_without_date_is_refused(tmp_path: Path) -> None:
    raw = tmp_path / "x.ast"
    raw.write_bytes(b"".join(codec.parse_block(d) and d for d in capture.split_blocks(
        capture.read_recording(PCAP)).data[:4]))
    with pytest.raises(Exception, match="--date"):
        dataset.import_recordings([raw], sites=_sites(tmp_path / "s.toml"))


# --------------------------------------------------------------------------- sites registry


def test_missing_sites_listed_and_template(tmp_path: Path) -> None:
    sites = _sites(tmp_path / "s.toml", codes=CODES[:5])
    tmpl = tmp_path / "tmpl.toml"
    with pytest.raises(Exception, match="25/204, 25/205"):
        dataset.import_recordings([PCAP], sites=sites)
    with pytest.raises(Exception, match="wrote a template"):
        dataset.import_recordings([PCAP], sites=sites, template=tmpl)
    text = tmpl.read_text()
    assert text.count("[[radar]]") == 2 and "sic = 204" in text and "lat_deg = nan" in text
    with pytest.raises(Exception, match="not filled in"):
        read_sites(tmpl)


def test_sites_errors(tmp_path: Path) -> None:
    bad = tmp_path / "b.toml"
    bad.write_text("[[radar]]\nsac = 1\nsic = 300\n")
    with pytest.raises(Exception, match="sac and sic"):
        read_sites(bad)
    bad.write_text("[[radar]]\nsac = 1\nsic = 2\nlat = 3\n")
    with pytest.raises(Exception, match="unknown key"):
        read_sites(bad)


# --------------------------------------------------------------------------- round trips


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory):
    from tertiary.cli.common import build_scenario
    from tertiary.io.dataset import write_dataset
    from tertiary.simulate import simulate
    out = tmp_path_factory.mktemp("sim")
    ds = simulate(build_scenario("terminal-area", aircraft=6, duration=150, runs=1, seed=3))
    write_dataset(ds, out)
    rec, sites, day = encode.write_recording(ds, out)
    res = dataset.import_recordings([rec], sites=sites, date=day, origin=ds.scenario.origin)
    return ds, res, rec


def test_simulated_round_trip_reports(simulated) -> None:
    ds, res, _ = simulated
    a = ds.reports.sort("time")
    b = res.reports.sort("time").with_columns(pl.col("time").alias("time_b"))
    assert res.rejects.height == 0 and b.height == a.height
    m = a.join_asof(b, on="time", by=["radar_id", "local_track_id"], strategy="nearest", suffix="_b",
                    check_sortedness=False)
    dt = (m["time"] - m["time_b"]).dt.total_microseconds().abs().max() / 1e6
    assert dt <= 1 / 256 + 1e-6                                                   # 1/128 s
    assert (m["range_m_b"] - m["range_m"]).abs().max() <= NM / 512 + 1e-9        # 1/256 NM
    daz = (((m["azimuth_deg_b"] - m["azimuth_deg"] + 180) % 360) - 180).abs().max()
    assert daz <= 360 / 2**17 + 1e-12                                             # 360/2^16 deg
    alt = (m["altitude_m_b"] - m["altitude_m"]).abs().max()
    assert alt <= 25 * 0.3048 / 2 + 1e-9                                           # 1/4 FL
    for c in ("mode_s", "mode_3a", "callsign"):
        assert (m[c].fill_null("") == m[f"{c}_b"].fill_null("")).all(), c
    # the simulator's EHS values are on the BDS 4,0/5,0/6,0 grids: I048/250 returns them (true
    # track in [0, 360) where the simulator says [-180, 180))
    ehs = ("selected_alt_m", "ehs_gs_mps", "ehs_track_deg", "ehs_track_rate_dps", "ehs_roll_deg", "ehs_vrate_mps")
    for c in ehs:
        assert m[c].is_not_null().sum() > 100 and (m[c].is_null() == m[f"{c}_b"].is_null()).all(), c
        d = (m[f"{c}_b"] - m[c]).drop_nulls()
        d = ((d + 180) % 360 - 180) if c == "ehs_track_deg" else d
        assert d.abs().max() < 1e-9, c
    assert res.radars.sort("radar_id")["scan_period_s"].to_list() == ds.radars.sort("radar_id")["scan_period_s"].to_list()


def test_simulated_round_trip_truth(simulated) -> None:
    ds, res, _ = simulated
    t = ds.truth.with_columns(pl.when(pl.col("icao24").fill_null("") != "")
                              .then(pl.col("icao24").str.to_integer(base=16, strict=False))
                              .otherwise(pl.col("truth_id")).alias("addr"))
    m = t.join(res.truth, left_on=["addr", "time"], right_on=["truth_id", "time"], suffix="_b")
    assert m.height == ds.truth.height
    horiz = np.hypot(m["x_m"] - m["x_m_b"], m["y_m"] - m["y_m_b"]).max()
    assert horiz < 0.05                                          # I021/131: 180/2^30 deg
    assert (m["z_m"] - m["z_m_b"]).abs().max() <= 6.25 * 0.3048 / 2 + 1e-3   # I021/140: 6.25 ft
    assert np.hypot(m["vx_mps"] - m["vx_mps_b"], m["vy_mps"] - m["vy_mps_b"]).max() < 0.2


def test_picture_round_trip_cat062(tmp_path: Path) -> None:
    frame = geo.LocalFrame(48.85, 2.35, 0.0)
    n, rng = 40, np.random.default_rng(7)
    tracks = pl.DataFrame({
        "run": pl.Series(np.zeros(n, np.uint32)),
        "epoch": pl.Series(((1633608000 + np.arange(n) * 4.0) * 1e6).astype(np.int64)).cast(pl.Datetime("us", "UTC")),
        "track_id": pl.Series(np.arange(n) % 5 + 70000, dtype=pl.UInt64), "filter": ["singer"] * n,
        "method": ["information"] * n,
        "x_m": rng.uniform(-2e5, 2e5, n), "y_m": rng.uniform(-2e5, 2e5, n), "z_m": rng.uniform(0, 1e4, n),
        "vx_mps": rng.uniform(-250, 250, n), "vy_mps": rng.uniform(-250, 250, n), "vz_mps": rng.uniform(-10, 10, n),
        "cov_diag": pl.Series(np.tile([400.0, 300.0, 900.0, 4.0, 9.0, 1.0], (n, 1)), dtype=pl.Array(pl.Float64, 6)),
        "alt_m": rng.uniform(0, 1e4, n), "mode_s": ["4ca1b2"] * n, "callsign": ["EIN123"] * n,
    })
    out = tmp_path / "pic.ast"
    encode.export_picture(tracks, frame, out)
    res = dataset.import_recordings([out], date="2021-10-07", origin=(48.85, 2.35, 0.0))
    e = res.external_tracks.with_columns(pl.col("track_id") + 65536)    # I062/040 is 16 bits
    m = tracks.join(e, on=["epoch", "track_id"], suffix="_b")
    assert m.height == n and res.rejects.height == 0
    assert np.hypot(m["x_m"] - m["x_m_b"], m["y_m"] - m["y_m_b"]).max() < 0.6         # 180/2^25 deg
    assert (m["z_m"] - m["z_m_b"]).abs().max() < 1.0                                   # 6.25 ft
    assert np.hypot(m["vx_mps"] - m["vx_mps_b"], m["vy_mps"] - m["vy_mps_b"]).max() <= 0.125 * 2**0.5 + 1e-9
    assert (m["alt_m"] - m["alt_m_b"]).abs().max() <= 25 * 0.3048 / 2 + 1e-9
    cov = np.stack(m["cov_diag_b"].to_numpy())
    assert np.allclose(np.sqrt(cov[:, [0, 1, 3, 4]]), [20.0, np.sqrt(300.0), 2.0, 3.0], atol=0.5)
    assert (m["mode_s_b"] == "4ca1b2").all() and (m["callsign_b"] == "EIN123").all()


# --------------------------------------------------------------------------- CLI


def test_cli_import_real(tmp_path: Path) -> None:
    sites = _sites(tmp_path / "s.toml")
    out = tmp_path / "ds"
    r = CliRunner().invoke(app, ["import", "asterix", str(PCAP), "--sites", str(sites), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "63 reports from 7 radar(s)" in r.output and "34 CAT034 messages" in r.output
    assert "25/201" in r.output                                        # the latency table
    for name in ("reports", "radars", "rejects", "latency", "antenna"):
        assert (out / f"{name}.parquet").is_file()
    from tertiary.io.dataset import read_dataset
    ds = read_dataset(out)
    assert ds.reports.height == 63 and ds.radars.height == 7


def test_cli_import_needs_sites(tmp_path: Path) -> None:
    r = CliRunner().invoke(app, ["import", "asterix", str(PCAP), "--out", str(tmp_path / "ds")])
    assert r.exit_code == 2 and "--sites" in r.output and "25/11" in r.output
    tmpl = tmp_path / "t.toml"
    r = CliRunner().invoke(app, ["import", "asterix", str(PCAP), "--out", str(tmp_path / "ds"),
                                 "--write-sites-template", str(tmpl)])
    assert r.exit_code == 3 and tmpl.read_text().count("[[radar]]") == 7


def test_rejects_detail_names_the_place(real: dataset.ImportResult) -> None:
    detail = json.loads(real.rejects["detail"][0])
    assert detail["file"].endswith("cat_034_048.pcap") and detail["sac"] == 25 and detail["sic"] == 13


def _rmse(run_dir: Path) -> dict[str, float]:
    from tertiary.store.run_store import RunStore
    with RunStore.open(run_dir, read_only=True) as store:
        m = store.sql("SELECT method, value FROM metrics WHERE stage = 'fusion' AND metric = 'rmse_horizontal_m' "
                      "AND segment = 'all'")
    return dict(m.iter_rows())


def test_cli_simulate_import_run_export(tmp_path: Path) -> None:
    """The README flow: simulate --format asterix → import → run → export; the pipeline's horizontal
    accuracy from the recording within 20 % of the Parquet path's."""
    runner = CliRunner()
    sim, imp = tmp_path / "ta", tmp_path / "ta-ast"
    r = runner.invoke(app, ["simulate", "terminal-area", "--out", str(sim), "--aircraft", "8", "--duration", "200",
                            "--runs", "1", "--format", "asterix"])
    assert r.exit_code == 0, r.output
    assert (sim / "recording.ast").is_file() and (sim / "sites.toml").is_file() and "--date 2021-10-07" in r.output
    r = runner.invoke(app, ["import", "asterix", str(sim / "recording.ast"), "--sites", str(sim / "sites.toml"),
                            "--date", "2021-10-07", "--out", str(imp)])
    assert r.exit_code == 0, r.output
    for src, run in ((sim, tmp_path / "run-pq"), (imp, tmp_path / "run-ast")):
        r = runner.invoke(app, ["run", str(src), "--out", str(run), "--filters", "singer",
                                "--methods", "arithmetic,information", "--no-report"])
        assert r.exit_code == 0, r.output
    pq, ast = _rmse(tmp_path / "run-pq"), _rmse(tmp_path / "run-ast")
    for method in ("arithmetic", "information"):
        assert abs(ast[method] - pq[method]) <= 0.2 * pq[method], (method, pq, ast)
    out = tmp_path / "pic.ast"
    r = runner.invoke(app, ["export", "asterix", str(tmp_path / "run-ast"), "--picture", "singer/information",
                            "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "I062/500 accuracy not written" in r.output          # a lean run stores no covariances
    back = dataset.import_recordings([out], date="2021-10-07")
    assert back.external_tracks.height > 0 and back.rejects.height == 0
    r = runner.invoke(app, ["export", "asterix", str(tmp_path / "run-ast"), "--picture", "nope/x", "--out", str(out)])
    assert r.exit_code == 2 and "--picture" in r.output


def test_asterix_doc_lines_name_real_options() -> None:
    """Every ``tertiary …`` line of docs/asterix.md's code blocks names a command and options the CLI has."""
    import typer.main
    doc = (Path(__file__).resolve().parents[1] / "docs" / "asterix.md").read_text()
    block = "\n".join(doc.split("```")[1::2])
    group = typer.main.get_command(app)
    lines = [ln.split("#")[0].split() for ln in block.splitlines() if ln.startswith("tertiary ")]
    assert {ln[1] for ln in lines} >= {"simulate", "import", "run", "export"}
    for words in lines:
        cmd = group.commands[words[1]]
        if words[1] in ("import", "export"):
            cmd = cmd.commands[words[2]]
        known = {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)}
        assert all(w in known for w in words if w.startswith("--")), words


def test_import_is_lazy() -> None:
    """`import tertiary` (and the CLI module) must not pay libasterix's import cost."""
    import subprocess
    import sys
    code = "import sys, tertiary, tertiary.cli.commands; print('asterix' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.split() == ["False"]


def _pcapng(pcap: bytes) -> bytes:
    """The same frames as a pcapng file (section header, one Ethernet interface, enhanced packets)."""
    import struct

    def block(btype: int, body: bytes) -> bytes:
        body += b"\0" * (-len(body) % 4)
        n = 12 + len(body)
        return struct.pack("<II", btype, n) + body + struct.pack("<I", n)

    out = [block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1)), block(1, struct.pack("<HHI", 1, 0, 65535))]
    off = 24
    while off < len(pcap):
        sec, usec, incl, orig = struct.unpack("<IIII", pcap[off:off + 16])
        ts = sec * 1_000_000 + usec
        out.append(block(6, struct.pack("<IIIII", 0, ts >> 32, ts & 0xFFFFFFFF, incl, orig)
                         + pcap[off + 16:off + 16 + incl]))
        off += 16 + incl
    return b"".join(out)


def test_pcapng_equals_pcap(tmp_path: Path, real: dataset.ImportResult) -> None:
    ng = tmp_path / "rec.pcapng"
    ng.write_bytes(_pcapng(PCAP.read_bytes()))
    sites = _sites(tmp_path / "s.toml")
    res = dataset.import_recordings([ng], sites=sites)
    assert res.counts["distinct"] == 64 and res.counts["cat034_messages"] == 34
    assert res.reports.select("time", "range_m", "mode_s").equals(real.reports.select("time", "range_m", "mode_s"))
    assert np.allclose(res.reports["latency_s"].to_numpy(), real.reports["latency_s"].to_numpy(), atol=1e-6)


def test_midnight_in_a_raw_recording(tmp_path: Path) -> None:
    t = pl.datetime_range(pl.datetime(2024, 1, 1, 23, 59, 40, time_zone="UTC"),
                          pl.datetime(2024, 1, 2, 0, 0, 20, time_zone="UTC"), "2s", eager=True)
    n = len(t)
    reports = pl.DataFrame({"radar_id": pl.Series([1] * n, dtype=pl.UInt32), "time": t,
                            "local_track_id": pl.Series([7] * n, dtype=pl.UInt32),
                            "range_m": np.linspace(10e3, 20e3, n), "azimuth_deg": np.linspace(10, 20, n)})
    raw = tmp_path / "mid.ast"
    raw.write_bytes(b"".join(codec.datablock(48, [r]) for r in encode.cat048(reports)))
    res = dataset.import_recordings([raw], sites=_sites(tmp_path / "s.toml", codes=[(0, 1)]), date="2024-01-01")
    assert res.reports["time"].to_list() == t.to_list()
    assert not res.reports["out_of_order"].any()


def test_impossible_values_and_unknown_category_are_rejects(tmp_path: Path) -> None:
    s48, s21 = codec.spec(48).cv_record, codec.spec(21).cv_record
    late = s48.create({"010": (("SAC", 0), ("SIC", 1)), "140": 86400 * 128 + 5,        # time of day >= 86 400 s
                       "040": (("RHO", 10.0), ("THETA", 5.0)), "161": (0, ("TRN", 3))})
    good = s48.create({"010": (("SAC", 0), ("SIC", 1)), "140": 100.0,
                       "040": (("RHO", 10.0), ("THETA", 5.0)), "161": (0, ("TRN", 3))})
    adsb = s21.create({"010": (("SAC", 0), ("SIC", 250)), "040": (0,), "071": 100.0, "080": 0xABCDEF,
                       "131": (("LAT", 95.0), ("LON", 2.0)), "140": 1000.0})
    data = codec.datablock(48, [late, good]) + codec.datablock(21, [adsb]) + bytes([99, 0, 4, 0]) \
        + bytes([48, 0, 200])
    raw = tmp_path / "bad.ast"
    raw.write_bytes(data)
    res = dataset.import_recordings([raw], sites=_sites(tmp_path / "s.toml", codes=[(0, 1)]), date="2024-01-01")
    reasons = res.rejects["reason"].to_list()
    assert res.reports.height == 1
    assert any("time of day" in r and "86400" in r for r in reasons)
    assert any(r == "CAT021 position or time out of range" for r in reasons)
    assert any("category 99 not supported" in r for r in reasons)
    assert any("data block length 200" in r for r in reasons)
    assert res.truth.height == 0


def test_enu_velocity_against_finite_differences() -> None:
    """A velocity in the aircraft's own ENU frame (how CAT021 gives it) turned into the system
    frame equals the displacement of the position over 1 s, computed through geodetic
    coordinates with the package's geo frames (an independent path)."""
    system = geo.LocalFrame(48.85, 2.35, 0.0)
    lat, lon, h = np.array([50.2, 47.1, 48.85]), np.array([5.9, -1.3, 2.35]), np.array([10000.0, 3000.0, 500.0])
    ve, vn, vu = np.array([150.0, -80.0, 0.0]), np.array([60.0, 200.0, -240.0]), np.array([5.0, -10.0, 0.0])
    vx, vy, vz = importer.enu_velocity(lat, lon, ve, vn, vu, system)
    dt = 1.0
    for i in range(3):
        local = geo.LocalFrame(lat[i], lon[i], h[i])
        lat2, lon2, h2 = local.to_geodetic(ve[i] * dt, vn[i] * dt, vu[i] * dt)
        p1 = np.array(system.from_geodetic(lat[i], lon[i], h[i])).ravel()
        p2 = np.array(system.from_geodetic(lat2, lon2, h2)).ravel()
        assert np.allclose((p2 - p1) / dt, [vx[i], vy[i], vz[i]], atol=1e-3)


def test_external_picture_scored_against_adsb(tmp_path: Path, simulated) -> None:
    """A CAT062 picture = the truth shifted 30 m east, with the truth as CAT021 in the same file:
    every matched row is 30 m off (within resolution), and the pooled RMSE of tertiary.evaluation.accuracy
    ((2.15): σ²(k) = Σ e² / (N_k − 1) over the few aircraft of an epoch) lies in [30, 30·√2]."""
    ds, _, _ = simulated
    truth = ds.truth.filter(pl.col("icao24").fill_null("") != "")
    tracks = truth.select(
        pl.lit(0, pl.UInt32).alias("run"), pl.col("time").alias("epoch"), pl.col("truth_id").cast(pl.UInt64).alias("track_id"),
        pl.lit("cat062").alias("filter"), pl.lit("x").alias("method"), pl.col("x_m") + 30.0, "y_m", "z_m",
        "vx_mps", "vy_mps", "vz_mps", pl.lit([100.0] * 6).cast(pl.Array(pl.Float64, 6)).alias("cov_diag"),
        "alt_m", pl.col("icao24").alias("mode_s"))
    system = ds.origin
    recs = [(t, 62, r) for t, r in encode.cat062(tracks, system)] + [(t, 21, r) for t, r in encode.cat021(truth, system)]
    f = tmp_path / "both.ast"
    f.write_bytes(encode.interleave(recs))
    res = score_import(dataset.import_recordings([f], date="2021-10-07", origin=ds.scenario.origin))
    rows = match_external(res.external_tracks, res.truth)
    assert rows.height == tracks.height
    assert (rows["x_m"] - rows["true_x_m"] - 30.0).abs().max() < 0.35
    assert (rows["y_m"] - rows["true_y_m"]).abs().max() < 0.35
    m = res.external_metrics.filter(pl.col("segment") == "all")
    value = dict(zip(m["metric"], m["value"]))
    assert 29.8 <= value["rmse_horizontal_m"] <= 30.2 * 2**0.5
    assert value["rmse_height_m"] < 5.0
    assert (m["stage"] == "external").all() and m["method"].unique().to_list() == ["sdps-0-1"]


def test_nothing_decodable_is_a_clear_error(tmp_path: Path) -> None:
    f = tmp_path / "junk.bin"
    f.write_bytes(b"\x30\x00\x02hello")
    with pytest.raises(Exception, match="no CAT048, CAT021 or CAT062 record decoded.*length 2 below 3"):
        dataset.import_recordings([f], date="2024-01-01")
    r = CliRunner().invoke(app, ["import", "asterix", str(f), "--date", "2024-01-01", "--out", str(tmp_path / "o")])
    assert r.exit_code == 3 and "Traceback" not in r.output


def test_raw_stream_resynchronises_after_a_bad_length(tmp_path: Path) -> None:
    """A wrong length field in a raw recording costs that block, not the rest of the file."""
    blocks = [d for d, c in zip(*(lambda b: (b.data, b.cat))(capture.split_blocks(capture.read_recording(PCAP))))
              if c == 48][:6]
    broken = bytearray(blocks[2])
    broken[1:3] = (5000).to_bytes(2, "big")
    raw = tmp_path / "r.ast"
    raw.write_bytes(b"".join(blocks[:2]) + bytes(broken) + b"".join(blocks[3:]))
    got = capture.split_blocks(capture.read_recording(raw))
    assert got.data == blocks[:2] + blocks[3:]
    assert [p[2] for p in got.problems][0].startswith("CAT048 data block length 5000 beyond")
    assert "skipped to the next data block" in got.problems[1][2]


def test_flags_out_of_order_and_stale(tmp_path: Path) -> None:
    """Arrival order: a report older than its track's previous one is out of order; older than
    its radar's latest by more than --stale-s, stale; a garbage time of day is a reject that
    disturbs neither flag nor the other reports' times."""
    s48 = codec.spec(48).cv_record

    def rec(tod: float | int, trn: int) -> object:
        return s48.create({"010": (("SAC", 0), ("SIC", 1)), "140": tod, "040": (("RHO", 10.0), ("THETA", 5.0)),
                           "161": (0, ("TRN", trn))})
    recs = [rec(100.0, 1), rec(101.0, 2), rec(100.5, 1), rec(86400 * 128 + 9, 3), rec(102.0, 1), rec(80.0, 2)]
    raw = tmp_path / "o.ast"
    raw.write_bytes(b"".join(codec.datablock(48, [r]) for r in recs))
    res = dataset.import_recordings([raw], sites=_sites(tmp_path / "s.toml", codes=[(0, 1)]), date="2024-01-01",
                                    stale_s=10.0)
    r = res.reports
    assert r["local_track_id"].to_list() == [1, 2, 1, 1, 2] and res.rejects.height == 1
    assert r["out_of_order"].to_list() == [False, False, False, False, True]
    assert r["stale"].to_list() == [False, False, False, False, True]
    secs = (r["time"].dt.epoch("us").to_numpy() / 1e6) % 86400
    assert np.allclose(secs, [100.0, 101.0, 100.5, 102.0, 80.0])


def test_pcap_resynchronises_after_a_bad_record_header(tmp_path: Path, real: dataset.ImportResult) -> None:
    """A corrupted captured-length field costs that frame, not the rest of the capture."""
    import struct
    data = bytearray(PCAP.read_bytes())
    off = 24
    for _ in range(10):                                   # the 11th record header
        off += 16 + struct.unpack("<I", data[off + 8:off + 12])[0]
    data[off + 8:off + 12] = struct.pack("<I", 10**6)
    f = tmp_path / "bad.pcap"
    f.write_bytes(bytes(data))
    grams = capture.read_recording(f)
    assert len(grams.payloads) == 99 and "runs past the end" in grams.problems[0][2]
    assert "skipped to the next pcap record" in grams.problems[1][2]
    res = dataset.import_recordings([f], sites=_sites(tmp_path / "s.toml"))
    assert res.counts["distinct"] == 64          # the lost frame's twin on the other line carries its records
