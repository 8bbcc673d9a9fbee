"""The NIS gate applied to the fusion rows before every method.

A row whose range NIS ν²/S exceeds χ²₁(``nis_gate_prob``) (9.0 at 0.9973 = 3σ), or with
``gate_test="trace"`` fails the innovation trace test νᵀν ≤ γ tr S (:func:`trace_test`), is
``"reject"``-ed (left out of its group unless every source fails), ``"downweight"``-ed
(C_n × NIS/threshold: changes the weights of the covariance-based methods, the reported P of all)
or only ``"flag"``-ged (fusion unchanged; :mod:`tertiary.sensors.radar_health` counts the flags
per radar) — ``FusionConfig.nis_gate``.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from tertiary.core.distributions import chi2_ppf
from tertiary.stages.fusion.base import GROUP, B, F
from tertiary.stages.fusion.config import FusionConfig

__all__ = ["apply_gate", "chi2_threshold", "gate_pass", "nis", "trace_test"]


def nis(res: F, res_var: F) -> F:
    """Normalised innovation squared of the range channel, ν²/S (m = 1; NaN when unusable)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(np.isfinite(res) & (res_var > 0), res * res / res_var, np.nan)


def chi2_threshold(prob: float, dof: int = 1) -> float:
    """χ²_m quantile of the gate: 9.0 for m = 1 at 2Φ(3) − 1 = 0.9973, 11.83 for m = 2."""
    return float(chi2_ppf(prob, dof))


def trace_test(nu: F, s: F, gamma: float = 3.0) -> B:
    """Innovation trace test (seed 003 §3.1.2): accept when νᵀν ≤ γ tr S, for innovations
    ``nu`` (n, m) or (n,) and covariances ``s`` (n, m, m), (n, m) diagonals or (n,) scalars.
    With S = s I, νᵀν/s ~ χ²_m: γ = 3 passes 91.7 % for m = 1 (not 3σ; that needs γ = 9)."""
    nu = np.asarray(nu, float)
    s = np.asarray(s, float)
    r2 = nu * nu if nu.ndim == 1 else np.sum(nu * nu, axis=1)
    tr = s if s.ndim == 1 else (np.einsum("nii->n", s) if s.ndim == 3 else s.sum(axis=1))
    return r2 <= gamma * tr


def gate_pass(res: F, res_var: F, cfg: FusionConfig) -> tuple[B, F, float]:
    """Per row: whether its range innovation passes the gate of ``cfg`` (True when it has no
    usable innovation), its NIS, and the gate's NIS threshold (χ²₁ quantile, or γ for the trace
    test, which for m = 1 is NIS ≤ γ)."""
    v = nis(res, res_var)
    thr = chi2_threshold(cfg.nis_gate_prob) if cfg.gate_test == "chi2" else cfg.trace_gamma
    ok = trace_test(res, res_var, thr) if cfg.gate_test == "trace" else v <= thr
    return ~np.isfinite(v) | ok, v, thr


def apply_gate(rows: pl.DataFrame, cfg: FusionConfig) -> tuple[pl.DataFrame, F | None]:
    """The NIS gate of ``cfg`` on sorted rows: ``"reject"`` drops the failing rows of each group
    (all kept when every row fails: the target is still fused); ``"downweight"`` returns the
    covariance factor max(1, NIS/threshold) per row; ``"flag"``/None change nothing."""
    if cfg.nis_gate in (None, "flag") or rows.height == 0:
        return rows, None
    col = lambda c: rows[c].cast(pl.Float64).fill_null(np.nan).to_numpy()  # noqa: E731
    ok, v, thr = gate_pass(col("res_range_m"), col("res_range_var_m2"), cfg)
    if cfg.nis_gate == "downweight":
        return rows, np.where(ok, 1.0, np.maximum(v / thr, 1.0))
    keep = pl.Series("__ok", ok)
    return (rows.with_columns(keep).filter(pl.col("__ok") | ~pl.col("__ok").any().over(GROUP))
            .drop("__ok")), None
