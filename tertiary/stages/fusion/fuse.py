"""Stage 5 — fusion (weighted averaging) of the reports associated to one system target.

Input: one row per (run, epoch, report) already associated to a target (the ``aligned`` state
and covariance joined with ``associations``, plus ``fresh`` and ``nominal_var``; see
:data:`INPUT_COLUMNS`). Output: the ``fused`` table, one row per (run, epoch, target_id,
method). Equation numbers are the monograph's (seed 000, chapter 4); §-numbers refer to the
digest ``docs/seeds/tertiary-and-safety.md``.

Methods and the meaning of the reported ``weights`` (one per contributing radar, same order as
``radar_ids``, summing to 1):

* ``arithmetic`` (4.1): x = mean of the states, P = (1/N²) Σ C_n (independent errors).
  Weights 1/N.
* ``apriori`` (4.3)–(4.4) for N radars, per coordinate c ∈ {x, y, z}:
  b_{n,c} = σ⁻²_{n,c} / Σ_m σ⁻²_{m,c} with σ²_{n,c} = ``nominal_var[c]``; each velocity
  coordinate uses the weight of its position axis. P = Σ_n B_n C_n B_n, B_n = diag(b_n).
  Reported weight: the mean of the x, y, z weights of the radar (sums to 1 because each
  coordinate's weights do).
* ``aposteriori_seed`` — (4.72)–(4.77) **as printed**, N radars as digest §6.2:
  b_n(k) = L_n(k)(1 − b_n(k−1)) / Σ_m L_m(k)(1 − b_m(k−1)),
  L_n = (2πD_n)^{-1/2} exp(−ΔD_n²/(2D_n)), ΔD_n = ``res_range_m``, D_n fixed per (run, radar,
  local track) = ``res_range_var_m2 − sigma_range_m²`` at the local track's first row with a
  finite innovation (the step-1 predicted variance without R, (4.75)–(4.76)), b_n(0) = 1/N
  (4.77). One weight per radar for all six coordinates; P = Σ b_n² C_n (the seed fuses states
  only; this is the covariance of a fixed-weight mix of independent estimates). The printed
  prior (1 − b(k−1)) is Markov mixing with π_nn = 0: constant unequal likelihoods give the
  period-2 oscillation of digest §2.3 (b), which this method deliberately keeps.
* ``aposteriori`` — corrected recursion (digest §6.3, "markov"):
  c_n = Σ_m π_mn b_m(k−1), π_nn = ``p_stay``, π_mn = (1 − p_stay)/(N − 1);
  b_n ∝ N(ν_n; 0, S_n(k)) c_n with S_n(k) = ``res_range_var_m2``; floor ``b_min``, renormalise.
  Weight and covariance as for the seed variant.
* ``information``: P = (Σ C_n⁻¹)⁻¹, x = P Σ C_n⁻¹ x_n over the full 6-D state. Reported
  weight tr(P C_n⁻¹)/6 (the weights sum to 1 because Σ P C_n⁻¹ = I; renormalised against
  rounding).
* ``bar_shalom_campo``: track-to-track fusion with the common-process-noise cross-covariance
  P_ij = ρ C_i^{1/2} C_j^{1/2} between the radars' tracks: Bar-Shalom–Campo for two sources,
  the BLUE of N correlated estimates for more (:func:`fuse_bar_shalom_campo`). Reported weight
  tr W_n / 6.
* ``covariance_intersection``: P⁻¹ = Σ ω_n C_n⁻¹, x = P Σ ω_n C_n⁻¹ x_n, ω on the simplex.
  Two sources: ω minimises tr P (or det P, ``ci_objective="det"``) by a golden-section search
  vectorised over targets, on the closed form of P(ω) after simultaneous diagonalisation.
  N > 2: the fast-CI weights ω_n ∝ 1/tr C_n (Niehsen 2002), whatever ``ci_objective``.
  Reported weights: ω.

Optional methods (:data:`EXTRA_METHODS`, selectable by name, not in the default :data:`METHODS`):

* ``best_source`` — the single most accurate source (§1.3 (c)): the report with the smallest
  position-error trace tr C_n[0:3, 0:3] (m²; the velocity block is in other units), unchanged.
  Weights one-hot.
* ``invcov_nis`` (digest §6.4): information fusion of λ_n C_n, λ_n = max(1, mean of the last
  ``nis_window`` normalised innovations ν²/S of the (run, radar, local track)), which
  down-weights a radar whose filter lags (a manoeuvre) or is inconsistent.
* ``aposteriori_seed_S`` (digest §6.5 ``seed_S``): the printed prior (1 − b(k−1)) of
  (4.73)–(4.74) with the per-step S_n(k) = ``res_range_var_m2`` instead of the fixed D_n.
* ``aposteriori_coord`` — per-coordinate a-posteriori weights (digest §6.1): b_{n,c},
  c ∈ {x, y, z}, by the corrected recursion on N(ν_{n,c}; 0, S_{n,c}) (:func:`los_innovation`).
* ``aposteriori_mv`` — one weight per radar from the multivariate N(ν_n; 0, S_n) (digest §6.1)
  of the same 3-D innovation, corrected recursion.

The rows carry only the range innovation ΔD_n and its variance S_n (DESIGN §3), so the 3-D
innovation of §6.1 is built from it (:func:`los_innovation`): ν_n = u_n ΔD_n along the line of
sight u_n (radar site → reported position, system frame), covariance
S_n = a_n u_n u_nᵀ + diag(nominal_var_n), a_n = max(S_n − σ²_range,n, 0) the predicted range
variance without R, diag(nominal_var) the plot noise per system axis (range and cross-range).

NIS gate (``FusionConfig.nis_gate``, every method; seed 003 §2.2 and digest 003 §6): a row whose
range NIS ν²/S exceeds χ²₁(``nis_gate_prob``) (9.0 at 0.9973 = 3σ), or with ``gate_test="trace"``
fails the innovation trace test νᵀν ≤ γ tr S (:func:`trace_test`), is ``"reject"``-ed (left out of
its group unless every source fails), ``"downweight"``-ed (C_n × NIS/threshold: changes the
weights of the covariance-based methods, the reported P of all) or only ``"flag"``-ged (fusion
unchanged; :mod:`tertiary.sensors.radar_health` counts the flags per radar).

Rules shared by both a-posteriori recursions (digest §2.3, §6.2–6.3):

* the recursion state b(k−1) of a (run, target_id, radar_id) is its weight at the previous
  epoch at which the target was fused; when the target's radar set differs from that epoch's
  set (or the target is new) the recursion restarts from b(0) = 1/N for the current set;
* a row carries a usable innovation when it is ``fresh``, its ΔD is finite and its variance
  (D_n or S_n(k)) is finite and positive. Rows without one keep b(k−1); the radars with a
  usable innovation share the remaining mass 1 − Σ_{unusable} b_m(k−1) in proportion to
  L_n c_n (the usual update restricted to them);
* the update runs in the log domain (softmax); a target whose every log-term is −∞/NaN (all
  likelihoods or priors vanish) keeps b(k−1) (digest §2.3 (e)).

Single-source targets: every method returns the report unchanged with weight [1.0].

Freshness, the tracker's measurement and tentative targets (columns of
:data:`tertiary.contract.schema.FUSED_EXTRA`): ``n_fresh`` counts the group's fresh rows (a new report at
this epoch) and ``age_s`` is the age of the newest of them. Given the reports' measured plots
(``fuse(..., plots=measured_plots(...))``, joined to the fresh rows only), each method also gives the plot-level fusion of the fresh
plots (:func:`plot_measurement`: the method's weights, or inverse covariance for
``information``, ``covariance_intersection`` and ``bar_shalom_campo``) with its full 3×3
covariance — the independent measurement the secondary tracker filters. ``tentative``: the
target has only ever been made of one radar's local tracks with fewer than ``min_plots``
plots (:func:`confirm_step`, a step function with explicit carried state).

Vertical channel (every method, :mod:`tertiary.stages.tracking.altitude`): ``alt_m``, ``alt_rate_mps``,
``alt_var_m2``, ``alt_rate_var_m2ps2``, ``alt_cov_m2ps``. When the rows carry the reports'
barometric ``altitude_m`` (with ``time``), a two-state (h, ḣ) filter runs per (run, radar,
local track) over its reports' replies (quantum 25 ft with ``mode_s``, 100 ft without,
R = q²/12, garble gate), is extrapolated from the report time to the epoch ((A1)–(A2)) and,
among the target's sources with an estimate, the one with the smallest height variance is kept
(all radars decode the same reply, so their errors are not independent:
:func:`tertiary.stages.tracking.altitude.combine_min_variance`). This channel does not depend on the method.
A target without any Mode C source falls back to the geodetic height of the method's fused
state, its variance from the covariance along the local vertical
(:func:`tertiary.stages.tracking.altitude.geodetic_channel`; ``origin=None``: spherical Earth, ≤ 9 m at
150 km) — never the ENU z.

The numeric kernels (``fuse_<method>``) work on numpy arrays whose rows are sorted by group
(run, epoch, target_id), described by ``starts`` (first row of each group) and, for the
recursions, by a :class:`Layout`. They use segment reductions (``np.add.reduceat``); the
recursions loop over the rank of the epoch along each target's history, vectorised across
targets and runs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.stages.tracking.altitude import (ALT_COLUMNS, QUANTUM_MODE_C_M, QUANTUM_MODE_S_M, AltitudeConfig, AltState, FilterCarry, combine_min_variance, filter_tracks_carry, geodetic_channel, predict, quantisation_variance)
from tertiary.core.distributions import chi2_ppf
from tertiary.contract.schema import (CLEARED_ALT_COLUMN, FUSED_EXTRA, SELECTED_ALT_COLUMN, TABLES, TIME, TURN_RATE_COLUMN, is_sorted_by)

__all__ = [
    "INPUT_COLUMNS",
    "METHODS",
    "Fused",
    "FusionConfig",
    "Layout",
    "apriori_weights",
    "ci_pair_weights",
    "fuse",
    "fuse_step",
    "FuseState",
    "init_fuse_state",
    "nis_inflation_step",
    "first_innovation_var",
    "fuse_aposteriori",
    "fuse_aposteriori_seed",
    "fuse_apriori",
    "fuse_arithmetic",
    "fuse_bar_shalom_campo",
    "fuse_covariance_intersection",
    "fuse_information",
    "layout",
    "markov_weights",
    "seed_fixed_variance",
    "seed_weights",
    "EXTRA_METHODS",
    "ALL_METHODS",
    "GATE_ACTIONS",
    "fuse_best_source",
    "fuse_invcov_nis",
    "nis_inflation",
    "los_innovation",
    "coord_loglik",
    "mv_loglik",
    "nis",
    "chi2_threshold",
    "trace_test",
    "gate_pass",
]

METHODS = (
    "arithmetic", "apriori", "aposteriori_seed", "aposteriori", "information",
    "covariance_intersection", "bar_shalom_campo",
)
#: selectable by name, never in the default list (the main job's cost does not grow)
EXTRA_METHODS = ("best_source", "invcov_nis", "aposteriori_seed_S", "aposteriori_coord", "aposteriori_mv")
ALL_METHODS = METHODS + EXTRA_METHODS
GATE_ACTIONS = ("reject", "downweight", "flag")
GATE_TESTS = ("chi2", "trace")
STATE = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
GROUP = ["run", "epoch", "target_id"]
CHAIN = ["run", "target_id"]
TRACK = ["run", "radar_id", "local_track_id"]
INPUT_COLUMNS = [
    *GROUP, "radar_id", "local_track_id", "report_id", *STATE, "cov",
    "res_range_m", "res_range_var_m2", "fresh", "nominal_var",
]
CI_OBJECTIVES = ("trace", "det")
_GOLDEN_ITERATIONS = 60  # bracket 0.618^60 ≈ 3e-13 of [0, 1]
_EIG_FLOOR = 1e-12  # relative eigenvalue floor for non-positive-definite covariances

F = NDArray[np.float64]
Ix = NDArray[np.intp]
B = NDArray[np.bool_]


@dataclass(frozen=True)
class FusionConfig:
    """Parameters of the fusion methods.

    * ``p_stay``: π_nn of the corrected a-posteriori recursion (digest §6.3; 0 reproduces the
      seed prior, 1 is pure Bayes, which locks in).
    * ``b_min``: floor of the corrected a-posteriori weights before renormalisation.
    * ``ci_objective``: ``"trace"`` or ``"det"`` of the covariance-intersection P (two sources).
    * ``bc_rho``: correlation coefficient ρ of the common-process-noise cross-covariance of
      ``bar_shalom_campo``, P_ij = ρ C_i^{1/2} C_j^{1/2} (Bar-Shalom & Li 1995; 0 gives
      information fusion).
    * ``min_plots``: a local track supports a target once it has this many plots (``tentative``).
    * ``altitude``: the per-local-track Mode C filter of the vertical channel.
    * ``nis_window``: innovations in the moving average of ``invcov_nis``'s λ_n.
    * ``nis_gate``: None (off) or an action of :data:`GATE_ACTIONS`; ``nis_gate_prob``: the χ²
      gate probability; ``gate_test``: ``"chi2"`` (NIS) or ``"trace"`` (νᵀν ≤ ``trace_gamma`` tr S;
      the printed γ = 3 is not a 3σ test).
    """

    p_stay: float = 0.95
    b_min: float = 0.01
    ci_objective: str = "trace"
    bc_rho: float = 0.4
    min_plots: int = 2
    altitude: AltitudeConfig = AltitudeConfig()
    nis_window: int = 5
    nis_gate: str | None = None
    nis_gate_prob: float = 0.9973002039367398   # 2Φ(3) − 1: χ²₁ threshold 9.0
    gate_test: str = "chi2"
    trace_gamma: float = 3.0

    def __post_init__(self) -> None:
        if self.nis_window < 1:
            raise ValueError(f"nis_window must be >= 1, got {self.nis_window}")
        if self.nis_gate is not None and self.nis_gate not in GATE_ACTIONS:
            raise ValueError(f"nis_gate must be None or one of {GATE_ACTIONS}, got {self.nis_gate!r}")
        if not 0.0 < self.nis_gate_prob < 1.0:
            raise ValueError(f"nis_gate_prob must lie in (0, 1), got {self.nis_gate_prob}")
        if self.gate_test not in GATE_TESTS:
            raise ValueError(f"gate_test must be one of {GATE_TESTS}, got {self.gate_test!r}")
        if not self.trace_gamma > 0:
            raise ValueError(f"trace_gamma must be > 0, got {self.trace_gamma}")
        if not 0.0 <= self.p_stay <= 1.0:
            raise ValueError(f"p_stay must lie in [0, 1], got {self.p_stay}")
        if not 0.0 <= self.b_min < 1.0:
            raise ValueError(f"b_min must lie in [0, 1), got {self.b_min}")
        if not 0.0 <= self.bc_rho < 1.0:
            raise ValueError(f"bc_rho must lie in [0, 1), got {self.bc_rho}")
        if self.min_plots < 1:
            raise ValueError(f"min_plots must be >= 1, got {self.min_plots}")
        if self.ci_objective not in CI_OBJECTIVES:
            raise ValueError(f"ci_objective must be one of {CI_OBJECTIVES}, got {self.ci_objective!r}")


class Fused(NamedTuple):
    """Kernel result: per-group state (G, 6) and covariance (G, 6, 6); per-row weights (n,)."""

    x: F
    cov: F
    weights: F


@dataclass(frozen=True)
class Layout:
    """Rows sorted by group (run, epoch, target_id), radar_id within a group.

    * ``starts`` (G,): first row of each group; ``counts`` (G,): rows per group (N);
    * ``group`` (n,): group index of each row;
    * ``prev_row`` (n,): row holding the same (run, target_id, radar_id) at the target's
      previous fused epoch when the radar set is unchanged, else −1 (restart at 1/N);
    * ``level`` (G,): rank of the group's epoch along its target's history (recursion order).
    """

    starts: Ix
    counts: Ix
    group: Ix
    prev_row: Ix
    level: Ix

    @classmethod
    def from_starts(cls, starts: Ix, n: int, prev_row: Ix | None = None, level: Ix | None = None) -> Layout:
        """Layout of independent groups (no recursion links unless given)."""
        starts = np.asarray(starts, dtype=np.intp)
        counts = np.diff(np.append(starts, n))
        group = np.repeat(np.arange(len(starts)), counts)
        prev = np.full(n, -1, dtype=np.intp) if prev_row is None else np.asarray(prev_row, dtype=np.intp)
        lev = np.zeros(len(starts), dtype=np.intp) if level is None else np.asarray(level, dtype=np.intp)
        return cls(starts, counts, group, prev, lev)

    @cached_property
    def levels(self) -> Levels:
        """The rows permuted into recursion order (computed once, shared by the recursions)."""
        n = len(self.group)
        order = np.argsort(self.level[self.group], kind="stable")
        bounds = np.append(0, np.cumsum(np.bincount(self.level[self.group]))).tolist()  # levels 0…max all occur
        pos = np.empty(n, dtype=np.intp)
        pos[order] = np.arange(n)
        prev = self.prev_row[order]
        prev = np.where(prev >= 0, pos[np.maximum(prev, 0)], -1)
        g = self.group[order]
        first = np.r_[True, g[1:] != g[:-1]][:n]
        return Levels(order, bounds, prev, np.cumsum(first) - 1, first, self.counts[g].astype(float))


class Levels(NamedTuple):
    """Rows of a :class:`Layout` in recursion order (by level, row order within a level).

    ``order``: row at each position; level k holds positions ``bounds[k]:bounds[k+1]``;
    ``prev``: position of the recursion predecessor (−1: restart); ``gid``: running group
    index; ``first``: first position of a group; ``n``: sources of the position's group."""

    order: Ix
    bounds: list[int]
    prev: Ix
    gid: Ix
    first: B
    n: F


