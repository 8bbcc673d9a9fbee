"""tertiary — tertiary processing of multi-radar air-traffic surveillance data.

The names a user needs are here; each lives in the sub-package of its pipeline stage
(``docs/architecture.md``) and is loaded when first used, so ``import tertiary`` is cheap and
changes nothing in the process (the CLI sets the allocator explicitly:
:func:`tertiary.core.memory.configure_allocator`).

* data contract: :func:`validate`, :data:`TABLES`, :data:`RULES`, :class:`Limits`
* datasets: :class:`Dataset`, :func:`read_dataset`, :func:`write_dataset`, :func:`load_scenario`
  (simulation: :mod:`tertiary.simulate`)
* the batch job: :class:`PipelineConfig` with each stage's configuration, :func:`run` (the run
  database, window by window, resumable), :func:`process` (in memory)
* evaluation of any picture: :func:`evaluate_pictures`, :func:`match_to_reference`,
  :func:`load_requirements`, :func:`check_requirements`
* results: :class:`RunStore`, :func:`export_parquet`, :func:`run_report`, :func:`list_reports`,
  :func:`build_report`
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: public name -> the module that defines it
_HOME: dict[str, str] = {
    **dict.fromkeys(("validate", "TABLES", "RULES", "Limits", "SchemaError"), "tertiary.contract"),
    **dict.fromkeys(("TertiaryError", "DataError", "OptionError", "ResourceError"), "tertiary.core.errors"),
    **dict.fromkeys(("Dataset", "read_dataset", "write_dataset"), "tertiary.io.dataset"),
    "load_scenario": "tertiary.simulate.config",
    "track_reports": "tertiary.sensors.local_tracks",
    **dict.fromkeys(("PipelineConfig", "process", "run", "StageError", "adapt_to_scenario"), "tertiary.pipeline"),
    "AlignConfig": "tertiary.stages.align",
    "AssociationConfig": "tertiary.stages.association.associate",
    **dict.fromkeys(("FusionConfig", "METHODS", "ALL_METHODS"), "tertiary.stages.fusion"),
    "ClusteringConfig": "tertiary.stages.clustering",
    "TrackerConfig": "tertiary.stages.tracking",
    "evaluate_pictures": "tertiary.evaluation.evaluate",
    **dict.fromkeys(("match_to_reference", "MatchConfig"), "tertiary.evaluation.matching"),
    **dict.fromkeys(("load_requirements", "check_requirements"), "tertiary.evaluation.requirements"),
    **dict.fromkeys(("RunStore", "export_parquet"), "tertiary.store"),
    **dict.fromkeys(("run_report", "list_reports"), "tertiary.store.sql_reports"),
    "build_report": "tertiary.report",
}

__all__ = sorted(_HOME)


def __getattr__(name: str) -> Any:
    # PEP 562: a public name's module is imported on first use, then the name is cached here
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module 'tertiary' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
