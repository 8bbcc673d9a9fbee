"""Stage 5 — fusion of the associated plots into one estimate per system target and epoch: the
fusion methods behind one registry (:mod:`~tertiary.stages.fusion.registry`, one module per
family under :mod:`~tertiary.stages.fusion.methods`), the NIS gate, the vertical channel, the
tracker's measurement, target confirmation, the windowed step (:mod:`~tertiary.stages.fusion.step`)
and the centralised reference (:mod:`~tertiary.stages.fusion.centralized`)."""

from tertiary.stages.fusion.base import Fused, Layout, layout
from tertiary.stages.fusion.config import CI_OBJECTIVES, GATE_ACTIONS, GATE_TESTS, FusionConfig
from tertiary.stages.fusion.confirm import LIFE_GAP_S, ConfirmState, confirm_targets_step
from tertiary.stages.fusion.gate import chi2_threshold, gate_pass, nis, trace_test
from tertiary.stages.fusion.measurement import PLOT_COLUMNS, measured_plots, plot_measurement
from tertiary.stages.fusion.methods import ALL_METHODS, EXTRA_METHODS, INFO_PLOTS, METHODS, RECURSIVE
from tertiary.stages.fusion.methods.aposteriori import (coord_loglik, first_innovation_var, fuse_aposteriori,
                                                        fuse_aposteriori_seed, los_innovation, markov_weights,
                                                        mv_loglik, seed_fixed_variance, seed_weights)
from tertiary.stages.fusion.methods.bar_shalom_campo import fuse_bar_shalom_campo
from tertiary.stages.fusion.methods.nis import fuse_invcov_nis, nis_inflation, nis_inflation_step
from tertiary.stages.fusion.methods.weighted import (apriori_weights, ci_pair_weights, fuse_apriori, fuse_arithmetic,
                                                     fuse_best_source, fuse_covariance_intersection, fuse_information)
from tertiary.stages.fusion.registry import REGISTRY, FusionMethod, register
from tertiary.stages.fusion.step import INPUT_COLUMNS, FuseState, fuse, fuse_step, init_fuse_state
from tertiary.stages.fusion.vertical import AltCarry, vertical_channel

__all__ = [
    "ALL_METHODS", "AltCarry", "CI_OBJECTIVES", "ConfirmState", "EXTRA_METHODS", "FuseState", "Fused", "FusionConfig",
    "FusionMethod", "GATE_ACTIONS", "GATE_TESTS", "INFO_PLOTS", "INPUT_COLUMNS", "LIFE_GAP_S", "Layout", "METHODS",
    "PLOT_COLUMNS", "RECURSIVE", "REGISTRY", "apriori_weights", "chi2_threshold", "ci_pair_weights",
    "confirm_targets_step", "coord_loglik", "first_innovation_var", "fuse", "fuse_aposteriori",
    "fuse_aposteriori_seed", "fuse_apriori", "fuse_arithmetic", "fuse_bar_shalom_campo", "fuse_best_source",
    "fuse_covariance_intersection", "fuse_information", "fuse_invcov_nis", "fuse_step", "gate_pass", "init_fuse_state",
    "layout", "los_innovation", "markov_weights", "measured_plots", "mv_loglik", "nis", "nis_inflation",
    "nis_inflation_step", "plot_measurement", "register", "seed_fixed_variance", "seed_weights", "trace_test",
    "vertical_channel",
]