# ---------------------------------------------------------------------------
# segment helpers and linear algebra
# ---------------------------------------------------------------------------


def _segsum(a: F, starts: Ix) -> F:
    """Σ over each group of rows (rows sorted by group). Matrices are scattered into a
    zero-padded (N_max, G, ...) block by rank within the group and its N_max slabs added in
    rank order, several times faster than ``np.add.reduceat`` along axis 0 of a
    multi-dimensional array."""
    if a.ndim == 1:
        return np.add.reduceat(a, starts)
    counts = np.diff(np.append(starts, len(a)))
    group = np.repeat(np.arange(len(starts)), counts)
    block = np.zeros((int(counts.max()), len(starts), *a.shape[1:]))
    block[np.arange(len(a)) - starts[group], group] = a
    out = block[0]
    for slab in block[1:]:
        out += slab
    return out


def _per_row(a: NDArray, starts: Ix, n: int) -> NDArray:
    """Broadcast a per-group value back to the group's rows."""
    return np.repeat(a, np.diff(np.append(starts, n)), axis=0)


def _sym(c: F) -> F:
    return 0.5 * (c + np.swapaxes(c, -1, -2))


def _chol(c: F) -> F:
    """Batched Cholesky factor of symmetric covariances; a matrix that is not positive
    definite is first projected onto PD (eigenvalues floored at 1e-12 × its largest)."""
    c = _sym(c)
    try:
        return np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(c)
        w = np.maximum(w, _EIG_FLOOR * np.maximum(w.max(axis=-1, keepdims=True), 1e-300))
        return np.linalg.cholesky(_sym((v * w[..., None, :]) @ np.swapaxes(v, -1, -2)))


def _inv_lapack(c: F) -> F:
    """Batched inverse on the diagonally scaled matrix by LAPACK; Cholesky with projection onto
    PD (:func:`_chol`) when a matrix is singular. The fallback of :func:`_inv_spd`."""
    d = 1.0 / np.sqrt(np.maximum(np.einsum("...ii->...i", c), 1e-300))
    r = c * d[..., :, None] * d[..., None, :]
    try:
        inv = np.linalg.inv(r)
        if not np.isfinite(inv).all():
            raise np.linalg.LinAlgError("non-finite inverse")
    except np.linalg.LinAlgError:
        lower = _chol(r)               # projects non-positive-definite matrices onto PD
        linv = np.linalg.solve(lower, np.broadcast_to(np.eye(c.shape[-1]), c.shape))
        inv = np.einsum("...ki,...kj->...ij", linv, linv, optimize=True)
    return _sym(inv * d[..., :, None] * d[..., None, :])


