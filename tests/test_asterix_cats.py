"""CAT001/002 (legacy radar), CAT004 (safety nets) and CAT020 (MLAT) import: recordings made
with libasterix's own encoder, the compiled walker against libasterix record for record (bytes
mutated too), the values, the contract and the rejects."""

from __future__ import annotations

import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import polars as pl
import pytest

import tertiary
from asterix_mutants import mutants
from tertiary.contract import TABLES
from tertiary.core.units import FT
from tertiary.io.asterix import codec, dataset, encode, fastcats, fastwalk, plots

DAY0 = datetime(2024, 3, 1, tzinfo=timezone.utc).timestamp()
SITES = """
[[radar]]
sac = 7
sic = 20
kind = "mlat"
lat_deg = 45.0
lon_deg = 16.0
alt_m = 100.0
sigma_range_m = 20.0
sigma_azimuth_deg = 0.5
max_range_m = 200000.0
scan_period_s = 1.0

[[radar]]
sac = 9
sic = 1
lat_deg = 45.5
lon_deg = 16.5
alt_m = 300.0
sigma_range_m = 70.0
sigma_azimuth_deg = 0.08
max_range_m = 400000.0
scan_period_s = 4.0
"""


def cat020_records(n: int = 6, t0: float = 3600.0) -> list[object]:
    s = codec.spec(20).cv_record
    out = []
    for i in range(n):
        items = {"010": (("SAC", 7), ("SIC", 20)), "020": (0x40,), "140": t0 + i,
                 "041": (("LAT", 45.0 + 0.01 * i), ("LON", 16.0 + 0.02 * i)), "161": (0, ("TRN", 100 + i % 2)),
                 "070": (0, 0, 0, 0, ("MODE3A", "1234")), "090": (("V", 0), ("G", 0), ("FL", 35.0 + i)),
                 "220": 0xABCDEF, "245": (("STI", 2), 0, ("CHR", "MLAT01  ")), "105": 3600.0 + 25 * i,
                 "500": {"SDP": (("X", 7.5), ("Y", 10.0), ("XY", 2.0 + i))}}
        if i % 3 == 2:                       # Cartesian only
            del items["041"]
            items["042"] = (("X", -1500.5), ("Y", 2500.0))
        out.append(s.create(items))
    return out


def cat001_records(t0: float) -> list[object]:
    u = codec.spec(1).cv_uap
    plot = u.cv_uaps["plot"].create({
        "010": (("SAC", 9), ("SIC", 1)), "020": (0x10,), "040": (("RHO", 40.5), ("THETA", 45.0)),
        "070": (0, 0, 0, 0, ("MODE3A", "4321")), "090": (("V", 0), ("G", 0), ("HGT", 120.25)),
        "141": math.fmod(t0, 512.0)})
    track = u.cv_uaps["track"].create({
        "010": (("SAC", 9), ("SIC", 1)), "020": (0x50,), "161": 77, "040": (("RHO", 100.25), ("THETA", 270.0)),
        "141": math.fmod(t0 + 1.0, 512.0)})
    return [plot, track]


def cat002_north(t: float) -> object:
    return codec.spec(2).cv_record.create({"010": (("SAC", 9), ("SIC", 1)), "000": 1, "030": t, "041": 4.0})


def cat004_stca(t: float, alert: int, a: int, b: int, call: str | None = "AFR123 ") -> object:
    items: dict[str, object] = {"010": (("SAC", 3), ("SIC", 4)), "000": 7, "020": t, "040": alert, "030": a,
                                "035": b, "070": {"TCA": 42.5, "MHS": 1800.0, "MVS": 500.0}}
    if call:
        items["170"] = {"AI1": call, "M31": (0, ("MODE3A", "1234"))}
        items["171"] = {"MS2": "BAW9   "}
    return codec.spec(4).cv_record.create(items)


def _blocks() -> dict[int, list[bytes]]:
    t0 = 7200.0
    return {
        20: [codec.datablock(20, cat020_records()[i:i + 2]) for i in range(0, 6, 2)],
        1: [codec.datablock(1, cat001_records(t0 + 4 * k)) for k in range(3)],
        2: [codec.datablock(2, [cat002_north(t0 + 4 * k) for k in range(3)])],
        4: [codec.datablock(4, [cat004_stca(t0 + k, 5, 12, 3) for k in range(3)] + [cat004_stca(t0, 6, 1, 2, None)])],
    }


BLOCKS = _blocks()


