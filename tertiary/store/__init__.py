"""The run store: one DuckDB database (and Parquet parts) per run, the named SQL reports and the
run summary read from it."""

from tertiary.store.files import atomic_path, write_parquet_atomic, write_text_atomic
from tertiary.store.run_store import DB_FILENAME, TABLES_DIR, RunStore, export_parquet, record_run

__all__ = ["DB_FILENAME", "TABLES_DIR", "RunStore", "atomic_path", "export_parquet", "record_run",
           "write_parquet_atomic", "write_text_atomic"]