def _chol_inv_small(c: F) -> tuple[F, B]:
    """Inverse of m symmetric k×k matrices c (m, k, k) on their diagonally scaled form
    r = D c D, D = diag(c)^-1/2: Cholesky L Lᵀ = r, M = L⁻¹, c⁻¹ = D Mᵀ M D. Written element by
    element, each step one vector operation over the m matrices (several times faster than
    LAPACK's per-matrix calls for 6×6). Returns the inverse and a mask of the matrices found
    positive definite (the others hold garbage)."""
    k = c.shape[-1]
    d = [1.0 / np.sqrt(np.maximum(c[:, i, i], 1e-300)) for i in range(k)]
    low: list[list[F]] = [[d[0]] * k for _ in range(k)]   # filled below the diagonal
    dinv: list[F] = [d[0]] * k                          # 1 / L_jj
    ok = np.ones(len(c), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for j in range(k):
            s = c[:, j, j] * (d[j] * d[j])
            for p in range(j):
                s = s - low[j][p] * low[j][p]
            ok &= s > 0
            dinv[j] = 1.0 / np.sqrt(s)
            for i in range(j + 1, k):
                t = (0.5 * (c[:, i, j] + c[:, j, i])) * (d[i] * d[j])
                for p in range(j):
                    t -= low[i][p] * low[j][p]
                low[i][j] = t * dinv[j]
        m = [[dinv[i]] * k for i in range(k)]           # M_ii = 1 / L_ii; below it next
        for j in range(k):
            for i in range(j + 1, k):
                t = low[i][j] * m[j][j]
                for p in range(j + 1, i):
                    t += low[i][p] * m[p][j]
                m[i][j] = -t * dinv[i]
        out = np.empty_like(c)
        for i in range(k):
            for j in range(i + 1):
                t = m[i][i] * m[i][j]
                for p in range(i + 1, k):
                    t += m[p][i] * m[p][j]
                t *= d[i] * d[j]
                out[:, i, j] = t
                out[:, j, i] = t
    return out, ok & np.isfinite(out).all(axis=(1, 2))


_INV_CHUNK = 8_192  # matrices per call of _chol_inv_small: its per-element vectors stay in cache


def _inv_spd(c: F) -> F:
    """Batched inverse of symmetric positive-definite matrices, computed on the diagonally
    scaled (correlation-like) matrix via Cholesky (:func:`_chol_inv_small`); matrices that are
    not numerically positive definite go through :func:`_inv_lapack`."""
    flat = c.reshape(-1, *c.shape[-2:])
    out = np.empty_like(flat)
    for lo in range(0, len(flat), _INV_CHUNK):
        part, ok = _chol_inv_small(flat[lo:lo + _INV_CHUNK])
        out[lo:lo + _INV_CHUNK] = part
        if not ok.all():
            bad = lo + np.flatnonzero(~ok)
            out[bad] = _inv_lapack(flat[bad])
    return out.reshape(c.shape)


def _mix(x: F, cov: F, w: F, starts: Ix) -> tuple[F, F]:
    """x = Σ w_n x_n and P = Σ W_n C_n W_n for per-row weights w of shape (n,) or (n, 6)."""
    w6 = np.broadcast_to(w[:, None], x.shape) if w.ndim == 1 else w
    xf = _segsum(w6 * x, starts)
    pf = _segsum(w6[:, :, None] * cov * w6[:, None, :], starts)
    return xf, pf


def _keep_single(res: Fused, x: F, cov: F, starts: Ix) -> Fused:
    """Single-source groups: the report unchanged, weight 1."""
    n = len(x)
    single = np.diff(np.append(starts, n)) == 1
    rows = starts[single]
    res.x[single] = x[rows]
    res.cov[single] = cov[rows]
    res.weights[rows] = 1.0
    return res


# ---------------------------------------------------------------------------
# arithmetic, a-priori
# ---------------------------------------------------------------------------


def fuse_arithmetic(x: F, cov: F, starts: Ix) -> Fused:
    """Arithmetic mean (4.1): x = (1/N) Σ x_n, P = (1/N²) Σ C_n; weights 1/N."""
    n_row = _per_row(np.diff(np.append(starts, len(x))), starts, len(x)).astype(float)
    w = 1.0 / n_row
    xf, pf = _mix(x, cov, w, starts)
    return _keep_single(Fused(xf, pf, w), x, cov, starts)


def apriori_weights(nominal_var: F, starts: Ix) -> F:
    """Per-coordinate a-priori weights (4.3)–(4.4) for N radars, shape (n, 3):
    b_{n,c} = σ⁻²_{n,c} / Σ_m σ⁻²_{m,c}."""
    if not (np.isfinite(nominal_var).all() and (nominal_var > 0).all()):
        raise ValueError("apriori: nominal_var must be finite and positive in every row")
    inv = 1.0 / nominal_var
    return inv / _per_row(_segsum(inv, starts), starts, len(inv))


def fuse_apriori(x: F, cov: F, nominal_var: F, starts: Ix) -> Fused:
    """A-priori weights (4.3)–(4.4) per coordinate; velocity uses its position axis's weight.

    P = Σ B_n C_n B_n (independent radars). Reported weight: mean of the x, y, z weights."""
    b3 = apriori_weights(nominal_var, starts)
    xf, pf = _mix(x, cov, np.tile(b3, 2), starts)
    return _keep_single(Fused(xf, pf, b3.mean(axis=1)), x, cov, starts)


# ---------------------------------------------------------------------------
# a-posteriori recursions
# ---------------------------------------------------------------------------

LogPrior = Callable[[F, F], F]  # (b(k−1), N) per row -> log c_n(k)


def _log_prior_seed(b_prev: F, n: F) -> F:
    """log(1 − b_n(k−1)): the printed prior of (4.73)/(4.74), digest §6.2."""
    with np.errstate(divide="ignore"):
        return np.log1p(-b_prev)


def _log_prior_markov(p_stay: float) -> LogPrior:
    """log c_n = log(p b_n + (1 − p)/(N − 1) (1 − b_n)) (digest §6.3)."""

    def log_prior(b_prev: F, n: F) -> F:
        q = (1.0 - p_stay) / np.maximum(n - 1.0, 1.0)
        with np.errstate(divide="ignore"):
            return np.log(p_stay * b_prev + q * (1.0 - b_prev))

    return log_prior


def _log_normal(nu: F, var: F) -> F:
    """log N(ν; 0, var) = −½ log(2π var) − ν²/(2 var) (the seed's L_n)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return -0.5 * np.log(2.0 * np.pi * var) - nu * nu / (2.0 * var)


def _usable(fresh: B, nu: F, var: F) -> B:
    """A new, finite innovation with a finite positive variance."""
    return fresh & np.isfinite(nu) & np.isfinite(var) & (var > 0)


def _bayes_step(prior: F, loglik: F, usable: B, n: F, starts: Ix, log_prior: LogPrior, b_min: float,
                gid: Ix | None = None) -> F:
    """One update of the weights of the rows of a set of groups (rows sorted by group).

    b_n ∝ L_n c_n over the usable rows, which share the mass Σ_usable b(k−1); other rows and
    groups without a finite log-term keep b(k−1); single-source groups get 1. ``gid``: the
    group (0 … G−1) of each row, derived from ``starts`` when not given."""
    if gid is None:
        gid = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(prior))))
    t = np.where(usable, loglik + log_prior(prior, n), -np.inf)
    t = np.where(np.isnan(t), -np.inf, t)
    peak = np.maximum.reduceat(t, starts)[gid]
    ok = usable & np.isfinite(peak)
    with np.errstate(invalid="ignore"):
        e = np.exp(np.where(ok, t - peak, -np.inf))
    p = e / np.where(ok, np.add.reduceat(e, starts)[gid], 1.0)
    if b_min > 0:
        p = np.where(ok, np.maximum(p, b_min), 0.0)
        p = p / np.where(ok, np.add.reduceat(p, starts)[gid], 1.0)
    mass = np.add.reduceat(np.where(ok, prior, 0.0), starts)[gid]
    b = np.where(ok, mass * p, prior)
    return np.where(n == 1, 1.0, b)


def _recursive_weights(loglik: F, usable: B, lay: Layout, log_prior: LogPrior, b_min: float,
                       b0: F | None = None) -> F:
    """Run the recursion level by level (epoch rank along each target's history), on the rows
    permuted into level order so that every level is a contiguous slice. ``b0`` (n,), optional:
    the weight b(k−1) carried from the previous window for rows without an in-call
    predecessor (NaN: restart at 1/N)."""
    b = np.empty(len(loglik))
    if len(loglik) == 0:
        return b
    lv = lay.levels
    lik, use = loglik[lv.order], usable[lv.order]
    start = np.full(len(b), np.nan) if b0 is None else np.asarray(b0, float)[lv.order]
    bp = np.empty(len(b))                               # weights in level order
    for lo, hi in zip(lv.bounds[:-1], lv.bounds[1:]):
        gid = lv.gid[lo:hi] - lv.gid[lo]
        local = np.flatnonzero(lv.first[lo:hi])
        prev, n = lv.prev[lo:hi], lv.n[lo:hi]
        carried = start[lo:hi]
        prior = np.where(prev >= 0, bp[np.maximum(prev, 0)], np.where(np.isfinite(carried), carried, 1.0 / n))
        prior = prior / np.add.reduceat(prior, local)[gid]  # no rounding drift
        bp[lo:hi] = _bayes_step(prior, lik[lo:hi], use[lo:hi], n, local, log_prior, b_min, gid)
    b[lv.order] = bp
    return b


def seed_weights(res: F, d_fixed: F, fresh: B, lay: Layout, b0: F | None = None) -> F:
    """Printed a-posteriori weights (4.73)–(4.74), N radars (digest §6.2), b(0) = 1/N (4.77)."""
    loglik = _log_normal(res, d_fixed)
    return _recursive_weights(loglik, _usable(fresh, res, d_fixed), lay, _log_prior_seed, 0.0, b0)


def markov_weights(res: F, res_var: F, fresh: B, lay: Layout, p_stay: float, b_min: float,
                   b0: F | None = None) -> F:
    """Corrected a-posteriori weights (digest §6.3) with per-step S_n(k) = ``res_var``."""
    loglik = _log_normal(res, res_var)
    usable = _usable(fresh, res, res_var)
    return _recursive_weights(loglik, usable, lay, _log_prior_markov(p_stay), b_min, b0)


def fuse_weighted(x: F, cov: F, w: F, starts: Ix) -> Fused:
    """(4.72) with given per-row weights on every coordinate: x = Σ b_n x_n, P = Σ b_n² C_n."""
    xf, pf = _mix(x, cov, w, starts)
    return _keep_single(Fused(xf, pf, w), x, cov, starts)


def fuse_aposteriori_seed(x: F, cov: F, res: F, d_fixed: F, fresh: B, lay: Layout) -> Fused:
    """(4.72) with the weights of :func:`seed_weights` on every coordinate; P = Σ b_n² C_n."""
    return fuse_weighted(x, cov, seed_weights(res, d_fixed, fresh, lay), lay.starts)


def fuse_aposteriori(x: F, cov: F, res: F, res_var: F, fresh: B, lay: Layout,
                     p_stay: float = 0.95, b_min: float = 0.01) -> Fused:
    """(4.72) with the weights of :func:`markov_weights` on every coordinate; P = Σ b_n² C_n."""
    return fuse_weighted(x, cov, markov_weights(res, res_var, fresh, lay, p_stay, b_min), lay.starts)


# ---------------------------------------------------------------------------
# information fusion and covariance intersection
# ---------------------------------------------------------------------------


def _information_mix(x: F, cov: F, omega: F, starts: Ix, cov_inv: F | None = None) -> Fused:
    """P⁻¹ = Σ ω_n C_n⁻¹, x = x_ref + P Σ ω_n C_n⁻¹ (x_n − x_ref) (x_ref: the group's first
    row, which leaves identical reports exactly unchanged); weights tr(P ω_n C_n⁻¹)/6.
    ``cov_inv``: the C_n⁻¹ when already computed (shared by information fusion and CI)."""
    n = len(x)
    info = omega[:, None, None] * (_inv_spd(cov) if cov_inv is None else cov_inv)
    pf = _inv_spd(_segsum(info, starts))  # _inv_spd reads the symmetric part: no _sym needed
    dx = x - _per_row(x[starts], starts, n)
    xf = x[starts] + np.einsum("gij,gj->gi", pf, _segsum(np.einsum("nij,nj->ni", info, dx), starts))
    w = np.einsum("nij,nji->n", _per_row(pf, starts, n), info) / 6.0
    w = w / _per_row(_segsum(w, starts), starts, n)
    return Fused(xf, pf, w)


def fuse_information(x: F, cov: F, starts: Ix, cov_inv: F | None = None) -> Fused:
    """Inverse-covariance fusion (digest §6.4): P = (Σ C_n⁻¹)⁻¹, x = P Σ C_n⁻¹ x_n."""
    res = _information_mix(x, cov, np.ones(len(x)), starts, cov_inv)
    return _keep_single(res, x, cov, starts)


def _ci_profile(c1: F, c2: F) -> tuple[F, F, F]:
    """Simultaneous diagonalisation of a pair: C2 = L Lᵀ, L⁻¹ C1 L⁻ᵀ = U Γ Uᵀ, W = L U.

    Then P(ω) = W diag(γ/(ω + γ(1−ω))) Wᵀ, so tr P = Σ a_k γ_k/(ω + γ_k(1−ω)) with
    a_k = ‖W_k‖², and log det P = const − Σ log(ω + γ_k(1−ω)). Returns (γ, a, W)."""
    lower = _chol(c2)
    linv = np.linalg.solve(lower, np.broadcast_to(np.eye(6), lower.shape))
    gam, u = np.linalg.eigh(_sym(linv @ _sym(c1) @ np.swapaxes(linv, -1, -2)))
    gam = np.maximum(gam, _EIG_FLOOR * np.maximum(gam.max(axis=-1, keepdims=True), 1e-300))
    w = lower @ u
    return gam, np.einsum("gik,gik->gk", w, w), w


def _ci_objective(omega: F, gam: F, a: F, objective: str) -> F:
    """tr P(ω) or log det P(ω) up to a constant (both convex in ω ∈ [0, 1])."""
    den = omega[:, None] + gam * (1.0 - omega[:, None])
    if objective == "det":
        return -np.log(den).sum(axis=1)
    return (a * gam / den).sum(axis=1)


def _golden_min(f: Callable[[F], F], size: int, atol: float = 0.0) -> F:
    """Minimiser on [0, 1] of convex functions, vectorised over groups (golden section;
    0.5 and the endpoints are candidates too; ties within 1e-12·|f| + ``atol`` prefer them
    in that order)."""
    phi = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.zeros(size), np.ones(size)
    c, d = hi - phi * (hi - lo), lo + phi * (hi - lo)
    fc, fd = f(c), f(d)
    for _ in range(_GOLDEN_ITERATIONS):
        left = fc <= fd
        hi, lo = np.where(left, d, hi), np.where(left, lo, c)
        new = np.where(left, hi - phi * (hi - lo), lo + phi * (hi - lo))
        fnew = f(new)
        c, d = np.where(left, new, d), np.where(left, c, new)
        fc, fd = np.where(left, fnew, fd), np.where(left, fc, fnew)
    # candidates in order of preference; a near-tie (flat objective, e.g. identical
    # covariances) goes to equal weights rather than to wherever rounding led the search
    cand = np.stack([np.full(size, 0.5), 0.5 * (lo + hi), np.zeros(size), np.ones(size)])
    vals = np.stack([f(v) for v in cand])
    best = vals.min(axis=0)
    pick = np.argmax(vals <= best + 1e-12 * np.abs(best) + atol, axis=0)
    return cand[pick, np.arange(size)]


def ci_pair_weights(c1: F, c2: F, objective: str = "trace") -> F:
    """ω of the first source of each pair, minimising tr P or det P (two-source CI)."""
    gam, a, _ = _ci_profile(c1, c2)
    atol = 1e-12 if objective == "det" else 0.0  # log det is O(1) near a tie, tr P is not
    return _golden_min(lambda om: _ci_objective(om, gam, a, objective), len(c1), atol)


def fuse_covariance_intersection(x: F, cov: F, starts: Ix, objective: str = "trace",
                                 cov_inv: F | None = None) -> Fused:
    """Covariance intersection: P⁻¹ = Σ ω_n C_n⁻¹, x = P Σ ω_n C_n⁻¹ x_n.

    Two sources: ω optimal for ``objective``; more: fast CI ω_n ∝ 1/tr C_n (Niehsen 2002)."""
    if objective not in CI_OBJECTIVES:
        raise ValueError(f"objective must be one of {CI_OBJECTIVES}, got {objective!r}")
    n = len(x)
    tr = np.einsum("nii->n", cov)
    omega = (1.0 / tr) / _per_row(_segsum(1.0 / tr, starts), starts, n)
    counts = np.diff(np.append(starts, n))
    first = starts[counts == 2]
    if len(first):
        om = ci_pair_weights(cov[first], cov[first + 1], objective)
        omega[first], omega[first + 1] = om, 1.0 - om
    res = _information_mix(x, cov, omega, starts, cov_inv)
    res = Fused(res.x, res.cov, omega)
    return _keep_single(res, x, cov, starts)


def _spd_roots(c: F) -> tuple[F, F]:
    """C⁻¹ and the symmetric C^{-1/2} of symmetric covariances (eigenvalues floored at
    1e-12 × the largest, as :func:`_chol`)."""
    w, v = np.linalg.eigh(_sym(c))
    w = np.maximum(w, _EIG_FLOOR * np.maximum(w.max(axis=-1, keepdims=True), 1e-300))
    vt = np.swapaxes(v, -1, -2)
    return (v / w[..., None, :]) @ vt, (v / np.sqrt(w)[..., None, :]) @ vt


def fuse_bar_shalom_campo(x: F, cov: F, starts: Ix, rho: float = 0.4) -> Fused:
    """Track-to-track fusion with the common-process-noise cross-covariance.

    The radars' track errors of one target are correlated because every local filter follows
    the same manoeuvre (common process noise). Two sources: Bar-Shalom & Campo (1986)

        x = x₁ + (P₁ − P₁₂)(P₁ + P₂ − P₁₂ − P₂₁)⁻¹ (x₂ − x₁),
        P = P₁ − (P₁ − P₁₂)(P₁ + P₂ − P₁₂ − P₂₁)⁻¹ (P₁ − P₂₁).                       (BC)

    The fusion centre does not see the local gains needed for the exact cross-covariance
    recursion, so P_ij uses the constant-correlation approximation (Bar-Shalom & Li 1995,
    *Multitarget-multisensor tracking*, §8.3): P_ij = ρ S_i S_j, S_i = C_i^{1/2} (symmetric
    root). N sources — the generalisation: the BLUE of N correlated estimates of one state
    (Chang, Saha & Bar-Shalom 1997), x = (Hᵀ Σ⁻¹ H)⁻¹ Hᵀ Σ⁻¹ x̄ with the 6N×6N joint covariance
    Σ_ij = P_ij, H = stacked identities; it reduces to (BC) for N = 2. With this P_ij,
    Σ = S̃ (M ⊗ I₆) S̃, S̃ = blockdiag(S_i), M = ρ 11ᵀ + (1 − ρ) I, whose inverse is known:
    M⁻¹ = (I − c 11ᵀ)/(1 − ρ), c = ρ / (1 + (N − 1)ρ). Hence, summing the blocks of Σ⁻¹,

        P⁻¹ = [Σ_i C_i⁻¹ − c (Σ_i S_i⁻¹)(Σ_j S_j⁻¹)] / (1 − ρ),
        x   = P [Σ_i C_i⁻¹ x_i − c (Σ_i S_i⁻¹)(Σ_j S_j⁻¹ x_j)] / (1 − ρ),

    segment sums over each group (no per-group loop). Weight of source j:
    W_j = P [C_j⁻¹ − c (Σ_i S_i⁻¹) S_j⁻¹]/(1 − ρ) (Σ_j W_j = I); reported tr W_j / 6. ρ = 0 is
    information fusion."""
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"rho must lie in [0, 1), got {rho}")
    n = len(x)
    n_row = _per_row(np.diff(np.append(starts, n)), starts, n).astype(float)
    c = rho / (1.0 + (n_row - 1.0) * rho)
    cinv, sinv = _spd_roots(cov)
    dx = x - _per_row(x[starts], starts, n)          # relative to the group's first source
    s_sum = _segsum(sinv, starts)
    s_sum_row = _per_row(s_sum, starts, n)
    c_g = c[starts]
    info = (_segsum(cinv, starts) - c_g[:, None, None] * s_sum @ s_sum) / (1.0 - rho)
    pf = _inv_spd(info)
    vec = (_segsum(np.einsum("nij,nj->ni", cinv, dx), starts)
           - c_g[:, None] * np.einsum("gij,gj->gi", s_sum, _segsum(np.einsum("nij,nj->ni", sinv, dx), starts)))
    xf = x[starts] + np.einsum("gij,gj->gi", pf, vec / (1.0 - rho))
    wmat = (cinv - c[:, None, None] * s_sum_row @ sinv) / (1.0 - rho)
    w = np.einsum("nij,nji->n", _per_row(pf, starts, n), wmat) / 6.0
    w = w / _per_row(_segsum(w, starts), starts, n)
    return _keep_single(Fused(xf, pf, w), x, cov, starts)


# ---------------------------------------------------------------------------
# optional methods: best source, NIS-inflated information, a-posteriori variants, NIS gate
# ---------------------------------------------------------------------------


def _onehot_min(v: F, starts: Ix) -> F:
    """1.0 at the first row of each group holding the group's minimum of ``v`` (NaN never wins
    unless the whole group is NaN: then the first row), 0 elsewhere."""
    n = len(v)
    key = np.where(np.isnan(v), np.inf, v)
    gid = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, n)))
    low = np.minimum.reduceat(key, starts)[gid]
    hit = key == low
    first = np.minimum.reduceat(np.where(hit, np.arange(n), n), starts)
    w = np.zeros(n)
    w[first] = 1.0
    return w


def fuse_best_source(x: F, cov: F, starts: Ix) -> Fused:
    """The single most accurate source (§1.3 (c)): each group's report with the smallest
    position-error trace tr C_n[0:3, 0:3], state and covariance unchanged; weights one-hot."""
    w = _onehot_min(np.einsum("nii->n", cov[:, :3, :3]), starts)
    pick = np.flatnonzero(w)
    return Fused(x[pick].copy(), cov[pick].copy(), w)


def nis(res: F, res_var: F) -> F:
    """Normalised innovation squared of the range channel, ν²/S (m = 1; NaN when unusable)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(np.isfinite(res) & (res_var > 0), res * res / res_var, np.nan)


def nis_inflation(rows: pl.DataFrame, window: int) -> F:
    """λ_n of ``invcov_nis`` per row (digest §6.4): max(1, mean of the last ``window`` values of
    ν²/S of the row's (run, radar, local track), counting its fresh rows up to this epoch);
    1 before the track's first usable innovation."""
    return nis_inflation_step(rows, window, None)[0]


def nis_inflation_step(rows: pl.DataFrame, window: int, carry: pl.DataFrame | None
                       ) -> tuple[F, pl.DataFrame]:
    """:func:`nis_inflation` continued across windows: ``carry`` holds per (run, radar, local
    track) its last ``window`` usable NIS values (``hist``, oldest first) and the last moving
    mean (``last_mean``); returns λ per row and the new carry."""
    v = nis(rows["res_range_m"].cast(pl.Float64).fill_null(np.nan).to_numpy(),
            rows["res_range_var_m2"].cast(pl.Float64).fill_null(np.nan).to_numpy())
    use = rows["fresh"].fill_null(False).to_numpy() & np.isfinite(v)
    carry = _empty_nis_carry() if carry is None else carry
    k = _track_keys(rows.select(*TRACK, "epoch")).with_columns(
        pl.Series("__v", np.where(use, v, np.nan)).fill_nan(None), pl.Series("__u", use)).with_row_index("__i")
    fresh = k.filter("__u").select(*TRACK, "epoch", "__i", "__v", pl.lit(1, pl.Int8).alias("__o"))
    # the carried history goes first in each track's sequence (order 0), oldest value first
    hist = (carry.join(fresh.select(TRACK).unique(), on=TRACK, how="semi").select(*TRACK, "hist")
            .explode("hist").drop_nulls("hist")
            .select(*TRACK, pl.lit(None, k.schema["epoch"]).alias("epoch"), pl.lit(None, pl.UInt32).alias("__i"),
                    pl.col("hist").alias("__v"), pl.lit(0, pl.Int8).alias("__o")))
    seq = (pl.concat([hist, fresh.cast(hist.schema)]).sort([*TRACK, "__o", "epoch"], maintain_order=True)
           .with_columns(pl.col("__v").rolling_mean(window, min_samples=1).over(TRACK).alias("__m")))
    allr = (k.join(seq.filter(pl.col("__o") == 1).select("__i", "__m"), on="__i", how="left")
            .sort([*TRACK, "epoch", "__i"])
            .with_columns(pl.col("__m").forward_fill().over(TRACK))
            .join(carry.select(*TRACK, "last_mean"), on=TRACK, how="left", maintain_order="left")
            .sort("__i"))
    lam = np.maximum(allr["__m"].fill_null(allr["last_mean"]).fill_null(1.0).to_numpy(), 1.0)
    new = seq.group_by(TRACK, maintain_order=True).agg(pl.col("__v").tail(window).alias("hist"),
                                                       pl.col("__m").last().alias("last_mean"))
    new = pl.concat([carry.join(new, on=TRACK, how="anti"), new.cast(carry.schema)])
    return lam, new


def _empty_nis_carry() -> pl.DataFrame:
    return pl.DataFrame(schema={"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
                                "hist": pl.List(pl.Float64), "last_mean": pl.Float64})


def fuse_invcov_nis(x: F, cov: F, lam: F, starts: Ix) -> Fused:
    """``invcov_nis`` (digest §6.4): P = (Σ (λ_n C_n)⁻¹)⁻¹, x = P Σ (λ_n C_n)⁻¹ x_n."""
    return fuse_information(x, cov * lam[:, None, None], starts)


def los_innovation(x: F, site: F, res_var: F, sigma_r2: F, nominal_var: F) -> tuple[F, F, F]:
    """The 3-D innovation model of digest §6.1 from the range innovation: unit line of sight
    u_n (n, 3) from the radar site to the reported position, a_n = max(S_n − σ²_r, 0) (the
    predicted range variance without R, (4.75)) and the plot-noise diagonal D_n = nominal_var:
    ν_n = u_n ΔD_n, S_n = a_n u_n u_nᵀ + diag(D_n). Returns (u, a, D)."""
    d = x[:, :3] - site
    with np.errstate(invalid="ignore", divide="ignore"):
        u = d / np.linalg.norm(d, axis=1, keepdims=True)
    return u, np.maximum(res_var - sigma_r2, 0.0), nominal_var


def coord_loglik(res: F, u: F, a: F, dvar: F) -> tuple[F, F]:
    """Per-coordinate log-likelihoods (n, 3) of ν_{n,c} = u_c ΔD_n with variance
    S_{n,c} = a_n u_c² + D_c (the diagonal of the §6.1 S_n), and S_{n,c}."""
    s = a[:, None] * u * u + dvar
    return _log_normal(u * res[:, None], s), s


def mv_loglik(res: F, u: F, a: F, dvar: F) -> F:
    """log N(ν_n; 0, S_n) with ν = u ΔD, S = a u uᵀ + diag(D) (rank-one update, closed form):
    q = Σ u_c²/D_c, det S = Π D_c (1 + a q), νᵀS⁻¹ν = ΔD² q/(1 + a q)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.sum(u * u / dvar, axis=1)
        logdet = np.sum(np.log(dvar), axis=1) + np.log1p(a * q)
        return -1.5 * np.log(2.0 * np.pi) - 0.5 * logdet - 0.5 * res * res * q / (1.0 + a * q)


def seed_s_weights(res: F, res_var: F, fresh: B, lay: Layout, b0: F | None = None) -> F:
    """``aposteriori_seed_S``: the printed prior (1 − b(k−1)) of (4.73)–(4.74) with the per-step
    S_n(k) in L_n (digest §6.5 ``seed_S``), b(0) = 1/N (4.77)."""
    return _recursive_weights(_log_normal(res, res_var), _usable(fresh, res, res_var), lay, _log_prior_seed, 0.0,
                              b0)


def coord_weights(res: F, fresh: B, u: F, a: F, dvar: F, lay: Layout, p_stay: float, b_min: float,
                  b0: F | None = None) -> F:
    """Per-coordinate corrected a-posteriori weights b_{n,c} (n, 3) (digest §6.1, §6.3): one
    recursion per system axis on :func:`coord_loglik`; ``b0`` (n, 3) carried weights."""
    ll, s = coord_loglik(res, u, a, dvar)
    prior = _log_prior_markov(p_stay)
    return np.stack([_recursive_weights(ll[:, c], _usable(fresh, res, s[:, c]) & np.isfinite(ll[:, c]),
                                        lay, prior, b_min, None if b0 is None else b0[:, c])
                     for c in range(3)], axis=1)


def mv_weights(res: F, fresh: B, u: F, a: F, dvar: F, lay: Layout, p_stay: float, b_min: float,
               b0: F | None = None) -> F:
    """One corrected a-posteriori weight per radar from the multivariate N(ν_n; 0, S_n) (§6.1)."""
    ll = mv_loglik(res, u, a, dvar)
    return _recursive_weights(ll, fresh & np.isfinite(ll), lay, _log_prior_markov(p_stay), b_min, b0)


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


# ---------------------------------------------------------------------------
# frame level
# ---------------------------------------------------------------------------


def layout(keys: pl.DataFrame) -> Layout:
    """Group layout and recursion links of rows sorted by (run, epoch, target_id, radar_id)."""
    n = keys.height
    k = keys.select(*GROUP, "radar_id").with_row_index("__i")
    grp = k.group_by(GROUP, maintain_order=True).agg(
        pl.col("radar_id").alias("__set"), pl.col("__i").first().alias("__start"), pl.len().alias("__n"))
    grp = grp.with_columns(
        pl.int_range(pl.len()).over(CHAIN).alias("__level"),
        (pl.col("__set") == pl.col("__set").shift(1)).over(CHAIN).fill_null(False).alias("__cont"))
    starts = grp["__start"].to_numpy().astype(np.intp)
    counts = grp["__n"].to_numpy().astype(np.intp)
    if not np.array_equal(np.append(starts, n)[1:] - starts, counts):
        raise ValueError("rows must be sorted by (run, epoch, target_id, radar_id)")
    group = np.repeat(np.arange(len(starts)), counts)
    radar = keys["radar_id"].to_numpy()
    if n > 1 and np.any((group[1:] == group[:-1]) & (radar[1:] == radar[:-1])):
        raise ValueError("a radar contributes two reports to one (run, epoch, target_id)")
    prev = k.select(pl.col("__i").shift(1).over(CHAIN + ["radar_id"]))["__i"]
    prev = prev.fill_null(-1).to_numpy().astype(np.intp)
    prev = np.where(grp["__cont"].to_numpy()[group], prev, -1)
    return Layout(starts, counts, group, prev, grp["__level"].to_numpy().astype(np.intp))


def seed_fixed_variance(rows: pl.DataFrame, radars: pl.DataFrame, first: pl.DataFrame | None = None) -> F:
    """D_n of (4.75)–(4.76) per row: the step-1 predicted range variance without R,
    ``res_range_var_m2 − sigma_range_m²`` at the first row of the (run, radar, local track)
    with a finite innovation (NaN when the track has none). ``first`` (:func:`first_innovation_var`
    of the earlier windows): the tracks' first finite ``res_range_var_m2`` seen before ``rows``."""
    unknown = set(rows["radar_id"].unique().to_list()) - set(radars["radar_id"].to_list())
    if unknown:
        raise ValueError(f"aposteriori_seed: radar_id(s) {sorted(unknown)} missing from radars")
    first_var = first_innovation_var(rows, first)
    out = rows.select(*TRACK).join(first_var, on=TRACK, how="left", maintain_order="left").join(
        radars.select(pl.col("radar_id").cast(pl.UInt32), "sigma_range_m"),
        on="radar_id", how="left", maintain_order="left",
    ).select(pl.col("first_var") - pl.col("sigma_range_m") ** 2)
    return out.to_series().fill_null(np.nan).to_numpy().astype(float)


def _track_keys(df: pl.DataFrame) -> pl.DataFrame:
    """``df`` with its (run, radar_id, local_track_id) keys cast to the state's types."""
    return df.with_columns(pl.col("run").cast(pl.UInt32), pl.col("radar_id").cast(pl.UInt32),
                           pl.col("local_track_id").cast(pl.UInt32))


def first_innovation_var(rows: pl.DataFrame, first: pl.DataFrame | None = None) -> pl.DataFrame:
    """Per (run, radar, local track): the ``res_range_var_m2`` of its first row (in ``rows``'
    order, epoch order) with a finite innovation — from ``first`` (the earlier windows) when it
    has the track. Columns TRACK + ``first_var``; tracks without one are absent."""
    finite = pl.col("res_range_m").is_finite() & pl.col("res_range_var_m2").is_finite()
    now = (_track_keys(rows.select(*TRACK, "res_range_m", "res_range_var_m2")).filter(finite)
           .group_by(TRACK, maintain_order=True).agg(pl.col("res_range_var_m2").first().cast(pl.Float64)
                                                     .alias("first_var")))
    if first is None or first.is_empty():
        return now
    return pl.concat([first, now.join(first, on=TRACK, how="anti")])


def _check_columns(rows: pl.DataFrame) -> None:
    missing = [c for c in INPUT_COLUMNS if c not in rows.columns]
    if missing:
        raise ValueError(f"fusion input lacks column(s): {', '.join(missing)}")


def _arrays(rows: pl.DataFrame) -> dict[str, NDArray]:
    n = rows.height
    col = lambda c: rows[c].cast(pl.Float64).fill_null(np.nan).to_numpy()  # noqa: E731
    return {
        "x": rows.select(STATE).to_numpy().astype(float),
        "cov": _sym(rows["cov"].to_numpy().astype(float).reshape(n, 6, 6)),
        "res": col("res_range_m"),
        "res_var": col("res_range_var_m2"),
        "fresh": rows["fresh"].fill_null(False).to_numpy().astype(bool),
        "nominal_var": rows["nominal_var"].to_numpy().astype(float).reshape(n, 3),
    }


BLOCK_ROWS = 65_536


def _blocks(starts: Ix, n: int, block: int = BLOCK_ROWS):
    """(row slice, group-local starts) of runs of whole groups holding about ``block`` rows."""
    firsts = np.unique(np.searchsorted(starts, np.arange(0, n, block), side="right") - 1)
    bounds = np.append(firsts, len(starts))
    for g0, g1 in zip(bounds[:-1], bounds[1:]):
        r0 = int(starts[g0])
        r1 = int(starts[g1]) if g1 < len(starts) else n
        yield slice(r0, r1), starts[g0:g1] - r0


def _run_methods(methods: list[str], a: dict[str, NDArray], lay: Layout, d_fixed: Callable[[], F],
                 cfg: FusionConfig, b0: dict[str, F] | None = None) -> tuple[F, F, F, dict[str, F]]:
    """Every method over all groups: states (M, G, 6), covariances (M, G, 6, 6) and weights
    (M, n), M methods in the order given, and the per-axis weights (n, 3) of the methods that
    have them. The a-posteriori recursions run once over every row
    (per-row scalars); the mixing and all per-group linear algebra run block by block, all
    methods in one pass so that information fusion and CI share the block's C_n⁻¹, written
    straight into the outputs. Memory is bounded by the block, not by the dataset (stacked 6×6
    temporaries over all rows reached gigabytes). ``b0``: per recursive method, the weights
    carried from the previous window (NaN: none)."""
    x, cov, nominal = a["x"], a["cov"], a["nominal_var"]
    b0 = b0 or {}
    n_groups = len(lay.starts)
    xs = np.empty((len(methods), n_groups, 6))
    covs = np.empty((len(methods), n_groups, 6, 6))
    ws = np.empty((len(methods), len(x)))
    w = {}
    if "aposteriori_seed" in methods:
        w["aposteriori_seed"] = seed_weights(a["res"], d_fixed(), a["fresh"], lay, b0.get("aposteriori_seed"))
    if "aposteriori" in methods:
        w["aposteriori"] = markov_weights(a["res"], a["res_var"], a["fresh"], lay, cfg.p_stay, cfg.b_min,
                                          b0.get("aposteriori"))
    if "aposteriori_seed_S" in methods:
        w["aposteriori_seed_S"] = seed_s_weights(a["res"], a["res_var"], a["fresh"], lay, b0.get("aposteriori_seed_S"))
    los = (a["res"], a["fresh"], a["u"], a["a_pred"], a["dvar"], lay, cfg.p_stay, cfg.b_min) if "u" in a else None
    if "aposteriori_mv" in methods:
        w["aposteriori_mv"] = mv_weights(*los, b0.get("aposteriori_mv"))
    w3 = ({"aposteriori_coord": coord_weights(*los, b0.get("aposteriori_coord"))}
          if "aposteriori_coord" in methods else {})
    shared_inv = bool({"information", "covariance_intersection"} & set(methods))
    for r, st in _blocks(lay.starts, len(x)):
        g0 = int(np.searchsorted(lay.starts, r.start))
        g = slice(g0, g0 + len(st))
        xb, cb = x[r], cov[r]
        cinv = _inv_spd(cb) if shared_inv else None
        for i, m in enumerate(methods):
            if m in w:
                out = fuse_weighted(xb, cb, w[m][r], st)
            elif m == "arithmetic":
                out = fuse_arithmetic(xb, cb, st)
            elif m == "apriori":
                out = fuse_apriori(xb, cb, nominal[r], st)
            elif m == "information":
                out = fuse_information(xb, cb, st, cinv)
            elif m == "bar_shalom_campo":
                out = fuse_bar_shalom_campo(xb, cb, st, cfg.bc_rho)
            elif m == "covariance_intersection":
                out = fuse_covariance_intersection(xb, cb, st, cfg.ci_objective, cinv)
            elif m in w3:                          # per coordinate; velocity takes its axis's weight
                b3 = w3[m][r]
                xf, pf = _mix(xb, cb, np.tile(b3, 2), st)
                out = _keep_single(Fused(xf, pf, b3.mean(axis=1)), xb, cb, st)
            elif m == "best_source":
                out = fuse_best_source(xb, cb, st)
            elif m == "invcov_nis":
                out = fuse_invcov_nis(xb, cb, a["lam"][r], st)
            else:
                raise ValueError(f"unknown fusion method {m!r}")
            xs[i, g], covs[i, g], ws[i, r] = out
    return xs, covs, ws, w3


@dataclass(frozen=True)
class AltCarry:
    """Carried Mode C filters of the vertical channel: per (run, radar, local track) the
    :class:`~tertiary.stages.tracking.altitude.FilterCarry` columns after its last report (``report_id``), whose
    output serves the track's rows that still hold that report in a later window; ``ref_us``:
    the time base (µs) of the filters' ``t_last`` — the first report time ever filtered, so the
    seconds are the same floats as in one whole-run call."""

    tracks: pl.DataFrame | None = None
    ref_us: int | None = None


def _alt_lookup(carry: pl.DataFrame) -> pl.DataFrame:
    """(run, report_id) → the :data:`ALT_COLUMNS` and ``__has`` of each carried track's last report."""
    names = dict(zip(("h", "r", "phh", "phr", "prr"),
                     ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_cov_m2ps", "alt_rate_var_m2ps2")))
    return carry.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64),
                        *(pl.col(f"af_post_{f}").alias(c) for f, c in names.items()),
                        pl.col("af_has").alias("__has"))


def _mode_c_per_row(rows: pl.DataFrame, cfg: AltitudeConfig, carry: AltCarry = AltCarry()
                    ) -> tuple[AltState, B, AltCarry]:
    """Each row's Mode C estimate (h, ḣ, P) at its epoch and whether it has one: the filter of
    its (run, radar, local track) after the row's report, extrapolated by epoch − time. The
    filters continue from ``carry`` (earlier windows) and the new carry is returned."""
    n = rows.height
    none = AltState.full(n), np.zeros(n, bool), carry
    if "altitude_m" not in rows.columns or "time" not in rows.columns:
        return none
    fresh = pl.col("fresh").fill_null(False)
    has_s = "mode_s" in rows.columns
    # the Mode S address as an integer identity: a radar track whose address changes has swapped
    # aircraft, and its altitude filter restarts (tertiary.stages.tracking.altitude.filter_tracks, ident)
    ident = (pl.col("mode_s").cast(pl.String).str.to_integer(base=16, strict=False).fill_null(-1)
             if has_s else pl.lit(-1, pl.Int64))
    rep = _track_keys(rows.filter(fresh).select(*TRACK, pl.col("report_id").cast(pl.UInt64), "time", "altitude_m",
                                                (pl.col("mode_s").is_not_null() if has_s else pl.lit(True)).alias("__s"),
                                                ident.cast(pl.Int64).alias("__ident"))
                      .unique(subset=["run", "report_id"], keep="first", maintain_order=True)
                      .sort([*TRACK, "time"]))
    old = carry.tracks
    lookups = [] if old is None else [_alt_lookup(old)]
    ref_us, tracks = carry.ref_us, old
    if rep.height:
        keys = rep.select(TRACK).to_numpy()
        new = np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)]
        starts = np.flatnonzero(new)
        lengths = np.diff(np.append(starts, len(keys)))
        t_us = rep["time"].dt.epoch("us").to_numpy()
        ref_us = int(t_us.min()) if ref_us is None else ref_us
        t = (t_us - ref_us) * 1e-6
        z = rep["altitude_m"].cast(pl.Float64).fill_null(np.nan).to_numpy()
        var = quantisation_variance(np.where(rep["__s"].to_numpy(), QUANTUM_MODE_S_M, QUANTUM_MODE_C_M))
        init = _alt_init(rep[starts].select(TRACK), old, cfg)
        post, has, _, final = filter_tracks_carry(t, z, var, starts, lengths, cfg,
                                                  ident=rep["__ident"].to_numpy(), init=init)
        cols = post.columns()
        lookups.insert(0, rep.select("run", "report_id").with_columns(
            *(pl.Series(c, cols[c]) for c in ALT_COLUMNS), pl.Series("__has", has)))
        now = rep[starts + lengths - 1].select(*TRACK, "report_id").with_columns(
            pl.Series(c, v) for c, v in final.columns().items())
        tracks = now if old is None else pl.concat([old.join(now, on=TRACK, how="anti"), now])
    if not lookups:
        return AltState.full(n), np.zeros(n, bool), carry
    table = pl.concat(lookups, how="diagonal_relaxed").unique(subset=["run", "report_id"], keep="first",
                                                              maintain_order=True)
    j = rows.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64), "epoch", "time").join(
        table, on=["run", "report_id"], how="left", maintain_order="left")
    at = AltState(*(j[c].fill_null(np.nan).to_numpy() for c in
                    ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_cov_m2ps", "alt_rate_var_m2ps2")))
    age = (j["epoch"].dt.epoch("us").to_numpy() - j["time"].dt.epoch("us").to_numpy()) * 1e-6
    return (predict(at, np.maximum(age, 0.0), cfg.q_m2ps3), j["__has"].fill_null(False).to_numpy(),
            AltCarry(tracks, ref_us))


def _alt_init(keys: pl.DataFrame, old: pl.DataFrame | None, cfg: AltitudeConfig) -> FilterCarry:
    """The filters' starting state for the tracks ``keys`` (in order): carried where ``old`` has
    the track, else a filter that has seen nothing."""
    k = keys.height
    if old is None or old.is_empty():
        return FilterCarry.fresh(k, cfg)
    j = keys.join(old, on=TRACK, how="left", maintain_order="left")
    default = FilterCarry.fresh(1, cfg).columns()
    return FilterCarry.from_columns({c: j[c].fill_null(v[0]).to_numpy() for c, v in default.items()}, cfg)


def vertical_channel(rows: pl.DataFrame, lay: Layout, xs: F, covs: F, origin: geo.LocalFrame | None,
                     cfg: AltitudeConfig, carry: AltCarry = AltCarry()) -> tuple[dict[str, F], AltCarry]:
    """The :data:`~tertiary.stages.tracking.altitude.ALT_COLUMNS` of every (method, group), shape (M, G) each,
    stacked in method order: Mode C where a source has it, else the geodetic height of the
    method's fused state (module docstring); and the Mode C filters' new carry."""
    n_groups = len(lay.starts)
    per_row, has, carry = _mode_c_per_row(rows, cfg, carry)
    mode_c, got = combine_min_variance(per_row, has, lay.group, n_groups)
    mc = mode_c.columns()
    out = {c: np.repeat(mc[c][None], len(xs), axis=0) for c in ALT_COLUMNS}
    rest = np.flatnonzero(~got)                      # the fallback only where no Mode C
    for i in range(len(xs)):
        fb = geodetic_channel(xs[i, rest], covs[i, rest], origin).columns()
        for c in ALT_COLUMNS:
            out[c][i, rest] = fb[c]
    return out, carry


# ---------------------------------------------------------------------------
# measurements for the secondary tracker: freshness and plot-level fusion
# ---------------------------------------------------------------------------

PLOT_COLUMNS = ["plot_x_m", "plot_y_m", "plot_z_m", "plot_cov"]
#: methods whose plot-level measurement is the inverse-covariance combination of the plots
_INFO_PLOTS = ("information", "covariance_intersection", "bar_shalom_campo", "invcov_nis")


def measured_plots(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
                   altitude_sigma_m: float = 30.0) -> pl.DataFrame:
    """Each report's *measured* plot in the system frame, one row per report: run, report_id
    and :data:`PLOT_COLUMNS` (position and row-major 3×3 covariance R = M J R_polar Jᵀ Mᵀ from
    the radar's nominal sigmas, seed 002 eq. 12; :func:`tertiary.stages.fusion.centralized.converted_plots`),
    NaN where the plot cannot be converted. Unlike the radars' track estimates, these errors
    are white: independent from scan to scan and between radars. Pass it to :func:`fuse`
    (``plots=``): it is joined to the fresh rows only, so the aligned rows are not widened."""
    from tertiary.stages.fusion.centralized import converted_plots   # centralized imports nothing from here

    rep = reports if "run" in reports.columns else reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    z, r, ok = converted_plots(rep, radars, origin, altitude_sigma_m)
    return rep.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64)).with_columns(
        *(pl.Series(c, np.where(ok, z[:, i], np.nan)) for i, c in enumerate(PLOT_COLUMNS[:3])),
        pl.Series("plot_cov", np.where(ok[:, None], r.reshape(-1, 9), np.nan), dtype=pl.Array(pl.Float64, 9)))


