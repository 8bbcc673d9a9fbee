"""The self-contained HTML report of a run (plotly), built from the run store."""
