"""Consistency of a matched picture: the NEES and NIS statistics and their χ² bands.

``nees_*`` (position NEES Δpᵀ P_pp⁻¹ Δp, 3 degrees of freedom; from the diagonal ``cov_diag``
when a picture has no full ``cov``), ``nees6_*`` (6-state, 6) and, for pictures that carry a
``nis`` column (the trackers), ``nis_*`` (3): the mean; the Monte-Carlo test ``*_in_band_frac``
— the fraction of epochs whose mean over the N_k samples lies in the two-sided 95 % band
χ²(dN_k)/N_k; and the band of the overall mean from the effective sample size n/τ
(``*_band_lo``/``_hi``, ``*_n_eff``; τ from :func:`integrated_autocorrelation`). :class:`Lags`
keeps the per-lag sums of τ so that a picture read in buckets gets the same τ.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import TABLES
from tertiary.core.distributions import chi2_ppf
from tertiary.core.units import STATE

__all__ = ["add_nees", "chi2_band", "integrated_autocorrelation", "consistency_metrics", "consistency_dicts",
           "consistency_rows", "consistency_statistics", "series_codes", "Lags", "WholeSeries", "CONSISTENCY", "CONSISTENCY_ALL", "NIS_DOF", "MAX_LAG"]

#: cells of one zero-padded FFT block of :func:`_lag_products` (16 MiB of float64)
_FFT_CELLS = 1 << 21


def _nees_full(p: NDArray[np.float64], e: NDArray[np.float64]) -> NDArray[np.float64]:
    """eᵀ P⁻¹ e per row; NaN on a row whose full covariance is singular (position NEES only), so
    that one singular row never blanks the rows solved with it."""
    try:
        return np.einsum("ni,ni->n", e, np.linalg.solve(p, e[..., None])[..., 0])
    except np.linalg.LinAlgError:
        out = np.full(len(e), np.nan)
        ok = np.linalg.cond(p) < 1.0 / np.finfo(float).eps       # inf for an exactly singular P
        if ok.any():
            out[ok] = np.einsum("ni,ni->n", e[ok], np.linalg.solve(p[ok], e[ok][..., None])[..., 0])
        return out


def add_nees(matched: pl.DataFrame, cov: pl.Series | None = None, block: int = 131_072) -> pl.DataFrame:
    """Add the normalised estimation error squared of each scored row:
    ``nees_pos`` = Δpᵀ P_pp⁻¹ Δp (3 degrees of freedom, mean 3 when consistent) and ``nees``
    over the full 6-state (mean 6). The flattened 6×6 covariance (x, y, z, vx, vy, vz) is the
    row's ``cov`` column, or ``cov`` given aligned with the rows; computed in blocks of rows
    so the (n, 6, 6) arrays stay small. A singular covariance gives NaN."""
    if matched.is_empty():
        return matched.with_columns(pl.lit(None, pl.Float64).alias("nees_pos"), pl.lit(None, pl.Float64).alias("nees"))
    cov = matched["cov"] if cov is None else cov
    err = np.stack([(matched[c] - matched[f"true_{c}"]).to_numpy() for c in STATE], axis=1)
    nees_pos, nees = np.full(len(err), np.nan), np.full(len(err), np.nan)
    for lo in range(0, len(err), block):
        sl = slice(lo, lo + block)
        p = cov.slice(lo, block).to_numpy().reshape(-1, 6, 6)
        e = err[sl]
        ok = np.all(np.isfinite(p.reshape(-1, 36)), axis=1) & np.all(np.isfinite(e), axis=1)
        ok &= np.linalg.det(p[:, :3, :3]) > 0
        if not ok.any():
            continue
        pk, ek = p[ok], e[ok]
        with np.errstate(all="ignore"):
            a = np.einsum("ni,ni->n", ek[:, :3], np.linalg.solve(pk[:, :3, :3], ek[:, :3, None])[..., 0])
            b = _nees_full(pk, ek)
        idx = np.flatnonzero(ok) + lo
        nees_pos[idx], nees[idx] = a, b
    return matched.with_columns(pl.Series("nees_pos", nees_pos), pl.Series("nees", nees))


def chi2_band(n, dof: int, band: float = 0.95):
    """Two-sided ``band`` interval of the mean of ``n`` independent χ²(``dof``) samples:
    χ²_{(1∓band)/2}(dof·n)/n. ``n`` may be an array (also non-integer: an effective sample
    size); n ≤ 0 gives NaN. Scalars in, a (lo, hi) tuple of floats out."""
    arr = np.asarray(n, dtype=float)
    # the per-epoch counts repeat: the quantile (an iterative inverse) is found once per count
    safe, where = np.unique(np.where(arr > 0, arr, np.nan), return_inverse=True)
    with np.errstate(all="ignore"):
        lo = chi2_ppf((1 - band) / 2, dof * safe) / safe
        hi = chi2_ppf((1 + band) / 2, dof * safe) / safe
    if arr.ndim == 0:
        return float(lo[0]), float(hi[0])
    return lo[where].reshape(arr.shape), hi[where].reshape(arr.shape)


#: the lags of :func:`integrated_autocorrelation`'s sum: 0 … MAX_LAG − 1
MAX_LAG = 1000


def integrated_autocorrelation(x: np.ndarray, series: np.ndarray, max_lag: int = MAX_LAG) -> float:
    """Integrated autocorrelation time τ of a sequence observed as several series (``series``
    codes; rows sorted by series then time, consecutive rows of a series one step apart), so
    that the mean of the n rows has the variance of n/τ independent ones.

    Var(Σ x) = n γ₀ + 2 Σ_{l≥1} Σ_{pairs at lag l inside one series} Cov, hence

        τ = 1 + 2 Σ_{l≥1} (P_l/n) ρ_l,    ρ_l = γ_l/γ₀,

    with P_l the number of pairs at lag l inside a series (P_l/n → 1 for long series: the
    usual 1 + 2 Σ ρ_l), γ_l the mean of (x_t − x̄)(x_{t+l} − x̄) over those pairs and x̄ the mean
    of all rows (the series are runs or targets of one picture). The sum is truncated by
    Geyer's initial positive sequence rule (Geyer 1992, Stat. Sci. 7(4)): the pair sums of
    consecutive terms (lags 2m, 2m + 1, lag 0 counting 1) are added while positive.
    τ ≥ 1 (independent samples: τ = 1)."""
    x = np.asarray(x, float)
    n = len(x)
    if n < 3:
        return 1.0
    y = x - x.mean()
    g0 = float(np.mean(y * y))
    if not g0 > 0:
        return 1.0

    def term(lag: int) -> float:
        same = series[lag:] == series[:-lag]
        return float(np.sum((y[lag:] * y[:-lag])[same])) / (n * g0)
    return _geyer_tau(term, n, max_lag)


def _geyer_tau(term: Callable[[int], float], n: int, max_lag: int) -> float:
    """τ = 1 + 2 Σ_l term(l), term(l) = (P_l/n) ρ_l for 1 ≤ l < n, truncated by Geyer's initial
    positive sequence rule (:func:`integrated_autocorrelation`); the terms are asked for in lag
    order and only up to the truncation (a term costs a pass over the rows)."""
    terms = [1.0]          # (P_l / n) ρ_l, lag 0 first
    tau = -1.0
    for m in range(max_lag // 2):
        for lag in (2 * m, 2 * m + 1):
            if lag == 0:
                continue
            terms.append(term(lag) if lag < n else 0.0)
        pair = terms[2 * m] + terms[2 * m + 1]
        if pair <= 0:
            break
        tau += 2 * pair
    return max(tau, 1.0)


#: consistency statistic → (column, degrees of freedom)
CONSISTENCY = {"nees": ("nees_pos", 3), "nees6": ("nees", 6)}


def consistency_metrics(rows: pl.DataFrame, column: str, dof: int, prefix: str, stage: str,
                        obj: str = "track_id", band: float = 0.95) -> pl.DataFrame:
    """Consistency of a normalised squared error ``column`` (NEES or NIS, χ²(``dof``) when the
    covariance is right) per ``method`` and segment (all/straight/turn), in the metrics schema:

    * ``<prefix>_mean``: the mean over all samples.
    * ``<prefix>_in_band_frac``: the Monte-Carlo test — at each epoch k the N_k samples (one
      per run and object; independent draws) are averaged and compared with the two-sided
      ``band`` interval χ²(dof·N_k)/N_k of such an average; the fraction of epochs inside.
      With one run and one object N_k = 1: the χ²(dof) interval of a single sample.
    * ``<prefix>_band_lo`` / ``_band_hi``: the interval of ``<prefix>_mean`` itself, from the
      effective sample size n_eff = n/τ (τ: :func:`integrated_autocorrelation` along each
      (run, ``obj``) series in epoch order) — consecutive errors of a filter are correlated,
      so the n samples are worth n/τ independent ones.
    * ``<prefix>_n_eff``: that effective sample size.
    """
    spec = TABLES["metrics"].required
    # the columns read, then the rows, sorted once along each (run, obj) series: the scored
    # picture is never copied whole, and a segment's rows are a filter of these (memory of the
    # stage on a long run)
    r = rows.select("method", "run", "epoch", obj, "seg_class", column).filter(
        pl.col(column).is_not_null() & pl.col(column).is_finite()).sort("method", "run", obj, "epoch")
    if r.is_empty():
        return pl.DataFrame(schema=spec)
    out = []
    for method in sorted(r["method"].unique().to_list()):
        m = r.filter(pl.col("method") == method) if r["method"].n_unique() > 1 else r
        segments = sorted(["all", *m["seg_class"].drop_nulls().unique().to_list()])
        for seg in segments:
            g = m if seg == "all" else m.filter(pl.col("seg_class") == seg)
            out += _consistency_rows(g, column, dof, prefix, stage, obj, band, method, seg)
            del g
    return pl.DataFrame(out, schema=spec)


def _consistency_rows(g: pl.DataFrame, column: str, dof: int, prefix: str, stage: str, obj: str, band: float,
                      method: str, seg: str) -> list[dict]:
    """The five :func:`consistency_metrics` rows of one picture's segment ``g`` (sorted by run,
    ``obj``, epoch)."""
    per = g.group_by("epoch").agg(pl.col(column).mean().alias("__m"), pl.len().alias("__n"))
    x = g[column].to_numpy()
    tau = integrated_autocorrelation(x, series_codes(g, obj))
    return consistency_dicts(stage, method, seg, prefix, dof, band, float(x.mean()), per["__m"].to_numpy(),
                              per["__n"].to_numpy(), len(x), tau, g["run"].n_unique())


def series_codes(g: pl.DataFrame, obj: str) -> NDArray[np.int64]:
    """One code per (run, ``obj``) series of ``g``, whose rows are sorted along the series."""
    run, who = g["run"].to_numpy(), g[obj].to_numpy()
    return np.cumsum(np.r_[True, (run[1:] != run[:-1]) | (who[1:] != who[:-1])])


def consistency_dicts(stage: str, method: str, seg: str, prefix: str, dof: int, band: float, mean: float,
                       mean_k: NDArray[np.float64], n_k: NDArray, n: int, tau: float, n_runs: int) -> list[dict]:
    """The five :func:`consistency_metrics` rows of one picture's segment from its overall
    ``mean``, the per-epoch means ``mean_k`` of ``n_k`` samples, its ``n`` samples and their τ."""
    lo, hi = chi2_band(n_k, dof, band)
    in_band = float(np.mean((mean_k >= lo) & (mean_k <= hi)))
    return consistency_rows(stage, method, seg, prefix, dof, band, mean, in_band, n, tau, n_runs)


def consistency_rows(stage: str, method: str, seg: str, prefix: str, dof: int, band: float, mean: float,
                     in_band: float, n: int, tau: float, n_runs: int) -> list[dict]:
    """:func:`consistency_dicts` given the fraction of epochs whose mean is in its band (``in_band``)."""
    n_eff = n / tau
    b_lo, b_hi = chi2_band(n_eff, dof, band)
    return [{"stage": stage, "method": method, "metric": f"{prefix}_{metric}", "segment": seg, "value": value,
             "n_runs": n_runs}
            for metric, value in (("mean", mean), ("in_band_frac", in_band), ("band_lo", b_lo),
                                  ("band_hi", b_hi), ("n_eff", n_eff))]


#: consistency statistics of a picture that carries a ``nis`` column (its innovations): the
#: tracker's measurement is the fused 3-D position
NIS_DOF = 3


#: every consistency statistic a picture may have (NIS: a picture with a ``nis`` column), in order
CONSISTENCY_ALL = {**CONSISTENCY, "nis": ("nis", NIS_DOF)}


def consistency_statistics(columns: list[str]) -> dict[str, tuple[str, int]]:
    """The consistency statistics (prefix → column, dof) of a scored picture with ``columns``."""
    return {p: (c, d) for p, (c, d) in CONSISTENCY_ALL.items() if c in columns}


@dataclass(frozen=True)
class Lags:
    """Sums over the pairs of rows at lag l = 0 … MAX_LAG − 1 inside the series of a set of rows
    (:func:`integrated_autocorrelation`), about a centre c: ``s[l]`` = Σ (x_a − c)(x_b − c),
    ``a[l]`` = Σ (x_a − c) + (x_b − c), ``p[l]`` the number of pairs; ``n`` rows summing to
    ``total``. Moved to another centre exactly (Σ (y_a + d)(y_b + d) = s + d a + p d²), so the
    sums of parts of the rows (whole series each) add up to those of their union about its
    mean: τ without holding the rows, and without the cancellation of raw Σ x_a x_b."""

    n: int
    total: float
    centre: float
    s: NDArray[np.float64]
    a: NDArray[np.float64]
    p: NDArray[np.float64]

    @classmethod
    def of(cls, x: NDArray[np.float64], series: NDArray) -> Lags:
        """The sums of rows ``x`` sorted along their ``series`` (codes), about their mean."""
        n, c = len(x), float(x.mean())
        y = x - c
        starts = np.flatnonzero(np.r_[True, series[1:] != series[:-1]])
        lengths = np.diff(np.r_[starts, n])
        first = np.repeat(starts, lengths)
        end = first + np.repeat(lengths, lengths)
        lag = np.arange(n) - first                  # each lag < its series' length, once a series
        cum = np.r_[0.0, np.cumsum(y)]
        # Σ y over the first and the last L − lag rows of a series: its pairs at that lag
        ends = cum[end - lag] - cum[first] + cum[end] - cum[first + lag]
        k = lag < MAX_LAG
        p = np.bincount(lag[k], weights=(end - first - lag)[k], minlength=MAX_LAG)
        a = np.bincount(lag[k], weights=ends[k], minlength=MAX_LAG)
        s = _lag_products(y, starts, lengths)
        s[0] = float(np.dot(y, y))
        return cls(n, float(x.sum()), c, s, a, p)

    def moved(self, centre: float) -> Lags:
        """The same sums about ``centre``."""
        d = self.centre - centre
        return Lags(self.n, self.total, centre, self.s + d * self.a + d * d * self.p, self.a + 2 * d * self.p,
                     self.p)

    def __add__(self, other: Lags) -> Lags:
        n, total = self.n + other.n, self.total + other.total
        u, v = self.moved(total / n), other.moved(total / n)
        return Lags(n, total, total / n, u.s + v.s, u.a + v.a, u.p + v.p)

    def tau(self) -> float:
        """:func:`integrated_autocorrelation` of the rows summed."""
        n = self.n
        if n < 3:
            return 1.0
        y = self.moved(self.total / n)
        g0 = float(y.s[0]) / n
        if not g0 > 0:
            return 1.0
        s = np.where(y.p > 0, y.s, 0.0)             # no pair at a lag: exactly 0, not FFT round-off
        return _geyer_tau(lambda lag: float(s[lag]) / (n * g0), n, MAX_LAG)


@dataclass(frozen=True)
class WholeSeries:
    """:class:`Lags`' finish (``n``, ``total``, :meth:`tau`) of rows read whole, τ summed lag by
    lag up to Geyer's truncation (:func:`integrated_autocorrelation`): what a set of rows that
    is never merged with another needs, without every lag's sums."""

    n: int
    total: float
    value: float

    @classmethod
    def of(cls, x: NDArray[np.float64], series: NDArray) -> WholeSeries:
        return cls(len(x), float(x.sum()), integrated_autocorrelation(x, series))

    def tau(self) -> float:
        return self.value