@dataclass(frozen=True)
class ConfirmState:
    """Carried state of target confirmation (natural keys, no ranks): per local track the plots
    of its current life in its current target, the time of its last plot and that target
    (``tracks``: run, radar_id, local_track_id, n_plots, last_time, target_id) and the targets
    already confirmed (``targets``: run, target_id)."""

    tracks: pl.DataFrame
    targets: pl.DataFrame

    @staticmethod
    def empty() -> ConfirmState:
        return ConfirmState(
            pl.DataFrame(schema={"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
                                 "n_plots": pl.Int64, "last_time": TIME, "target_id": pl.UInt64}),
            pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64}))


#: a local track silent for longer than this has ended; a plot under the same number after it
#: starts a new life (radars reuse track numbers) whose plots are counted afresh
LIFE_GAP_S = 30.0


def confirm_step(state: ConfirmState, rows: pl.DataFrame, min_plots: int = 2
                 ) -> tuple[pl.DataFrame, ConfirmState]:
    """Which (run, epoch, target_id) groups of ``rows`` are tentative, and the new state.

    A local track supports its target from the epoch at which it has ``min_plots`` plots in
    its current life *in that target* (its fresh rows counted, carried across windows by
    ``state``; a silence longer than :data:`LIFE_GAP_S` starts a new life, since radars reuse
    the numbers of ended tracks, often for a false plot); a group is supported when one of its
    local tracks is, or when two radars see the target. A target is confirmed from its first
    supported group on and stays so; before that it is *tentative*: made only of one radar's
    unconfirmed one-plot tracks — the clutter signature (a lone false plot never gets a second
    plot of its local track). Counting in the target, not over the local track's life, keeps a
    split-off tentative: one radar's plot that misses the gate with the others for a scan is
    grouped alone under a new id and rejoins its aircraft's target at the next scan (counted
    over the track's life, such one-scan targets were 3 456 of the 6 131 confirmed targets of
    a 12 h terminal-area run). Returns the groups (GROUP + ``tentative``) in ``rows``' group
    order."""
    key_types = {c: t for c, t in state.tracks.schema.items() if c in TRACK}
    has_time = "time" in rows.columns
    when = pl.col("time").cast(TIME) if has_time else pl.col("epoch").cast(TIME)
    r = rows.select(*GROUP, *[pl.col(c).cast(t) for c, t in key_types.items() if c != "run"],
                    pl.col("fresh").fill_null(False), when.alias("__t")).with_row_index("__i")
    r = (r.join(state.tracks.rename({"target_id": "__last_target"}), on=TRACK, how="left", maintain_order="left")
         .sort("epoch", "__i"))
    fresh_t = pl.when(pl.col("fresh")).then(pl.col("__t"))
    prev = pl.coalesce(fresh_t.forward_fill().shift(1).over(TRACK), pl.col("last_time"))
    gap_us = round(LIFE_GAP_S * 1e6)
    brk = pl.col("fresh") & ((pl.col("__t") - prev).dt.total_microseconds() > gap_us).fill_null(False)
    # the track's target at its previous row (this window's, else the carried one)
    before = pl.coalesce(pl.col("target_id").shift(1).over(TRACK), pl.col("__last_target"))
    moved = (pl.col("target_id") != before).fill_null(False)
    r = r.with_columns((brk | moved).cast(pl.Int64).cum_sum().over(TRACK).alias("__life"))
    base = pl.when(pl.col("__life") == 0).then(pl.col("n_plots").fill_null(0)).otherwise(0)
    r = r.with_columns((base + pl.col("fresh").cast(pl.Int64).cum_sum().over([*TRACK, "__life"])).alias("__n"))
    grp = (r.group_by(GROUP, maintain_order=True)
           .agg(((pl.col("__n").max() >= min_plots) | (pl.col("radar_id").n_unique() >= 2)).alias("__sup"))
           .join(state.targets.with_columns(pl.lit(True).alias("__was")), on=CHAIN, how="left",
                 maintain_order="left")
           .with_columns((pl.col("__sup") | pl.col("__was").fill_null(False)).cum_max().over(CHAIN)
                         .alias("__conf")))
    order = rows.select(GROUP).unique(maintain_order=True)
    out = order.join(grp.select(*GROUP, (~pl.col("__conf")).alias("tentative")), on=GROUP, how="left",
                     maintain_order="left")
    last = r.group_by(TRACK).agg(pl.col("__n").last().alias("n_plots"),
                                 pl.col("__t").filter(pl.col("fresh")).max().alias("__lt"),
                                 pl.col("target_id").last().alias("__tg"))
    tracks = (state.tracks.join(last, on=TRACK, how="full", coalesce=True)
              .select(*TRACK, pl.coalesce("n_plots_right", "n_plots").alias("n_plots"),
                      pl.coalesce("__lt", "last_time").alias("last_time"),
                      pl.coalesce("__tg", "target_id").alias("target_id"))
              .cast(state.tracks.schema))
    targets = pl.concat([state.targets, grp.filter("__conf").select(CHAIN).cast(state.targets.schema)]).unique()
    return out, ConfirmState(tracks, targets)


