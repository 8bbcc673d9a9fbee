"""Requirements with pass/fail: an editable TOML, its validating loader, and
:func:`check_requirements` turning the ``metrics`` table into the ``requirements`` table.

File format: see ``datasets/requirements/example.toml`` (example values, not quotations of any
standard). ``[settings]``: ``confidence`` (default 0.95), ``samples_per_independent`` (default
10: consecutive accuracy samples of a track are correlated, so that many count as one
independent sample), ``min_samples`` (default 30). Each ``[[requirement]]``: ``name``,
``metric``, ``threshold``, optional ``op`` (``"<="`` default, or ``">="``), ``breakdown``
(metrics segment, default ``"all"``), ``stage`` (default ``"evaluation"``), ``method`` (one
picture; default every picture) and ``samples_metric`` (the metric holding the sample size;
default from the metric's name, :data:`SAMPLES`).

Verdict rule (α = 1 − confidence; n = independent samples):

* ``fail`` when the point value breaks the threshold (whatever n);
* otherwise ``pass`` when a one-sided (1 − α) confidence bound on the metric also meets it and
  n ≥ ``min_samples``, else ``insufficient``. The bound depends on the metric's kind:

  - RMS (``*rms*``, ``rmse_*``), n = samples / samples_per_independent: the RMS² of n
    zero-mean Gaussian errors is σ² χ²_n / n, so σ ≤ RMS·√(n / χ²_{n; α}) at 1 − α     (1)
  - percentiles / max (``p95_*``, ``p99_*``, ``max_*``): no parametric bound; a pass needs
    n ≥ ln α / ln q independent samples (q = 0.95, 0.99; the sample maximum then bounds the
    q-quantile at 1 − α: 59 for p95, 299 for p99)                                        (2)
  - proportions (``prob_*``, ``*_frac``, ``pd``): Wilson score bound with n trials          (3)
  - rates (``*_per_hour``), exposure H hours, k = value·H events: exact Poisson bound
    λ ≤ χ²_{2k+2; 1−α} / (2H) (0 events in H hours pass "≤ r" only when H ≥ 3.0/r at 95 %) (4)
  - anything else (counts, latency, biases): the point value; pass needs n ≥ min_samples.

``n_samples`` in the output is the raw sample size (accuracy rows, update intervals, Mode S
rows, or exposure hours for a rate).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from tertiary.core.distributions import chi2_ppf, norm_ppf
from tertiary.core.errors import DataError

__all__ = ["Requirement", "Requirements", "SAMPLES", "load_requirements", "check_requirements",
           "requirements_schema", "example_path", "metric_kind"]

#: sample-size metric of each metric (picture_metrics / radar_eval emit them beside the values)
SAMPLES: dict[str, str] = {
    "prob_update": "n_update_intervals", "mode_s_correct_frac": "n_mode_s",
    "id_changes_per_hour": "aircraft_hours", "track_breaks_per_hour": "aircraft_hours",
    "false_tracks_per_hour": "picture_hours", "duplicate_tracks_per_hour": "picture_hours", "pd": "n_expected",
    "mode_3a_correct_frac": "n_mode_3a", "mode_c_correct_frac": "n_mode_c",
    "callsign_correct_frac": "n_callsign", "flight_level_correct_frac": "n_flight_level",
}
_DEFAULT_SAMPLES = {"evaluation": "n_points", "radar": "n_reports"}
_OPS = ("<=", ">=")
_REQ_KEYS = {"name", "metric", "threshold", "op", "breakdown", "stage", "method", "samples_metric"}
_SETTINGS = {"confidence": (0.5, 1.0), "samples_per_independent": (1.0, math.inf), "min_samples": (0.0, math.inf)}


@dataclass(frozen=True)
class Requirement:
    name: str
    metric: str
    threshold: float
    op: str = "<="
    breakdown: str = "all"
    stage: str = "evaluation"
    method: str | None = None
    samples_metric: str | None = None


@dataclass(frozen=True)
class Requirements:
    items: tuple[Requirement, ...]
    confidence: float = 0.95
    samples_per_independent: float = 10.0
    min_samples: float = 30.0
    source: str = field(default="", compare=False)


def example_path() -> Path:
    """The shipped example file: ``tertiary/datasets/requirements/example.toml`` in an installed
    wheel, ``datasets/requirements/example.toml`` in a source checkout."""
    package = Path(__file__).resolve().parents[1]
    installed = package / "datasets" / "requirements" / "example.toml"
    return installed if installed.is_file() else package.parent / "datasets" / "requirements" / "example.toml"


def metric_kind(metric: str) -> str:
    """``rms``, ``quantile``, ``proportion``, ``rate`` or ``point`` (see the module docstring)."""
    if metric.startswith(("p95_", "p99_", "max_")):
        return "quantile"
    if "rms" in metric:
        return "rms"
    if metric.startswith("prob_") or metric.endswith("_frac") or metric == "pd":
        return "proportion"
    if metric.endswith("_per_hour"):
        return "rate"
    return "point"


# --------------------------------------------------------------------------- loading


def _bad(path: str, key: str, why: str) -> DataError:
    return DataError(f"{key}: {why}", path=path)


def _requirement(raw: Any, i: int, path: str) -> Requirement:
    where = f"requirement[{i}]"
    if not isinstance(raw, dict):
        raise _bad(path, where, "must be a table")
    unknown = sorted(set(raw) - _REQ_KEYS)
    if unknown:
        raise _bad(path, f"{where}.{unknown[0]}", f"unknown key (expected {', '.join(sorted(_REQ_KEYS))})")
    for key in ("name", "metric", "threshold"):
        if key not in raw:
            raise _bad(path, f"{where}.{key}", "missing")
    for key in ("name", "metric", "op", "breakdown", "stage", "method", "samples_metric"):
        if key in raw and (not isinstance(raw[key], str) or not raw[key].strip()):
            raise _bad(path, f"{where}.{key}", f"must be a non-empty string, got {raw[key]!r}")
    thr = raw["threshold"]
    if isinstance(thr, bool) or not isinstance(thr, (int, float)) or not math.isfinite(thr):
        raise _bad(path, f"{where}.threshold", f"must be a finite number, got {thr!r}")
    if raw.get("op", "<=") not in _OPS:
        raise _bad(path, f"{where}.op", f"must be one of {', '.join(_OPS)}, got {raw['op']!r}")
    if metric_kind(raw["metric"]) == "proportion" and not 0.0 <= thr <= 1.0:
        raise _bad(path, f"{where}.threshold", f"a fraction must be in [0, 1], got {thr!r}")
    return Requirement(**{**raw, "threshold": float(thr)})


def load_requirements(path: str | Path) -> Requirements:
    """Read and validate a requirements TOML; any problem is a :class:`DataError` naming the
    file and the key (``requirement[2].threshold``, ``settings.confidence`` …)."""
    p = str(path)
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror or exc}", path=p) from exc
    except UnicodeDecodeError as exc:
        raise DataError(f"not UTF-8 text: byte {exc.start}", path=p) from exc
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"not valid TOML: {exc}", path=p) from exc
    unknown = sorted(set(data) - {"settings", "requirement"})
    if unknown:
        raise _bad(p, unknown[0], "unknown table (expected settings, requirement)")
    settings = data.get("settings", {})
    for key, value in settings.items():
        if key not in _SETTINGS:
            raise _bad(p, f"settings.{key}", f"unknown key (expected {', '.join(_SETTINGS)})")
        lo, hi = _SETTINGS[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi \
                or (key == "confidence" and value in (lo, hi)):
            raise _bad(p, f"settings.{key}", f"must be a number in {'(' if key == 'confidence' else '['}"
                                               f"{lo:g}, {hi:g}{')' if key == 'confidence' else ']'}, got {value!r}")
    reqs = data.get("requirement", [])
    if not isinstance(reqs, list) or not reqs:
        raise _bad(p, "requirement", "no [[requirement]] entry")
    items = tuple(_requirement(r, i, p) for i, r in enumerate(reqs))
    names = [r.name for r in items]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup:
        raise _bad(p, f"requirement[{names.index(dup, names.index(dup) + 1)}].name", f"duplicate name {dup!r}")
    return Requirements(items=items, **{k: float(v) for k, v in settings.items()}, source=p)


# --------------------------------------------------------------------------- checking


def requirements_schema() -> dict[str, pl.DataType]:
    """Columns of the ``requirements`` table (the first seven name the requirement and its verdict)."""
    return {"requirement": pl.String(), "metric": pl.String(), "breakdown": pl.String(), "threshold": pl.Float64(),
            "value": pl.Float64(), "n_samples": pl.Float64(), "verdict": pl.String(), "method": pl.String(),
            "stage": pl.String(), "op": pl.String(), "bound": pl.Float64(), "confidence": pl.Float64()}


def _bounds(kind: np.ndarray, upper: np.ndarray, value: np.ndarray, n: np.ndarray, n_ind: np.ndarray,
            alpha: float) -> np.ndarray:
    """The one-sided (1 − α) bound of (1)–(4) on the side that must meet the threshold."""
    out = value.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        nn = np.maximum(n_ind, 1e-9)
        rms = np.where(upper, np.sqrt(nn / chi2_ppf(alpha, nn)), np.sqrt(nn / chi2_ppf(1 - alpha, nn)))
        out = np.where(kind == "rms", value * rms, out)
        z = norm_ppf(1 - alpha)
        p, m = np.clip(value, 0.0, 1.0), np.maximum(n, 1e-9)
        centre, half = (p + z * z / (2 * m)) / (1 + z * z / m), z * np.sqrt(p * (1 - p) / m + z * z / (4 * m * m)) / (1 + z * z / m)
        out = np.where(kind == "proportion", np.where(upper, centre + half, centre - half), out)
        k = np.maximum(value * n, 0.0)
        lam_hi = chi2_ppf(1 - alpha, 2 * k + 2) / (2 * m)
        lam_lo = np.where(k > 0, chi2_ppf(alpha, np.maximum(2 * k, 1e-9)) / (2 * m), 0.0)
        out = np.where(kind == "rate", np.where(upper, lam_hi, lam_lo), out)
    return out


def _verdicts(rows: pl.DataFrame, reqs: Requirements) -> pl.DataFrame:
    alpha = 1.0 - reqs.confidence
    kind = np.array([metric_kind(m) for m in rows["metric"]])          # one per requirement row
    upper = (rows["op"] == "<=").to_numpy()
    value = rows["value"].fill_null(np.nan).to_numpy()
    n = rows["n_samples"].fill_null(0.0).to_numpy()
    correlated = np.isin(kind, ["rms", "quantile", "point"]) & (rows["stage"] == "evaluation").to_numpy()
    n_ind = np.where(correlated, n / reqs.samples_per_independent, n)
    bound = _bounds(kind, upper, value, n, n_ind, alpha)
    thr = rows["threshold"].to_numpy()
    q = np.array([0.99 if m.startswith("p99_") else 0.95 for m in rows["metric"]])
    need = np.where(kind == "quantile", np.maximum(reqs.min_samples, np.log(alpha) / np.log(q)), reqs.min_samples)
    need = np.where(kind == "rate", 0.0, need)                        # the Poisson bound carries the sample size
    breaks = np.where(upper, value > thr, value < thr)
    meets = np.where(upper, bound <= thr, bound >= thr) & (n_ind >= need)
    verdict = np.where(np.isnan(value), "insufficient", np.where(breaks, "fail", np.where(meets, "pass", "insufficient")))
    return rows.with_columns(pl.Series("bound", bound), pl.Series("verdict", verdict),
                             pl.lit(reqs.confidence).alias("confidence"))


def check_requirements(metrics: pl.DataFrame, reqs: Requirements) -> pl.DataFrame:
    """The ``requirements`` table: one row per requirement and picture (``method``) of its
    stage in ``metrics``; a metric missing for a picture/segment gives value null and
    ``insufficient`` (never ``fail``: nothing was measured)."""
    req = pl.DataFrame([{"requirement": r.name, "metric": r.metric, "breakdown": r.breakdown, "threshold": r.threshold,
                         "op": r.op, "stage": r.stage, "only": r.method,
                         "samples_metric": r.samples_metric or SAMPLES.get(r.metric, _DEFAULT_SAMPLES.get(r.stage, "n_points"))}
                        for r in reqs.items], schema_overrides={"only": pl.String})
    methods = metrics.select("stage", "method").unique()
    rows = pl.concat([
        req.filter(pl.col("only").is_null()).join(methods, on="stage", how="left"),
        req.filter(pl.col("only").is_not_null()).with_columns(pl.col("only").alias("method"))],
        how="vertical_relaxed").with_columns(pl.col("method").fill_null(""))
    vals = metrics.select("stage", "method", "metric", pl.col("segment").alias("breakdown"), "value")
    samples = vals.rename({"metric": "samples_metric", "value": "n_samples"})
    rows = (rows.join(vals, on=["stage", "method", "metric", "breakdown"], how="left")
            .join(samples, on=["stage", "method", "samples_metric", "breakdown"], how="left"))
    out = _verdicts(rows, reqs)
    cols = requirements_schema()
    return out.select([pl.col(c).cast(t) for c, t in cols.items()]).sort("requirement", "method")
