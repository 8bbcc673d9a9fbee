"""tertiary — tertiary processing of multi-radar air-traffic surveillance data.

Public API (the CLI is a thin layer over these):

* data contract: :func:`validate`, :data:`TABLES`, :class:`SchemaError`
* geodesy: :mod:`tertiary.geo` (WGS-84, ENU frames, radar polar, covariance propagation)
* simulation: :func:`simulate`, :func:`load_scenario`, :func:`write_dataset`, :func:`read_dataset`
* the radar's own secondary processing: :func:`track_reports`
* storage: :class:`RunStore`, :func:`export_parquet`
* the batch job: :func:`run`, :func:`ingest`
"""

from tertiary import geo
from tertiary.local_tracks import LocalTrackerConfig, track_reports
from tertiary.pipeline import ingest, run
from tertiary.schema import TABLES, Limits, SchemaError, UnsortedTimeWarning, validate
from tertiary.simulate import Dataset, load_scenario, read_dataset, simulate, write_dataset
from tertiary.store import RunStore, export_parquet

__version__ = "0.1.0"

__all__ = ["geo", "validate", "TABLES", "Limits", "SchemaError", "UnsortedTimeWarning", "simulate",
           "load_scenario", "write_dataset", "read_dataset", "Dataset", "track_reports", "LocalTrackerConfig",
           "RunStore", "export_parquet", "run", "ingest", "__version__"]