def _solve3(r: F) -> F:
    """Inverse of 3×3 covariances (rows that are not invertible get NaN)."""
    out = np.full_like(r, np.nan)
    ok = np.isfinite(r).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.where(np.isfinite(r), r, 0.0))) > 0)
    if ok.any():
        out[ok] = np.linalg.inv(_sym(r[ok]))
    return out


def plot_measurement(zp: F, rp: F, use: B, age: F, vel: F, pvv: F, w: F | None, starts: Ix
                     ) -> tuple[F, F, F]:
    """Plot-level fusion of each group's fresh measured plots (rows ``use``), at the time of
    its newest one: returns z (G, 3), R (G, 3, 3) and that age (G,) (NaN: no fresh plot).

    A plot of age a_n is moved to the reference age a₀ = min a_n of its group with its radar's
    velocity estimate over d = a_n − a₀ (< one epoch period), z'_n = z_n + v_n d, and its
    covariance grown by d² P_vv,n (that small velocity term is the only correlated part; it is
    included in R, not removed). Then, with the method's weights ``w`` (n,) or per axis (n, 3)
    renormalised over the fresh plots, z = Σ W_n z'_n and R = Σ W_n R'_n W_n (the plots'
    errors are independent); with ``w`` None the inverse-covariance combination
    R = (Σ R'_n⁻¹)⁻¹, z = R Σ R'_n⁻¹ z'_n."""
    n = len(zp)
    use = use & np.isfinite(zp).all(axis=1) & np.isfinite(rp).all(axis=(1, 2)) & np.isfinite(age)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
    a0 = np.minimum.reduceat(np.where(use, age, np.inf), starts)
    d = np.where(use, age - _per_row(a0, starts, n), 0.0)
    zs = np.where(use[:, None], zp + np.nan_to_num(vel) * d[:, None], 0.0)
    rs = np.where(use[:, None, None], rp + d[:, None, None] ** 2 * np.nan_to_num(pvv), 0.0)
    if w is None:
        info = np.where(use[:, None, None], np.nan_to_num(_solve3(np.where(use[:, None, None], rs, np.eye(3)))), 0.0)
        r = _solve3(_segsum(info, starts))
        z = np.einsum("gij,gj->gi", r, _segsum(np.einsum("nij,nj->ni", info, zs), starts))
    else:
        w3 = np.where(use[:, None], np.broadcast_to(w.reshape(n, -1), (n, 3)), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            w3 = w3 / _per_row(_segsum(w3, starts), starts, n)
        w3 = np.where(use[:, None], np.nan_to_num(w3), 0.0)
        z = _segsum(w3 * zs, starts)
        r = _segsum(w3[:, :, None] * rs * w3[:, None, :], starts)
    none = ~np.isfinite(a0)
    z[none], r[none] = np.nan, np.nan
    return z, r, np.where(none, np.nan, a0)


def _fresh_plots(rows: pl.DataFrame, idx: Ix, plots: pl.DataFrame | None) -> tuple[F, F] | None:
    """Plot position (k, 3) and covariance (k, 3, 3) of the rows ``idx``: from ``plots`` (joined
    on run, report_id) or from the rows' own :data:`PLOT_COLUMNS`; None without either."""
    if plots is not None:
        sub = rows.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64))[idx].join(
            plots, on=["run", "report_id"], how="left", maintain_order="left")
    elif all(c in rows.columns for c in PLOT_COLUMNS):
        sub = rows.select(PLOT_COLUMNS)[idx]
    else:
        return None
    zp = sub.select(PLOT_COLUMNS[:3]).cast(pl.Float64).fill_null(np.nan).to_numpy()
    return zp, np.asarray(sub["plot_cov"].to_numpy(), float).reshape(len(idx), 3, 3)