def _lag_products(y: NDArray[np.float64], starts: NDArray, lengths: NDArray) -> NDArray[np.float64]:
    """Σ over the series (rows ``starts`` … + ``lengths``) of Σ_t y_t y_{t+l}, for every lag
    l < MAX_LAG at once: each series' autocorrelation by FFT, zero-padded to twice the power of
    two above its length, the series of one such width in blocks. O(n log n): which lags τ needs
    is known only once every bucket is summed, and a lag by lag sum costs O(n) per lag."""
    out = np.zeros(MAX_LAG)
    width = (1 << np.ceil(np.log2(lengths)).astype(np.int64)).astype(np.int64)
    for w in np.unique(width[lengths > 1]):        # a series of one row has no lag ≥ 1
        sel = np.flatnonzero(width == w)
        step = max(1, _FFT_CELLS // (2 * int(w)))
        for lo in range(0, len(sel), step):
            block = sel[lo:lo + step]
            k = min(int(w), MAX_LAG)
            out[:k] += _autocorrelation(y, starts[block], lengths[block], int(w))[:k]
    return out


def _autocorrelation(y: NDArray[np.float64], starts: NDArray, lengths: NDArray, w: int) -> NDArray[np.float64]:
    """Σ over the given series (each at most ``w`` rows) of their autocorrelation at lags 0 … w − 1."""
    first = np.cumsum(lengths) - lengths
    pos = np.arange(int(lengths.sum())) - np.repeat(first, lengths)
    mat = np.zeros((len(lengths), 2 * w))
    mat[np.repeat(np.arange(len(lengths)), lengths), pos] = y[np.repeat(starts, lengths) + pos]
    f = np.fft.rfft(mat, axis=1)
    return np.fft.irfft(f.real ** 2 + f.imag ** 2, n=2 * w, axis=1)[:, :w].sum(axis=0)
