"""The run store: one DuckDB database (and Parquet parts) per run, the named SQL reports and the
run summary read from it."""