def _measurements(rows: pl.DataFrame, methods: list[str], a: dict[str, NDArray], lay: Layout, ws: F,
                  plots: pl.DataFrame | None = None, axis_w: dict[str, F] | None = None) -> dict[str, F]:
    """:data:`~tertiary.contract.schema.FUSED_EXTRA` measurement columns (minus ``tentative``) of every
    (method, group), shape (M, G[, …]), stacked in method order. Only the fresh rows are
    read (their groups are a sorted subset of all groups)."""
    n, g, m = rows.height, len(lay.starts), len(methods)
    fresh = a["fresh"]
    n_fresh = np.add.reduceat(fresh.astype(np.int64), lay.starts) if n else np.zeros(0, np.int64)
    age = (rows["age_s"].cast(pl.Float64).fill_null(np.nan).to_numpy() if "age_s" in rows.columns
           else np.full(n, np.nan))
    with np.errstate(invalid="ignore"):
        newest = np.fmin.reduceat(age, lay.starts) if n else np.zeros(0)
    out = {"n_fresh": np.repeat(n_fresh[None], m, axis=0), "age_s": np.repeat(newest[None], m, axis=0),
           "meas": np.full((m, g, 3), np.nan), "meas_cov": np.full((m, g, 9), np.nan)}
    idx = np.flatnonzero(fresh)
    got = _fresh_plots(rows, idx, plots) if len(idx) and "age_s" in rows.columns else None
    if got is None:
        return out
    zp, rp = got
    gid = lay.group[idx]
    sub_starts = np.flatnonzero(np.r_[True, gid[1:] != gid[:-1]])
    gsub = gid[sub_starts]
    vel, pvv = a["x"][idx, 3:], a["cov"][idx, 3:, 3:]
    for i, meth in enumerate(methods):
        w = (None if meth in _INFO_PLOTS else
             apriori_weights(a["nominal_var"], lay.starts)[idx] if meth == "apriori" else
             axis_w[meth][idx] if axis_w and meth in axis_w else
             _onehot_min(np.einsum("nii->n", rp), sub_starts) if meth == "best_source" else ws[i][idx])
        z, r, a0 = plot_measurement(zp, rp, np.ones(len(idx), bool), age[idx], vel, pvv, w, sub_starts)
        out["meas"][i, gsub], out["meas_cov"][i, gsub] = z, r.reshape(-1, 9)
        out["age_s"][i, gsub] = np.where(np.isfinite(a0), a0, newest[gsub])
    return out