def _walk(cat: int, blocks: list[bytes]) -> tuple[np.ndarray, set[int]]:
    """Records per block and refused blocks of the compiled walker."""
    if cat == 1:
        _, _, _, block, _, _, bad = fastwalk.walk_select(blocks, fastcats.program(1, "plot"),
                                                         fastcats.program(1, "track"), 2)
    else:
        _, _, block, _, _, bad = fastwalk.walk(blocks, fastcats.program(cat))
    return np.bincount(block, minlength=len(blocks)), {k for k, _, _ in bad}


@pytest.mark.parametrize("cat", [1, 2, 4, 20])
def test_walker_accepts_and_refuses_as_libasterix(cat: int) -> None:
    """Block for block and record count for record count, on encoded and mutated bytes (CAT001:
    each record with the class its own I001/020 TYP names)."""
    blocks = BLOCKS[cat] + mutants(BLOCKS[cat], np.random.default_rng(cat), 100)
    counts, refused = _walk(cat, blocks)
    for k, b in enumerate(blocks):
        ref = codec.parse_block(b)
        assert (k in refused) == isinstance(ref, str), (cat, b.hex(), ref)
        if not isinstance(ref, str):
            assert counts[k] == len(ref), (cat, b.hex())


def test_walker_programs_cover_the_editions() -> None:
    """The walker reads the editions libasterix ships (newest of each); CAT001 has two classes."""
    assert {c: codec.EDITIONS[c] for c in (1, 2, 4, 20)} == {
        1: "Cat_001_1_4", 2: "Cat_002_1_2", 4: "Cat_004_1_13", 20: "Cat_020_1_11"}
    assert fastcats.program(1, "plot").names[:2] == fastcats.program(1, "track").names[:2] == ("010", "020")


def test_cat020_values_equal_libasterix_quantities() -> None:
    """Signed fields (southern, western positions; negative Cartesian) read as libasterix reads them."""
    s = codec.spec(20).cv_record
    recs = [s.create({"010": (("SAC", 1), ("SIC", 2)), "140": 86399.5, "041": (("LAT", lat), ("LON", lon)),
                      "042": (("X", x), ("Y", -x)), "090": (("V", 0), ("G", 0), ("FL", fl))})
            for lat, lon, x, fl in ((-33.9, -70.6, -1234.5, -5.25), (51.5, 179.9, 99999.5, 400.0))]
    frame = fastcats.decode_020([(codec.datablock(20, recs), {"file": "f", "datagram": 0}, math.nan, "raw", 0)], [])
    for row, rec in zip(frame.iter_rows(named=True), recs):
        assert row["lat_deg"] == codec.sub_qty(rec, "041", "LAT", "°")
        assert row["lon_deg"] == codec.sub_qty(rec, "041", "LON", "°")
        assert (row["x_m"], row["y_m"]) == (codec.sub_qty(rec, "042", "X", "m"), codec.sub_qty(rec, "042", "Y", "m"))
        assert row["flight_level"] == codec.sub_qty(rec, "090", "FL", "FL") and row["tod"] == 86399.5 * 128


def _import(tmp_path: Path, blocks: list[bytes]) -> dataset.ImportResult:
    rec, sites = tmp_path / "rec.ast", tmp_path / "sites.toml"
    rec.write_bytes(b"".join(blocks))
    sites.write_text(SITES)
    return dataset.import_recordings([rec], sites=sites, date="2024-03-01")


