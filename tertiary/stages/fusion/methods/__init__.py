"""The fusion methods, one module per family; importing this package registers them all in
:data:`tertiary.stages.fusion.registry.REGISTRY`. The method lists below are views of it."""

from tertiary.stages.fusion.methods import aposteriori, bar_shalom_campo, nis, weighted
from tertiary.stages.fusion.registry import registered

__all__ = ["ALL_METHODS", "EXTRA_METHODS", "INFO_PLOTS", "METHODS", "RECURSIVE", "aposteriori", "bar_shalom_campo",
           "nis", "weighted"]

#: the default methods, run unless the user names others
METHODS = registered(lambda m: m.default)
#: selectable by name, never in the default list (the main job's cost does not grow)
EXTRA_METHODS = registered(lambda m: not m.default)
ALL_METHODS = METHODS + EXTRA_METHODS
#: the recursive (a-posteriori) methods whose weights are carried across windows
RECURSIVE = registered(lambda m: m.recursive)
#: methods whose plot-level measurement is the inverse-covariance combination of the plots
INFO_PLOTS = registered(lambda m: m.info_plots)
