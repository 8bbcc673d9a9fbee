"""Per-radar evaluation against a reference: the table a radar engineer
checks before a radar joins the system.

Inputs: ``reports`` (the ``reports`` schema; a report is scored when its ``truth_id`` — in
simulation the generator's, on real data the reference aircraft found by joining ``mode_s`` to
the reference's ``icao24`` — is not null), ``radars`` and ``reference`` points (``truth_id``,
``time``, ``x_m, y_m, z_m`` system ENU, optional velocities, ``alt_m``, ``icao24``,
``squawk``/``mode_3a``; the ``truth`` table or :func:`tertiary.evaluation.reference.adsb_reference`).

Per report the reference is interpolated at the report's time stamp
(:func:`tertiary.evaluation.reference.interpolate_reference`) and seen from the radar site: range r*,
azimuth a*, range rate ṙ*, azimuth rate ȧ*. If the stamp is late by τ (report time − true
time), the measurement is that of time t − τ:
    Δr = r − r*(t) = b_r − ṙ* τ + ε_r,     Δa = a − a*(t) = b_a − ȧ* τ + ε_a           (1)
so ``range_bias_m`` b_r and ``time_offset_s`` τ come from one least-squares fit of (1) on the
range errors and ``azimuth_bias_deg`` b_a from the azimuth errors corrected by that τ;
``range_sigma_m`` / ``azimuth_sigma_deg`` are the residual standard deviations. Gross errors
(mis-association, clutter, outliers) are left out of the fits: |Δ − median| > ``outlier_k`` ×
1.4826 MAD (a robust σ).

Probability of detection: every (run, radar, aircraft, scan k = ⌊(t − phase)/T⌋) in which the
reference lies inside the radar's coverage (range ≤ ``max_range_m``, elevation ≥
``min_elevation_deg``) is expected; it is detected when a report of that aircraft carries that
scan. ``pd`` per range ring (segment ``range:lo-hikm``) and overall; the cone of silence is
inside the coverage by this definition, so it shows as a low Pd at short range.

Identity: ``mode_s_correct_frac`` (reported address = reference ``icao24``),
``mode_3a_correct_frac`` (code = reference ``squawk``/``mode_3a`` at that time),
``mode_c_correct_frac`` (|Mode C − reference altitude| ≤ ``mode_c_tolerance_m``, 200 ft).

Output: ``metrics`` rows, stage ``radar``, method = radar id (as text), with the sample sizes
``n_reports``, ``n_expected``, ``n_mode_s``, ``n_mode_3a``, ``n_mode_c``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.errors import DataError
from tertiary.core.units import FT
from tertiary.evaluation.picture_metrics import band_labels
from tertiary.evaluation.reference import interpolate_reference

__all__ = ["RadarEvalConfig", "radar_errors", "detections", "radar_metrics"]

STAGE = "radar"


@dataclass(frozen=True)
class RadarEvalConfig:
    range_rings_m: tuple[float, ...] = tuple(float(v) for v in range(0, 300_001, 25_000))
    outlier_k: float = 5.0
    mode_c_tolerance_m: float = 200 * FT
    max_gap_s: float = 10.0


def _seconds(s: pl.Series) -> NDArray[np.float64]:
    return s.dt.epoch("us").to_numpy().astype(np.float64) / 1e6


def _polar(radars: pl.DataFrame, rid: NDArray, pos: NDArray[np.float64], vel: NDArray[np.float64],
           origin: geo.LocalFrame) -> NDArray[np.float64]:
    """(n, 5) range, azimuth (deg), elevation (deg), range rate (m/s), azimuth rate (deg/s) of
    system-frame positions/velocities seen from each row's radar (a loop over radars only)."""
    out = np.full((len(rid), 5), np.nan)
    for row in radars.iter_rows(named=True):
        sel = np.flatnonzero(rid == row["radar_id"])
        if not sel.size:
            continue
        site = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
        p, v, _ = geo.frame_to_frame(pos[sel], origin, site, vel=vel[sel])
        rng, az, el = geo.enu_to_polar(p[:, 0], p[:, 1], p[:, 2])
        h2 = p[:, 0] ** 2 + p[:, 1] ** 2
        out[sel] = np.stack([rng, az, el, np.einsum("ij,ij->i", p, v) / rng,
                             np.degrees((p[:, 1] * v[:, 0] - p[:, 0] * v[:, 1]) / h2)], axis=1)
    return out


