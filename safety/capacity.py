"""Accuracy versus capacity: how many aircraft a controller may hold at a given risk, as a
function of the position accuracy (monograph §5.3, (5.18)–(5.21), figs. 5.2/5.3).

Units: σ in metres (the coordinate RMS error; the seed's fig. 5.2 uses the range RMS σ_d),
volumes in m³, probabilities dimensionless, n = number of aircraft in the zone.

Seed model (faithful, as printed)
---------------------------------
    V_об  = (4/3) π (6σ)³                                  (5.18)  safety sphere
    P_пij = V_ВС / (V_зо − V_ВС)                           (5.19)  (not used by (5.21))
    P_нп  = (V_об − V_ВС) / V_об                           (5.20)  "probability of non-entry"
    P_поб = (n − 1) V_об / (V_зо − (n − 1) V_об) · P_нп     (5.21)

(5.21) is odds-shaped: it exceeds 1 once (n − 1)V_об > V_зо/2, has a pole at
n = 1 + V_зо/V_об (139.2 for σ = 200 m, V_зо = 10¹² m³) and is negative beyond it, so
:func:`ppob_seed` returns the raw value with ``valid = (n − 1)V_об < V_зо/2``. Solving
(5.21) ≤ P* for n gives the closed form of :func:`nmax_seed`,

    n_max(σ) = 1 + floor( P* V_зо / ( V_об(σ) (P_нп(σ) + P*) ) ),

so n_max ∝ σ⁻³. **With the printed volumes (V_зо ≤ 10¹⁴ m³, σ ≥ 50 m) the seed model admits
n = 1 at P* = 10⁻⁶**: no second aircraft (n = 2 needs V_об ≤ 1.0e6 m³, σ ≤ 10.3 m at 10¹²).
Fig. 5.3 must therefore rest on other parameters; P* and V_зо are always parameters here.

Sounder model (separate, opt-in)
--------------------------------
Aircraft independent and uniform in V_зо; a pair conflicts when one lies within R_c of the
other, p = (4/3)π R_c³ / V_зо with R_c ∈ {``"6sigma"`` (reproduces (5.21) to first order),
``"12sigma"`` (two 6σ spheres intersect), ``"separation"`` (Δr + 3√2·σ: separation minimum
plus three sigma of the relative error)} or a number of metres:

    P_1(n)   = 1 − (1 − p)^(n − 1)           a given aircraft conflicts with any other
    P_any(n) = 1 − (1 − p)^(n(n − 1)/2)      any pair conflicts

and an optional hourly rate −ln(1 − P)/T_corr (:func:`rate_per_hour`). This fixes four oddities
of the printed model (odds shape, the P_нп factor, n − 1 instead of pairs, point-in-sphere);
it keeps the absence of exposure time unless a rate is asked for.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal, NamedTuple

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from tertiary.contract import TABLES

__all__ = [
    "V_BC_M3",
    "V_ZO_M3",
    "SeedRisk",
    "v_ob",
    "p_pij",
    "p_np",
    "ppob_seed",
    "nmax_seed",
    "conflict_radius",
    "ppob_sound",
    "nmax_sound",
    "rate_per_hour",
    "ppob_curves",
    "capacity_curve",
    "capacity_from_metrics",
    "CAPACITY_P_STAR",
    "CAPACITY_V_ZO_M3",
    "CAPACITY_N",
]

#: default aircraft volume V_ВС (m³; the seed quotes 4000…8000)
V_BC_M3 = 6000.0
#: default near-zone volume V_зо (m³; the seed quotes 10¹⁰…10¹⁴)
V_ZO_M3 = 1e12

#: the run's capacity figures: parameters at which the models discriminate
#: between pictures. V_зо = 10¹⁴ m³ is a 100 km × 100 km × 10 km zone — the size of the default
#: terminal area; at the printed P* = 10⁻⁶ and V_зо = 10¹² every realistic σ gives n_max = 1.
CAPACITY_P_STAR = 1e-3
CAPACITY_V_ZO_M3 = 1e14
#: P(n) is reported for this many aircraft in the zone (metric ``p_conflict_n20``)
CAPACITY_N = 20

RcOption = Literal["6sigma", "12sigma", "separation"] | float


# --------------------------------------------------------------------------- seed model


def v_ob(sigma: ArrayLike) -> NDArray[np.float64]:
    """Safety-sphere volume V_об = (4/3)π(6σ)³ (5.18), m³ (σ in m)."""
    s = np.asarray(sigma, dtype=np.float64)
    return 4.0 / 3.0 * np.pi * (6.0 * s) ** 3


def p_pij(v_bc: float = V_BC_M3, v_zo: float = V_ZO_M3) -> float:
    """P_пij = V_ВС / (V_зо − V_ВС) (5.19); printed but unused by (5.21)."""
    return v_bc / (v_zo - v_bc)


def p_np(sigma: ArrayLike, v_bc: float = V_BC_M3) -> NDArray[np.float64]:
    """P_нп = (V_об − V_ВС) / V_об (5.20)."""
    vo = v_ob(sigma)
    return (vo - v_bc) / vo


class SeedRisk(NamedTuple):
    """(5.21) value and its validity flag ((n − 1)V_об < V_зо/2)."""

    p: NDArray[np.float64]
    valid: NDArray[np.bool_]


def ppob_seed(n: ArrayLike, sigma: ArrayLike, v_bc: float = V_BC_M3, v_zo: float = V_ZO_M3) -> SeedRisk:
    """Seed safety-region intersection probability P_поб (5.21), exactly as printed, broadcast
    over ``n`` and ``sigma`` (m). Returns the raw value (> 1 past (n − 1)V_об = V_зо/2, a pole at
    n = 1 + V_зо/V_об, negative beyond) and ``valid``."""
    nn = np.asarray(n, dtype=np.float64)
    vo = v_ob(sigma)
    a = (nn - 1.0) * vo
    with np.errstate(divide="ignore", invalid="ignore"):
        p = a / (v_zo - a) * p_np(sigma, v_bc)
    return SeedRisk(p, np.asarray(a < 0.5 * v_zo))


def nmax_seed(sigma: ArrayLike, p_star: float = 1e-6, v_bc: float = V_BC_M3, v_zo: float = V_ZO_M3
              ) -> NDArray[np.int64]:
    """Largest n with (5.21) ≤ P*: 1 + floor(P* V_зо / (V_об (P_нп + P*))) (closed form)."""
    if not 0.0 < p_star < 1.0:
        raise ValueError(f"p_star must be in (0, 1), got {p_star}")
    x = p_star * v_zo / (v_ob(sigma) * (p_np(sigma, v_bc) + p_star))
    # guard the floor against a quotient that is an integer up to rounding
    return (1 + np.floor(x * (1.0 + 1e-12))).astype(np.int64)


# --------------------------------------------------------------------------- sounder model


def conflict_radius(sigma: ArrayLike, r_c: RcOption = "12sigma", dr_m: float = 5556.0) -> NDArray[np.float64]:
    """Conflict radius R_c (m): ``"6sigma"``, ``"12sigma"``, ``"separation"`` (Δr + 3√2σ with
    Δr = ``dr_m``) or a fixed number of metres."""
    s = np.asarray(sigma, dtype=np.float64)
    if isinstance(r_c, (int, float)) and not isinstance(r_c, bool):
        return np.full_like(s, float(r_c))
    if r_c == "6sigma":
        return 6.0 * s
    if r_c == "12sigma":
        return 12.0 * s
    if r_c == "separation":
        return dr_m + 3.0 * math.sqrt(2.0) * s
    raise ValueError(f"r_c must be '6sigma', '12sigma', 'separation' or metres, got {r_c!r}")


def p_pair(sigma: ArrayLike, r_c: RcOption = "12sigma", v_zo: float = V_ZO_M3, dr_m: float = 5556.0
           ) -> NDArray[np.float64]:
    """Pair conflict probability p = (4/3)πR_c³/V_зо of the sounder model (may be ≥ 1: the
    model's domain ends where the conflict sphere fills the zone)."""
    with np.errstate(over="ignore"):
        return 4.0 / 3.0 * np.pi * conflict_radius(sigma, r_c, dr_m) ** 3 / v_zo


def _p_pair(sigma, r_c, v_zo, dr_m) -> NDArray[np.float64]:
    p = p_pair(sigma, r_c, v_zo, dr_m)
    if np.any(~(p < 1.0)):
        raise ValueError("conflict sphere larger than the zone volume (p ≥ 1)")
    return p


def ppob_sound(n: ArrayLike, sigma: ArrayLike, r_c: RcOption = "12sigma", v_zo: float = V_ZO_M3,
               which: Literal["any", "one"] = "any", dr_m: float = 5556.0) -> NDArray[np.float64]:
    """Sounder conflict probability: ``which="one"`` P_1(n) = 1 − (1 − p)^(n−1), ``"any"``
    P_any(n) = 1 − (1 − p)^(n(n−1)/2), p = (4/3)πR_c³/V_зо."""
    if which not in ("one", "any"):
        raise ValueError(f"which must be 'one' or 'any', got {which!r}")
    nn = np.asarray(n, dtype=np.float64)
    p = _p_pair(sigma, r_c, v_zo, dr_m)
    m = nn - 1.0 if which == "one" else nn * (nn - 1.0) / 2.0
    return -np.expm1(m * np.log1p(-p))


def nmax_sound(sigma: ArrayLike, p_star: float = 1e-6, r_c: RcOption = "12sigma", v_zo: float = V_ZO_M3,
               which: Literal["any", "one"] = "any", dr_m: float = 5556.0) -> NDArray[np.int64]:
    """Largest n with the sounder probability ≤ P* (closed form; at least 1)."""
    if not 0.0 < p_star < 1.0:
        raise ValueError(f"p_star must be in (0, 1), got {p_star}")
    p = _p_pair(sigma, r_c, v_zo, dr_m)
    m = np.log1p(-p_star) / np.log1p(-p) * (1.0 + 1e-12)      # allowed exponent
    if which == "one":
        n = 1 + np.floor(m)
    elif which == "any":
        n = np.floor((1.0 + np.sqrt(1.0 + 8.0 * m)) / 2.0)
    else:
        raise ValueError(f"which must be 'one' or 'any', got {which!r}")
    return np.maximum(n, 1).astype(np.int64)


def rate_per_hour(p: ArrayLike, t_corr_h: float) -> NDArray[np.float64]:
    """Hourly rate −ln(1 − P)/T_corr of a per-configuration probability P (T_corr in hours:
    the time after which the traffic configuration is independent)."""
    if t_corr_h <= 0:
        raise ValueError(f"t_corr_h must be positive, got {t_corr_h}")
    return -np.log1p(-np.asarray(p, dtype=np.float64)) / t_corr_h


# --------------------------------------------------------------------------- curves


def ppob_curves(n: Sequence[int] | ArrayLike = tuple(range(2, 201)), sigmas: Sequence[float] = (50.0, 100.0, 200.0),
                v_bc: float = V_BC_M3, v_zo: float = V_ZO_M3, r_c: RcOption = "12sigma",
                models: Sequence[str] = ("seed", "sound_one", "sound_any"), dr_m: float = 5556.0) -> pl.DataFrame:
    """P_поб against n for several σ (fig. 5.2): long frame (model, sigma_m, n, p, valid).
    ``seed`` is (5.21) with its validity flag; ``sound_one`` / ``sound_any`` are P_1 / P_any of
    the sounder model (always valid)."""
    nn = np.asarray(n, dtype=np.float64)
    parts = []
    for s in sigmas:
        for model in models:
            if model == "seed":
                p, ok = ppob_seed(nn, s, v_bc, v_zo)
            elif model in ("sound_one", "sound_any"):
                p = ppob_sound(nn, s, r_c, v_zo, which=model.split("_")[1], dr_m=dr_m)  # type: ignore[arg-type]
                ok = np.ones(len(nn), bool)
            else:
                raise ValueError(f"unknown model {model!r}")
            parts.append(pl.DataFrame({"model": model, "sigma_m": float(s), "n": nn.astype(np.int64),
                                       "p": np.asarray(p, dtype=np.float64), "valid": np.asarray(ok, bool)}))
    return pl.concat(parts)


def capacity_curve(sigmas: Sequence[float] | ArrayLike = tuple(np.arange(10.0, 201.0, 5.0)), p_star: float = 1e-6,
                   v_bc: float = V_BC_M3, v_zo: float = V_ZO_M3, r_c: RcOption = "12sigma",
                   which: Literal["any", "one"] = "any", dr_m: float = 5556.0) -> pl.DataFrame:
    """n_max against σ (fig. 5.3) under both models: long frame (model, sigma_m, p_star, v_zo_m3,
    n_max); ``seed`` by the closed form of (5.21), ``sound`` by :func:`nmax_sound`."""
    s = np.asarray(sigmas, dtype=np.float64)
    seed = nmax_seed(s, p_star, v_bc, v_zo)
    sound = nmax_sound(s, p_star, r_c, v_zo, which, dr_m)
    return pl.DataFrame({
        "model": ["seed"] * len(s) + ["sound"] * len(s),
        "sigma_m": np.concatenate([s, s]),
        "p_star": p_star, "v_zo_m3": v_zo,
        "n_max": np.concatenate([seed, sound]).astype(np.int64),
    })


def _p_label(p: float) -> str:
    """1e-06 → '1e-6', 2.5e-05 → '2.5e-5'."""
    mant, exp = f"{p:e}".split("e")
    mant = mant.rstrip("0").rstrip(".")
    return f"{mant}e{int(exp)}"


def capacity_from_metrics(metrics: pl.DataFrame, p_star: float = CAPACITY_P_STAR, v_bc: float = V_BC_M3,
                          v_zo: float = CAPACITY_V_ZO_M3, r_c: RcOption = "12sigma", which: Literal["any", "one"] = "any",
                          sigma_metrics: Sequence[str] = ("rmse_range_m", "rmse_pos_m"),
                          dr_m: float = 5556.0, notes: list[str] | None = None,
                          n_fixed: int | None = CAPACITY_N) -> pl.DataFrame:
    """Capacity of every measured picture: for each (stage, method) of ``metrics`` with one of
    ``sigma_metrics`` (first found, segment ``all``), σ = that RMSE and

    * the largest n with P ≤ ``p_star`` under the seed model (metric ``capacity_n_<P*>``, e.g.
      ``capacity_n_1e-3``; *illustrative*: (5.21) as printed, odds-shaped) and the sounder model
      (``capacity_n_<P*>_sound``);
    * P(n) at ``n_fixed`` aircraft (``p_conflict_n<n>``: seed (5.21) as printed, NaN where it is
      not a probability; ``p_conflict_n<n>_sound``: any pair, sounder model) — a figure that
      varies continuously with σ (∝ σ³ for small p) where n_max is an integer.

    Rows in the ``metrics`` schema, stage ``"safety"``, method = the source method
    (``"<stage>/<method>"`` when a method name occurs in several stages), segment ``"all"``,
    n_runs from the source row.

    Defaults P* = 10⁻³, V_зо = 10¹⁴ m³ (:data:`CAPACITY_V_ZO_M3`): with the printed volumes
    (V_зо = 10¹² m³) the seed model admits n = 1 at P* = 10⁻⁶ for every realistic σ
    (≥ 10.3 m), a constant that separates nothing.

    A σ outside the sounder model's domain (conflict sphere ≥ the zone volume, p ≥ 1, e.g. a
    tracker whose RMSE is kilometres) gives NaN for that picture instead of failing the run;
    the reason is appended to ``notes`` (the run record's notes).
    """
    spec = TABLES["metrics"].required
    src = metrics.filter(pl.col("metric").is_in(list(sigma_metrics)) & (pl.col("segment") == "all")
                         & (pl.col("stage") != "safety") & pl.col("value").is_finite() & (pl.col("value") > 0))
    if src.is_empty():
        return pl.DataFrame(schema=spec)
    rank = pl.col("metric").replace_strict({m: i for i, m in enumerate(sigma_metrics)}, return_dtype=pl.Int32)
    src = (src.with_columns(rank.alias("__r")).sort("stage", "method", "__r")
           .unique(subset=["stage", "method"], keep="first", maintain_order=True))
    clash = src.group_by("method").agg(pl.len().alias("__c"))
    src = src.join(clash, on="method").with_columns(
        pl.when(pl.col("__c") > 1).then(pl.format("{}/{}", "stage", "method")).otherwise("method").alias("__m"))
    sigma = src["value"].to_numpy().astype(np.float64)
    label = _p_label(p_star)
    seed = nmax_seed(sigma, p_star, v_bc, v_zo).astype(np.float64)
    p = p_pair(sigma, r_c, v_zo, dr_m)
    inside = p < 1.0
    sound = np.full(len(sigma), np.nan)
    if inside.any():
        sound[inside] = nmax_sound(sigma[inside], p_star, r_c, v_zo, which, dr_m)
    if notes is not None:
        for m, s_m, p_m in zip(np.asarray(src["__m"].to_list(), dtype=object)[~inside], sigma[~inside], p[~inside]):
            notes.append(f"safety: capacity_n_{label}_sound of {m} is NaN: σ = {s_m:.4g} m puts the conflict "
                         f"sphere beyond the zone volume (p = {p_m:.3g} ≥ 1, V_zo = {v_zo:g} m³)")
    values = {f"capacity_n_{label}": seed, f"capacity_n_{label}_sound": sound}
    if n_fixed is not None:
        risk = ppob_seed(np.full(len(sigma), n_fixed), sigma, v_bc, v_zo)
        values[f"p_conflict_n{n_fixed}"] = np.where(risk.valid, risk.p, np.nan)
        p_any = np.full(len(sigma), np.nan)
        if inside.any():
            p_any[inside] = ppob_sound(n_fixed, sigma[inside], r_c, v_zo, "any", dr_m)
        values[f"p_conflict_n{n_fixed}_sound"] = p_any
    base = src.select(pl.col("__m").alias("method"), "n_runs")
    out = pl.concat([base.with_columns(pl.lit(name).alias("metric"), pl.Series("value", v))
                     for name, v in values.items()])
    return (out.select(pl.lit("safety").alias("stage"), "method", "metric", pl.lit("all").alias("segment"),
                       "value", "n_runs")
            .sort("method", "metric").select([pl.col(c).cast(t) for c, t in spec.items()]))