def _check_methods(methods: Sequence[str]) -> list[str]:
    if isinstance(methods, str):
        methods = [methods]
    bad = [m for m in methods if m not in ALL_METHODS]
    if bad:
        raise ValueError(f"unknown fusion method(s) {bad}; choose from {', '.join(ALL_METHODS)}")
    return list(dict.fromkeys(methods))


def _apply_gate(rows: pl.DataFrame, cfg: FusionConfig) -> tuple[pl.DataFrame, F | None]:
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


def _radar_sites(rows: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame) -> tuple[F, F]:
    """Each row's radar site in the system frame (n, 3) and σ²_range (n,)."""
    unknown = set(rows["radar_id"].unique().to_list()) - set(radars["radar_id"].to_list())
    if unknown:
        raise ValueError(f"radar_id(s) {sorted(unknown)} missing from radars")
    e, n_, u = origin.from_geodetic(radars["lat_deg"].to_numpy(), radars["lon_deg"].to_numpy(),
                                    radars["alt_m"].to_numpy())
    table = radars.select(pl.col("radar_id").cast(pl.UInt32), pl.col("sigma_range_m").cast(pl.Float64)
                          ).with_columns(pl.Series("__e", e), pl.Series("__n", n_), pl.Series("__u", u))
    j = rows.select(pl.col("radar_id").cast(pl.UInt32)).join(table, on="radar_id", how="left", maintain_order="left")
    return j.select("__e", "__n", "__u").to_numpy(), j["sigma_range_m"].to_numpy() ** 2


def _method_inputs(methods: list[str], rows: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame | None,
                   cfg: FusionConfig, a: dict[str, NDArray]) -> None:
    """Per-row inputs of the optional methods, added to ``a``: λ of ``invcov_nis``; the line of
    sight and §6.1 innovation terms of ``aposteriori_coord`` / ``aposteriori_mv``."""
    if "invcov_nis" in methods:
        a["lam"] = nis_inflation(rows, cfg.nis_window)
    los = [m for m in methods if m in ("aposteriori_coord", "aposteriori_mv")]
    if los:
        if origin is None:
            raise ValueError(f"{', '.join(los)}: needs the system frame origin (fuse(..., origin=...)) "
                             "for each radar's line of sight")
        site, sig2 = _radar_sites(rows, radars, origin)
        a["u"], a["a_pred"], a["dvar"] = los_innovation(a["x"], site, a["res_var"], sig2, a["nominal_var"])


#: the recursive (a-posteriori) methods whose weights are carried across windows
RECURSIVE = ("aposteriori_seed", "aposteriori", "aposteriori_seed_S", "aposteriori_mv", "aposteriori_coord")


@dataclass(frozen=True)
class FuseState:
    """Everything :func:`fuse_step` carries from one window to the next (natural keys only):

    * ``chains``: per (run, target_id, radar_id) of each target's last fused group, the weights
      b(k−1) of the a-posteriori recursions (``w_<method>``; ``w_aposteriori_coord_{0,1,2}``
      per axis) — the radar set of that group is its rows;
    * ``seed_first``: per (run, radar_id, local_track_id) the first finite ``res_range_var_m2``
      (D_n of ``aposteriori_seed``, (4.75)–(4.76));
    * ``nis``: per local track the last ``nis_window`` NIS values and moving mean (``invcov_nis``);
    * ``alt``: the Mode C filters of the vertical channel (:class:`AltCarry`);
    * ``confirm``: target confirmation (:class:`ConfirmState`);
    * ``reached_us``: the end of the last window stepped (µs since the Unix epoch), None before.

    The frames keep one row per target / local track ever seen (a few numbers each), since a
    target or track may resume after any silence."""

    chains: pl.DataFrame
    seed_first: pl.DataFrame
    nis: pl.DataFrame
    alt: AltCarry
    confirm: ConfirmState
    reached_us: int | None = None