def radar_errors(reports: pl.DataFrame, radars: pl.DataFrame, reference: pl.DataFrame, origin: geo.LocalFrame,
                 cfg: RadarEvalConfig = RadarEvalConfig()) -> pl.DataFrame:
    """Scored reports (``truth_id`` not null and an evaluated reference at their time) with
    ``err_range_m``, ``err_azimuth_deg``, ``ref_range_m``, ``ref_range_rate_mps``,
    ``ref_azimuth_rate_dps``, ``ref_alt_m`` and the reference identity ``ref_icao24`` /
    ``ref_mode_3a`` (null when the reference has none)."""
    for c in ("radar_id", "time", "range_m", "azimuth_deg", "truth_id"):
        if c not in reports.columns:
            raise DataError(f"reports table is missing column {c} (needed to score radars)")
    rep = reports.filter(pl.col("truth_id").is_not_null())
    ref = interpolate_reference(reference, rep.select("truth_id", "time"), cfg.max_gap_s)
    ok = (ref["status"] == "evaluated").to_numpy()
    rep, ref = rep.filter(ok), ref.filter(ok)
    pos = ref.select("true_x_m", "true_y_m", "true_z_m").to_numpy()
    vel = np.nan_to_num(ref.select("true_vx_mps", "true_vy_mps", "true_vz_mps").to_numpy())
    pol = _polar(radars, rep["radar_id"].to_numpy(), pos, vel, origin)
    out = rep.with_columns(
        pl.Series("ref_range_m", pol[:, 0]), pl.Series("ref_range_rate_mps", pol[:, 3]),
        pl.Series("ref_azimuth_rate_dps", pol[:, 4]), pl.Series("ref_alt_m", ref["true_alt_m"]),
        pl.Series("err_range_m", rep["range_m"].to_numpy() - pol[:, 0]),
        pl.Series("err_azimuth_deg", geo.wrap_deg(rep["azimuth_deg"].to_numpy() - pol[:, 1])))
    return out.join(_identity(reference, out), on=["truth_id", "time"], how="left")


def _identity(reference: pl.DataFrame, rep: pl.DataFrame) -> pl.DataFrame:
    """Reference icao24 / Mode 3/A code at each scored report's time (last reference row at or
    before it)."""
    code = "mode_3a" if "mode_3a" in reference.columns else "squawk"
    cols = [pl.col(c).cast(pl.String).alias(f"ref_{n}") for c, n in (("icao24", "icao24"), (code, "mode_3a"))
            if c in reference.columns]
    keys = rep.select("truth_id", "time").unique()
    if not cols:
        return keys.with_columns(pl.lit(None, dtype=pl.String).alias("ref_icao24"),
                                 pl.lit(None, dtype=pl.String).alias("ref_mode_3a"))
    ident = reference.select("truth_id", pl.col("time").alias("__t"), *cols).sort("__t")
    out = keys.sort("time").join_asof(ident, left_on="time", right_on="__t", by="truth_id", strategy="nearest",
                                      check_sortedness=False).drop("__t")
    for n in ("ref_icao24", "ref_mode_3a"):
        if n not in out.columns:
            out = out.with_columns(pl.lit(None, dtype=pl.String).alias(n))
    return out


def _robust(x: pl.Expr, k: float) -> pl.Expr:
    """Rows within k robust σ (1.4826 MAD) of the radar's median."""
    med = x.median().over("radar_id")
    mad = (x - med).abs().median().over("radar_id") * 1.4826
    return (x - med).abs() <= k * pl.max_horizontal(mad, pl.lit(1e-9))


def _fit(err: pl.DataFrame, k: float) -> pl.DataFrame:
    """Per radar: b_r, τ by least squares of eq. (1) on the inlying range errors, then b_a."""
    g = err.filter(_robust(pl.col("err_range_m"), k) & _robust(pl.col("err_azimuth_deg"), k)).with_columns(
        (-pl.col("ref_range_rate_mps")).alias("__u"))
    s = g.group_by("radar_id").agg(
        pl.len().alias("n"), pl.col("__u").mean().alias("mu"), pl.col("err_range_m").mean().alias("my"),
        ((pl.col("__u") - pl.col("__u").mean()) ** 2).sum().alias("suu"),
        ((pl.col("__u") - pl.col("__u").mean()) * (pl.col("err_range_m") - pl.col("err_range_m").mean())).sum()
        .alias("suy"))
    s = s.with_columns(pl.when(pl.col("suu") > 0).then(pl.col("suy") / pl.col("suu")).otherwise(0.0).alias("tau"))
    s = s.with_columns((pl.col("my") - pl.col("tau") * pl.col("mu")).alias("b_r"))
    g = g.join(s.select("radar_id", "tau", "b_r"), on="radar_id").with_columns(
        (pl.col("err_range_m") - pl.col("b_r") - pl.col("__u") * pl.col("tau")).alias("__res_r"),
        (pl.col("err_azimuth_deg") + pl.col("ref_azimuth_rate_dps") * pl.col("tau")).alias("__az"))
    return g.group_by("radar_id").agg(
        pl.col("b_r").first().alias("range_bias_m"), pl.col("__res_r").std().alias("range_sigma_m"),
        pl.col("__az").mean().alias("azimuth_bias_deg"), pl.col("__az").std().alias("azimuth_sigma_deg"),
        pl.col("tau").first().alias("time_offset_s"), pl.len().cast(pl.Float64).alias("n_reports"))