def test_cat020_reports_are_mlat_plots_that_validate(tmp_path: Path) -> None:
    res = _import(tmp_path, BLOCKS[20] + BLOCKS[20])            # two redundant lines
    rep = res.reports.sort("time")
    assert rep.height == 6 and res.counts["cat020_duplicates"] == 6
    assert res.radars.filter(pl.col("sac") == 7)["kind"].to_list() == ["mlat"]
    r0 = rep.row(0, named=True)
    assert r0["time"].timestamp() == DAY0 + 3600.0
    assert r0["local_track_id"] == 100 and r0["mode_s"] == "abcdef" and r0["callsign"] == "MLAT01"
    assert r0["mode_3a"] == "1234" and r0["altitude_m"] == pytest.approx(3500 * FT)
    assert r0["plot_lat_deg"] == pytest.approx(45.0, abs=1e-5) and r0["plot_lon_deg"] == pytest.approx(16.0, abs=1e-5)
    assert (r0["plot_sigma_x_m"], r0["plot_sigma_y_m"], r0["plot_sigma_xy_m"]) == (7.5, 10.0, 2.0)
    assert r0["plot_height_m"] == pytest.approx(3600 * FT)
    # the site's own position: x, y ~ 0, the range is the height above the site
    assert abs(r0["plot_x_m"]) < 1 and r0["range_m"] == pytest.approx(3600 * FT - 100.0, abs=1.0)
    cart = rep.row(2, named=True)                                   # Cartesian only
    assert (cart["plot_x_m"], cart["plot_y_m"]) == (-1500.5, 2500.0)
    assert cart["azimuth_deg"] == pytest.approx(math.degrees(math.atan2(-1500.5, 2500.0)) % 360)
    radars, _ = tertiary.validate(res.radars, "radars", strict=False)
    clean, rejects = tertiary.validate(rep, "reports", strict=False, radars=radars)
    assert clean.height == 6 and rejects.height == 0
    bad = rep.with_columns(pl.when(pl.col("local_track_id") == 101).then(9.0).otherwise(pl.col("plot_sigma_xy_m"))
                           .alias("plot_sigma_xy_m"))
    clean, rejects = tertiary.validate(bad, "reports", strict=False, radars=radars)
    assert clean.height == 3 and rejects["reason"].str.contains("not a covariance").all()
    lost = rep.with_columns(pl.lit(None, pl.Float64).alias("plot_x_m"))
    assert tertiary.validate(lost, "reports", strict=False, radars=radars)[0].height == 0


def test_cat020_of_a_radar_site_is_rejected(tmp_path: Path) -> None:
    res = _import(tmp_path, [codec.datablock(20, [codec.spec(20).cv_record.create(
        {"010": (("SAC", 9), ("SIC", 1)), "140": 10.0, "161": (0, ("TRN", 1)), "042": (("X", 10.0), ("Y", 10.0))})])])
    assert res.reports.height == 0
    assert res.rejects["reason"].str.contains("not of kind mlat").any()


def test_cat001_plots_and_tracks_with_cat002_time(tmp_path: Path) -> None:
    """Range, azimuth, Mode C, Mode 3/A; the truncated time of day made whole from CAT002
    (7 200 s is 14 periods of 512 s past 0: the reference decides which)."""
    res = _import(tmp_path, BLOCKS[2] + BLOCKS[1])
    rep = res.reports.sort("time")
    assert rep.height == 6
    t = np.array([x.timestamp() for x in rep["time"]]) - DAY0
    np.testing.assert_allclose(t, [7200, 7201, 7204, 7205, 7208, 7209])
    plot, track = rep.row(0, named=True), rep.row(1, named=True)
    assert plot["plot"] and plot["local_track_id"] == plots.PLOT_TRACK_BASE + 0o4321
    assert plot["range_m"] == pytest.approx(40.5 * 1852) and plot["azimuth_deg"] == pytest.approx(45.0)
    assert plot["altitude_m"] == pytest.approx(12025 * FT) and plot["mode_3a"] == "4321"
    assert not track["plot"] and track["local_track_id"] == 77 and track["range_m"] == pytest.approx(100.25 * 1852)
    assert res.antenna.row(0, named=True)["scan_period_s"] == 4.0
    radars, _ = tertiary.validate(res.radars, "radars", strict=False)
    assert tertiary.validate(rep, "reports", strict=False, radars=radars)[1].height == 0


def test_cat001_without_time_reference_is_rejected(tmp_path: Path) -> None:
    """A raw file (no capture time) without CAT002: the truncated time cannot be placed."""
    res = _import(tmp_path, BLOCKS[1][:1])
    assert res.reports.height == 0
    assert res.rejects["reason"].str.contains("no time reference").sum() == 2


def test_cat004_alerts_and_export_round_trip(tmp_path: Path) -> None:
    res = _import(tmp_path, BLOCKS[4])
    al = res.alerts.sort("alert_id")
    assert al.height == 2 and set(TABLES["alerts"].required) <= set(al.columns)
    a = al.row(0, named=True)
    assert a["method"] == "external:3/4" and (a["id_a"], a["id_b"]) == (3, 12)      # ordered pair
    assert a["callsign_b"] == "AFR123" and a["mode_3a_b"] == "1234" and a["mode_s_ident_a"] == "BAW9"
    assert a["alert_epochs"] == 3 and a["duration_s"] == 2.0 and a["t_start"].timestamp() == DAY0 + 7200
    assert (a["r_min_pred_m"], a["t_min_first_s"]) == (1800.0, 42.5)
    assert a["dz_min_pred_m"] == pytest.approx(500 * FT) and a["classification"] == plots.UNSCORED
    out = tmp_path / "alerts.ast"
    assert encode.export_alerts(al, out, 3, 4) == 3                       # start + end, start only
    back = dataset.external_alerts([out], date="2024-03-01").sort("alert_id")
    cols = ["id_a", "id_b", "t_start", "t_end", "r_min_pred_m", "t_min_first_s", "callsign_b", "mode_3a_b"]
    assert back.select(cols).equals(al.select(cols))