def init_fuse_state() -> FuseState:
    """The state before the first window."""
    return FuseState(pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64, "radar_id": pl.UInt32}),
                     pl.DataFrame(schema={"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
                                          "first_var": pl.Float64}),
                     _empty_nis_carry(), AltCarry(), ConfirmState.empty(), None)


def _weight_columns(method: str) -> list[str]:
    return [f"w_{method}_{c}" for c in range(3)] if method == "aposteriori_coord" else [f"w_{method}"]


def _carried_weights(rows: pl.DataFrame, chains: pl.DataFrame, methods: list[str]) -> dict[str, F]:
    """Per recursive method, b(k−1) of each row from ``chains``: for the rows of each target's
    first group in ``rows`` when its radar set equals the carried one (else the recursion
    restarts at 1/N, as within a call); NaN elsewhere."""
    rec = [m for m in methods if m in RECURSIVE]
    if not rec or chains.is_empty():
        return {}
    keys = rows.select(pl.col("run").cast(pl.UInt32), "epoch", pl.col("target_id").cast(pl.UInt64),
                       pl.col("radar_id").cast(pl.UInt32))
    first = (keys.group_by(GROUP, maintain_order=True).agg(pl.col("radar_id").alias("__set"))
             .group_by(CHAIN, maintain_order=True).first())
    sets = chains.group_by(CHAIN).agg(pl.col("radar_id").sort().alias("__old"))
    cont = first.join(sets, on=CHAIN, how="inner").filter(pl.col("__set") == pl.col("__old")).select(GROUP)
    cols = [c for m in rec for c in _weight_columns(m) if c in chains.columns]
    j = (keys.join(cont.with_columns(pl.lit(True).alias("__c")), on=GROUP, how="left", maintain_order="left")
         .join(chains.select(*CHAIN, "radar_id", *cols), on=[*CHAIN, "radar_id"], how="left", maintain_order="left"))
    ok = j["__c"].fill_null(False).to_numpy()
    col = lambda c: np.where(ok, j[c].cast(pl.Float64).fill_null(np.nan).to_numpy(), np.nan) if c in j.columns \
        else np.full(len(ok), np.nan)  # noqa: E731
    return {m: (np.stack([col(c) for c in _weight_columns(m)], axis=1) if m == "aposteriori_coord"
                else col(_weight_columns(m)[0])) for m in rec}


def _new_chains(rows: pl.DataFrame, chains: pl.DataFrame, methods: list[str], ws: F, w3: dict[str, F]
                ) -> pl.DataFrame:
    """``chains`` with every target of ``rows`` replaced by its last group and that group's weights."""
    rec = [m for m in methods if m in RECURSIVE]
    cols = []
    for i, m in enumerate(methods):
        if m == "aposteriori_coord":
            cols += [pl.Series(c, w3[m][:, a]) for a, c in enumerate(_weight_columns(m))]
        elif m in rec:
            cols.append(pl.Series(_weight_columns(m)[0], ws[i]))
    k = rows.select(pl.col("run").cast(pl.UInt32), "epoch", pl.col("target_id").cast(pl.UInt64),
                    pl.col("radar_id").cast(pl.UInt32)).with_columns(cols)
    last = k.filter(pl.col("epoch") == pl.col("epoch").max().over(CHAIN)).drop("epoch")
    return pl.concat([chains.join(last, on=CHAIN, how="anti"), last], how="diagonal_relaxed")


def _selected_alt_inputs(rows: pl.DataFrame) -> list[pl.Expr]:
    """``__sel`` (the row's selected altitude, null without) and ``__t`` (its report's age order:
    the report time, else −age_s, else none) for :func:`fuse_step`'s per-target latest."""
    def opt(c: str) -> pl.Expr:
        return pl.col(c).cast(pl.Float64).fill_nan(None) if c in rows.columns else pl.lit(None, pl.Float64)
    t = (pl.col("time").dt.epoch("us").cast(pl.Float64) if "time" in rows.columns
         else -pl.col("age_s").cast(pl.Float64) if "age_s" in rows.columns else pl.lit(0.0))
    # with the selected altitude, the BDS 5,0 track-angle rate (``__turn``) and the cleared level
    # from flight data (``__clr``) the same way
    return [opt(SELECTED_ALT_COLUMN).alias("__sel"), t.alias("__t"), opt(TURN_RATE_COLUMN).alias("__turn"),
            opt(CLEARED_ALT_COLUMN).alias("__clr")]


def fuse(rows: pl.DataFrame, radars: pl.DataFrame, methods: Sequence[str] = METHODS,
         cfg: FusionConfig = FusionConfig(), origin: geo.LocalFrame | None = None,
         plots: pl.DataFrame | None = None) -> pl.DataFrame:
    """Fuse the associated reports of every (run, epoch, target_id) with each method.

    ``rows`` holds :data:`INPUT_COLUMNS` (sorted here by (run, epoch, target_id, radar_id));
    null innovations count as NaN and a null ``fresh`` as False. ``radars`` (``radar_id``,
    ``sigma_range_m``) is read only by ``aposteriori_seed``, and with the sites (``lat_deg``,
    ``lon_deg``, ``alt_m``) and ``origin`` by ``aposteriori_coord`` / ``aposteriori_mv``. ``plots`` (:func:`measured_plots`)
    or the rows' own :data:`PLOT_COLUMNS` (with ``age_s``) give the tracker's measurement
    columns; without them those are null. Returns the ``fused`` table: the
    blocks of the methods in the order given, each sorted by (run, epoch, target_id).
    Raises ValueError for an unknown method, a missing column, or a radar reporting twice
    for one target at one epoch. The whole run as one window of :func:`fuse_step`."""
    return fuse_step(init_fuse_state(), rows, radars, methods, cfg, origin, plots)[0]


def fuse_step(state: FuseState, rows_window: pl.DataFrame, radars: pl.DataFrame, methods: Sequence[str] = METHODS,
              cfg: FusionConfig = FusionConfig(), origin: geo.LocalFrame | None = None,
              plots_window: pl.DataFrame | None = None, t0_us: int | None = None, t1_us: int | None = None
              ) -> tuple[pl.DataFrame, FuseState]:
    """:func:`fuse` of one time window, carrying every recursion in ``state`` (:class:`FuseState`).

    ``rows_window``: the fusion rows (aligned + target_id, :data:`INPUT_COLUMNS`, with ``time``,
    ``altitude_m``, ``mode_s``, ``age_s`` as the pipeline has them) with epoch in
    [``t0_us``, ``t1_us``) (µs since the Unix epoch; None = unbounded). ``plots_window``:
    :func:`measured_plots` of (at least) the reports of the window's fresh rows — every report
    whose first epoch lies in the window, i.e. reports with time in
    [t0_us − epoch period − max collection delay, t1_us); extra reports are ignored. No other
    history is needed. Stepping the windows of a run in order and concatenating the outputs
    gives :func:`fuse` of the whole run (same rows; values to round-off), provided ``methods``
    and ``cfg`` are the same in every window. The state passed in is not modified. Raises
    ValueError for rows outside the window (and as :func:`fuse`)."""
    methods = _check_methods(methods)
    _check_columns(rows_window)
    rows = rows_window
    reached = t1_us if t1_us is not None else state.reached_us
    if rows.height and (t0_us is not None or t1_us is not None):
        e = rows["epoch"].dt.epoch("us")
        if (t0_us is not None and e.min() < t0_us) or (t1_us is not None and e.max() >= t1_us):
            raise ValueError(f"fuse_step: rows_window has epochs outside [{t0_us}, {t1_us}) µs")
    schema = TABLES["fused"].required
    out_schema = {**schema, **TABLES["fused"].optional, **FUSED_EXTRA}
    if rows.height == 0 or not methods:
        return pl.DataFrame(schema=out_schema), replace(state, reached_us=reached)
    if not is_sorted_by(rows, [*GROUP, "radar_id"]):  # the pipeline passes sorted rows: skip the sort
        rows = rows.sort([*GROUP, "radar_id"], maintain_order=True)
    rows, inflate = _apply_gate(rows, cfg)
    lay, a = layout(rows), _arrays(rows)
    if inflate is not None:
        a["cov"] = a["cov"] * inflate[:, None, None]
    nis_carry = state.nis
    if "invcov_nis" in methods:
        a["lam"], nis_carry = nis_inflation_step(rows, cfg.nis_window, state.nis)
    _method_inputs([m for m in methods if m != "invcov_nis"], rows, radars, origin, cfg, a)
    seed_first = first_innovation_var(rows, state.seed_first)
    d_fixed = lambda: seed_fixed_variance(rows, radars, state.seed_first)  # noqa: E731
    b0 = _carried_weights(rows, state.chains, methods)
    xs, covs, ws, axis_w = _run_methods(methods, a, lay, d_fixed, cfg, b0)
    alt, alt_carry = vertical_channel(rows, lay, xs, covs, origin, cfg.altitude, state.alt)
    meas = _measurements(rows, methods, a, lay, ws, plots_window, axis_w)
    tentative, confirm = confirm_step(state.confirm, rows, cfg.min_plots)
    new_state = FuseState(_new_chains(rows, state.chains, methods, ws, axis_w), seed_first, nis_carry, alt_carry,
                          confirm, reached)
    mode_s = pl.col("mode_s").cast(pl.String) if "mode_s" in rows.columns else pl.lit(None, pl.String)
    head = rows.select(*GROUP, "radar_id", mode_s.alias("__s"), *_selected_alt_inputs(rows)).with_columns(
        pl.Series(f"__w{i}", ws[i]) for i in range(len(methods))
    ).group_by(GROUP, maintain_order=True).agg(
        pl.col("radar_id").alias("radar_ids"), pl.len().alias("n_sources"),
        # the target's identity: the address most of its reports carry (ties: the smallest)
        pl.col("__s").drop_nulls().mode().sort().first().alias("mode_s"),
        # its selected altitude (BDS 4,0): that of its newest report carrying one
        pl.col("__sel").sort_by("__t", "radar_id").drop_nulls().last().alias(SELECTED_ALT_COLUMN),
        # its track-angle rate (BDS 5,0): likewise the newest report's
        pl.col("__turn").sort_by("__t", "radar_id").drop_nulls().last().alias(TURN_RATE_COLUMN),
        # its cleared level from flight data (tertiary.stages.flight_data): likewise
        pl.col("__clr").sort_by("__t", "radar_id").drop_nulls().last().alias(CLEARED_ALT_COLUMN),
        *(pl.col(f"__w{i}") for i in range(len(methods))))
    head = head.with_columns(tentative["tentative"])
    keys = pl.concat([head.select(*GROUP, pl.lit(m).alias("method"), "radar_ids", "n_sources",
                                  pl.col(f"__w{i}").alias("weights"), "tentative", "mode_s", SELECTED_ALT_COLUMN,
                                  TURN_RATE_COLUMN, CLEARED_ALT_COLUMN)
                      for i, m in enumerate(methods)])
    # states and covariances of all methods in one go (they are stacked in method order)
    xs = xs.reshape(-1, 6)
    mz = meas["meas"].reshape(-1, 3)
    return keys.with_columns(
        *(pl.Series(c, xs[:, j]) for j, c in enumerate(STATE)),
        pl.Series("cov", covs.reshape(-1, 36)),
        *(pl.Series(c, alt[c].reshape(-1)) for c in ALT_COLUMNS),
        pl.Series("n_fresh", meas["n_fresh"].reshape(-1)),
        pl.Series("age_s", meas["age_s"].reshape(-1)).fill_nan(None),
        *(pl.Series(c, mz[:, j]).fill_nan(None) for j, c in enumerate(("meas_x_m", "meas_y_m", "meas_z_m"))),
        pl.Series("meas_cov", meas["meas_cov"].reshape(-1, 9), dtype=pl.Array(pl.Float64, 9)),
    ).with_columns(pl.when(pl.col("meas_x_m").is_not_null()).then(pl.col("meas_cov")).alias("meas_cov")
                   ).select(list(out_schema)).cast(out_schema), new_state