def detections(reports: pl.DataFrame, radars: pl.DataFrame, reference: pl.DataFrame, origin: geo.LocalFrame,
               cfg: RadarEvalConfig = RadarEvalConfig()) -> pl.DataFrame:
    """Expected (run, radar, aircraft, scan) with the reference range and ``detected``."""
    runs = reports.select("run").unique() if "run" in reports.columns else pl.DataFrame({"run": [0]})
    rad = radars.select("radar_id", pl.col("scan_period_s"), pl.col("max_range_m"),
                        (pl.col("scan_phase_s") if "scan_phase_s" in radars.columns else pl.lit(0.0)).alias("phase"),
                        (pl.col("min_elevation_deg") if "min_elevation_deg" in radars.columns else pl.lit(-90.0))
                        .alias("min_el"))
    ref = reference.select("truth_id", "time", "x_m", "y_m", "z_m").join(rad, how="cross")
    pol = _polar(radars, ref["radar_id"].to_numpy(), ref.select("x_m", "y_m", "z_m").to_numpy(),
                 np.zeros((ref.height, 3)), origin)
    t0 = float(min(_seconds(reference["time"]).min(), _seconds(reports["time"]).min()))

    def scan() -> pl.Expr:
        return (((pl.col("time").dt.epoch("us") / 1e6 - t0 - pl.col("phase")) / pl.col("scan_period_s"))
                .floor().cast(pl.Int64).alias("scan"))

    ref = ref.with_columns(pl.Series("__r", pol[:, 0]), pl.Series("__el", pol[:, 2])).filter(
        (pl.col("__r") <= pl.col("max_range_m")) & (pl.col("__el") >= pl.col("min_el")))
    exp = ref.with_columns(scan()).group_by("radar_id", "truth_id", "scan").agg(pl.col("__r").mean().alias("ref_range_m"))
    rep = reports.filter(pl.col("truth_id").is_not_null())
    if "run" not in rep.columns:
        rep = rep.with_columns(pl.lit(0, dtype=pl.UInt32).alias("run"))
    det = (rep.join(rad, on="radar_id").with_columns(scan()).select("run", "radar_id", "truth_id", "scan").unique()
           .with_columns(pl.lit(True).alias("detected")))
    return (exp.join(runs, how="cross").join(det, on=["run", "radar_id", "truth_id", "scan"], how="left")
            .with_columns(pl.col("detected").fill_null(False)))


def _ring(col: str, edges: tuple[float, ...]) -> pl.Expr:
    return band_labels(pl.col(col), edges, "range", 1000.0, "km")


def radar_metrics(reports: pl.DataFrame, radars: pl.DataFrame, reference: pl.DataFrame, origin: geo.LocalFrame,
                  cfg: RadarEvalConfig = RadarEvalConfig()) -> pl.DataFrame:
    """The per-radar ``metrics`` rows (stage ``radar``, method = radar id) of the module docstring."""
    err = radar_errors(reports, radars, reference, origin, cfg)
    n_runs = pl.lit(reports["run"].n_unique() if "run" in reports.columns else 1, dtype=pl.UInt32).alias("n_runs")
    fit = _fit(err, cfg.outlier_k).with_columns(pl.lit("all").alias("segment"))
    ident = err.group_by("radar_id").agg(
        *[(pl.col(a).str.to_lowercase() == pl.col(b).str.to_lowercase()).filter(pl.col(a).is_not_null()
                                                                                 & pl.col(b).is_not_null())
          .mean().alias(f"{n}_correct_frac") for a, b, n in (("mode_s", "ref_icao24", "mode_s"),
                                                             ("mode_3a", "ref_mode_3a", "mode_3a"))
          if a in err.columns],
        *[(pl.col(a).is_not_null() & pl.col(b).is_not_null()).sum().cast(pl.Float64).alias(f"n_{n}")
          for a, b, n in (("mode_s", "ref_icao24", "mode_s"), ("mode_3a", "ref_mode_3a", "mode_3a")) if a in err.columns],
        *([((pl.col("altitude_m") - pl.col("ref_alt_m")).abs() <= cfg.mode_c_tolerance_m)
           .filter(pl.col("altitude_m").is_not_null()).mean().alias("mode_c_correct_frac"),
           pl.col("altitude_m").is_not_null().sum().cast(pl.Float64).alias("n_mode_c")]
          if "altitude_m" in err.columns else []),
    ).with_columns(pl.lit("all").alias("segment"))
    det = detections(reports, radars, reference, origin, cfg).with_columns(_ring("ref_range_m", cfg.range_rings_m)
                                                                           .alias("ring"))
    pd = pl.concat([
        det.group_by("radar_id").agg(pl.col("detected").mean().alias("pd"),
                                     pl.len().cast(pl.Float64).alias("n_expected")).with_columns(pl.lit("all").alias("segment")),
        det.group_by("radar_id", pl.col("ring").alias("segment")).agg(
            pl.col("detected").mean().alias("pd"), pl.len().cast(pl.Float64).alias("n_expected"))
        .select("radar_id", "pd", "n_expected", "segment")])
    parts = [w.unpivot(index=["radar_id", "segment"], variable_name="metric") for w in (fit, ident, pd)]
    out = pl.concat(parts, how="vertical_relaxed").filter(pl.col("value").is_not_null() & pl.col("value").is_finite())
    return out.select(pl.lit(STAGE).alias("stage"), pl.col("radar_id").cast(pl.String).alias("method"), "metric",
                      "segment", pl.col("value").cast(pl.Float64), n_runs).sort("method", "metric", "segment")
