"""The data contract: the tables' columns and types (:mod:`~tertiary.contract.tables`), the rules a
row must meet (:mod:`~tertiary.contract.rules`), and the validation that turns bad input into
``rejects`` rows with a reason (:mod:`~tertiary.contract.validation`,
:mod:`~tertiary.contract.rejects`). Built on :mod:`tertiary.core` only."""

from tertiary.contract.errors import SchemaError, UnsortedTimeWarning
from tertiary.contract.rejects import has_dtype, rejects_table
from tertiary.contract.rules import RULES, Limits, Rule, contract_rules, rules_markdown
from tertiary.contract.tables import (ADSB_QUALITY_COLUMNS, BOOL, CLEARED_ALT_COLUMN, COV, EHS_REPORT_COLUMNS, F64, FUSED_EXTRA, I64, INPUT_ROW,
                                      MLAT_PLOT_COLUMNS, REASON, ROW_INDEX, SELECTED_ALT_COLUMN, STR, TABLES, TIME,
                                      TURN_RATE_COLUMN, U32, U64, TableSchema, empty_frame, is_sorted_by, table_schema)
from tertiary.contract.validation import (as_frame, sort_tracks, streamed_median_time, table_median_time, table_order,
                                          unsorted_groups, unsorted_message, validate)

__all__ = [
    "ADSB_QUALITY_COLUMNS", "BOOL", "CLEARED_ALT_COLUMN", "COV", "EHS_REPORT_COLUMNS", "F64", "FUSED_EXTRA", "I64", "INPUT_ROW", "Limits",
    "MLAT_PLOT_COLUMNS", "REASON", "ROW_INDEX", "RULES", "Rule", "SELECTED_ALT_COLUMN", "STR", "SchemaError", "TABLES",
    "TIME", "TURN_RATE_COLUMN", "TableSchema", "U32", "U64", "UnsortedTimeWarning", "as_frame", "contract_rules",
    "empty_frame",
    "has_dtype", "is_sorted_by", "rejects_table", "rules_markdown", "sort_tracks", "streamed_median_time",
    "table_median_time", "table_order", "table_schema", "unsorted_groups", "unsorted_message", "validate",
]