def test_malformed_blocks_are_rejects_with_the_edition(tmp_path: Path) -> None:
    cut = [b[:-3][:1] + (len(b) - 3).to_bytes(2, "big") + b[3:-3] for b in (BLOCKS[20][0], BLOCKS[1][0], BLOCKS[4][0])]
    good = BLOCKS[20][1]
    res = _import(tmp_path, cut + [good, bytes([99, 0, 4, 0])])
    reasons = res.rejects["reason"].to_list()
    for text in ("CAT020 record (edition 1.11)", "CAT001 record (edition 1.4)", "CAT004 record (edition 1.13)",
                 "category 99 not supported"):
        assert any(text in r for r in reasons), (text, reasons)
    assert res.reports.height == 2


def test_cli_imports_every_new_category_and_validate_reads_it(tmp_path: Path) -> None:
    """`tertiary import asterix` on a mixed recording, then `tertiary validate` on the dataset:
    every report accepted; an MLAT plot whose accuracy is no covariance rejected with the reason."""
    from typer.testing import CliRunner
    from tertiary.cli.commands import app
    rec, sites, out = tmp_path / "mixed.ast", tmp_path / "sites.toml", tmp_path / "ds"
    rec.write_bytes(b"".join(BLOCKS[2] + BLOCKS[1] + BLOCKS[20] + BLOCKS[4]))
    sites.write_text(SITES)
    r = CliRunner().invoke(app, ["import", "asterix", str(rec), "--sites", str(sites), "--date", "2024-03-01",
                                 "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "6 legacy radar reports (CAT001), 6 MLAT reports (CAT020)" in r.output and "2 STCA alert" in r.output
    assert pl.read_parquet(out / "alerts.parquet").height == 2
    r = CliRunner().invoke(app, ["validate", str(out)])
    assert r.exit_code == 0 and "not a covariance" not in r.output, r.output
    reports = pl.read_parquet(out / "reports.parquet")
    reports.with_columns(pl.when(pl.col("local_track_id") == 100).then(50.0).otherwise(pl.col("plot_sigma_xy_m"))
                         .alias("plot_sigma_xy_m")).write_parquet(out / "reports.parquet")
    r = CliRunner().invoke(app, ["validate", str(out)])
    assert r.exit_code == 0 and "not a covariance" in r.output, r.output


def test_cat004_episode_splits_at_a_gap() -> None:
    """One alert identifier and pair: messages 0, 1, 2 s and 100 s later are two episodes (gap 30 s)."""
    blk = codec.datablock(4, [cat004_stca(7200.0 + t, 5, 12, 3) for t in (0, 1, 2, 102)])
    raw = fastcats.decode_004([(blk, {"file": "f", "datagram": 0}, math.nan, "raw", 0)], [])
    alerts, rejects, _ = plots.alerts_table(raw, DAY0)
    assert not rejects and alerts["alert_epochs"].to_list() == [3, 1]
    assert alerts["duration_s"].to_list() == [2.0, 0.0]


def test_mutated_recordings_import_without_a_traceback(tmp_path: Path) -> None:
    """Flipped, cut and deleted bytes in every new category: the import ends with rejects rows
    (or a clear TertiaryError), never another exception; every reject has a reason."""
    from tertiary.core.errors import TertiaryError
    rng = np.random.default_rng(7)
    sites = tmp_path / "sites.toml"
    sites.write_text(SITES)
    for i in range(8):
        blocks = [b for cat in (2, 1, 20, 4) for b in mutants(BLOCKS[cat], rng, 2)]
        rec = tmp_path / f"m{i}.ast"
        rec.write_bytes(b"".join(blocks))
        try:
            res = dataset.import_recordings([rec], sites=sites, date="2024-03-01", skip_unknown=True)
        except TertiaryError:
            continue
        assert res.rejects["reason"].str.len_chars().min() > 0 if res.rejects.height else True


def test_cli_exports_a_pictures_alerts_as_cat004(tmp_path: Path) -> None:
    """`tertiary export asterix --alerts` writes the picture's alerts rows; importing the file
    gives back their pairs and times; an unknown picture names the ones with alerts."""
    from typer.testing import CliRunner
    from tertiary.cli.commands import app
    from tertiary.store.run_store import RunStore
    alerts = _import(tmp_path, BLOCKS[4]).alerts.with_columns(pl.lit("fused/information").alias("method"))
    run = tmp_path / "run"
    with RunStore.create(run) as store:
        store.write("alerts", alerts.select(list(TABLES["alerts"].required)))
    out = tmp_path / "stca.ast"
    r = CliRunner().invoke(app, ["export", "asterix", str(run), "--picture", "fused/information", "--alerts",
                                 "--out", str(out)])
    assert r.exit_code == 0 and "3 CAT004 STCA records of 2 alert episodes" in r.output, r.output
    back = dataset.external_alerts([out], date="2024-03-01")
    cols = ["id_a", "id_b", "t_start", "t_end"]
    assert back.sort(cols).select(cols).equals(alerts.sort(cols).select(cols))
    r = CliRunner().invoke(app, ["export", "asterix", str(run), "--picture", "singer/x", "--alerts", "--out",
                                 str(out)])
    assert r.exit_code != 0 and "fused/information" in r.output


def _layout(prog: fastwalk.Program) -> list[tuple[object, ...]]:
    """Per UAP slot: name, kind, fixed size or repetition, and for extended items (top level or
    subfield) the group sizes — what decides where each item of a record ends."""
    def ext(p1: int, p2: int) -> tuple[int, ...]:
        return tuple(int(g) for g in prog.groups[p1:p1 + p2])
    out = []
    for s, name in enumerate(prog.names):
        k, p1, p2 = int(prog.kind[s]), int(prog.p1[s]), int(prog.p2[s])
        if k == fastwalk.EXTENDED:
            out.append((name, k, ext(p1, p2)))
        elif k == fastwalk.COMPOUND:
            subs = range(prog.sub_start[s], prog.sub_start[s] + p2)
            out.append((name, k, tuple(ext(prog.sub_p1[j], prog.sub_p2[j]) if prog.sub_kind[j] == fastwalk.EXTENDED
                                       else (int(prog.sub_kind[j]), int(prog.sub_p1[j]), int(prog.sub_p2[j]))
                                       for j in subs)))
        else:
            out.append((name, k, p1, p2))
    return out


def _prefix(old: object, new: object) -> bool:
    """``old`` equals ``new`` but for extended items whose groups may be a prefix of the new ones."""
    if isinstance(old, tuple) and isinstance(new, tuple):
        if len(old) <= len(new) and all(isinstance(x, int) for x in (*old, *new)):
            return old == new[:len(old)]
        return len(old) == len(new) and all(_prefix(a, b) for a, b in zip(old, new))
    return old == new


@pytest.mark.parametrize("cat, older", [(1, ("1_2", "1_3")), (2, ("1_0", "1_1")), (4, ("1_12",)),
                                        (20, ("1_9", "1_10"))])
def test_older_editions_read_by_the_newest(cat: int, older: tuple[str, ...]) -> None:
    """Data blocks name no edition: the older editions libasterix ships lay their records out as
    the one read does (extended items may have gained groups), so it reads them."""
    _, gen = codec.lib()
    uaps = ("plot", "track") if cat == 1 else (None,)
    for ed in older:
        spec = getattr(gen, f"Cat_{cat:03d}_{ed}").cv_uap
        for uap in uaps:
            old = fastwalk.program(spec.cv_uaps[uap] if uap else spec.cv_record)
            assert _prefix(tuple(_layout(old)), tuple(_layout(fastcats.program(cat, uap)))), (cat, ed, uap)


def test_a_long_alert_exported_as_cat004_comes_back_as_one_episode(tmp_path: Path) -> None:
    """An STCA repeats an active alert every cycle: an episode of 100 s is exported as messages
    4 s apart and imported as one episode with its start and end, not split at the importer's
    30 s silence."""
    from datetime import datetime, timedelta, timezone
    from tertiary.io.asterix import encode
    t0 = datetime(2024, 3, 1, 10, 0, tzinfo=timezone.utc)
    alerts = pl.DataFrame({"method": ["information+imm_sym"], "id_a": [11], "id_b": [12], "t_start": [t0],
                           "t_end": [t0 + timedelta(seconds=100)]})
    out = tmp_path / "stca.ast"
    assert encode.export_alerts(alerts, out) == 26
    back = dataset.external_alerts([out], date="2024-03-01")
    assert back.height == 1
    assert back["t_start"][0] == t0 and back["t_end"][0] == t0 + timedelta(seconds=100)
