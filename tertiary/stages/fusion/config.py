"""The fusion methods' parameters (:class:`FusionConfig`) and the options they choose from."""

from __future__ import annotations

from dataclasses import dataclass

from tertiary.stages.tracking.altitude import AltitudeConfig

__all__ = ["CI_OBJECTIVES", "GATE_ACTIONS", "GATE_TESTS", "FusionConfig"]

GATE_ACTIONS = ("reject", "downweight", "flag")
GATE_TESTS = ("chi2", "trace")
CI_OBJECTIVES = ("trace", "det")


@dataclass(frozen=True)
class FusionConfig:
    """Parameters of the fusion methods.

    * ``p_stay``: π_nn of the corrected a-posteriori recursion (0 reproduces the
      seed prior, 1 is pure Bayes, which locks in).
    * ``b_min``: floor of the corrected a-posteriori weights before renormalisation.
    * ``ci_objective``: ``"trace"`` or ``"det"`` of the covariance-intersection P (two sources).
    * ``bc_rho``: correlation coefficient ρ of the common-process-noise cross-covariance of
      ``bar_shalom_campo``, P_ij = ρ C_i^{1/2} C_j^{1/2} (Bar-Shalom & Li 1995; 0 gives
      information fusion).
    * ``min_plots``: a local track supports a target once it has this many plots (``tentative``);
      ``min_plots_primary``: as many for a track none of whose plots carried a transponder reply
      (primary-only: clutter's signature).
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
    min_plots_primary: int = 3
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
        if self.min_plots < 1 or self.min_plots_primary < 1:
            raise ValueError(f"min_plots and min_plots_primary must be >= 1, got {self.min_plots}, "
                             f"{self.min_plots_primary}")
        if self.ci_objective not in CI_OBJECTIVES:
            raise ValueError(f"ci_objective must be one of {CI_OBJECTIVES}, got {self.ci_objective!r}")
