"""The batch job, the top of the pipeline: dataset in, one DuckDB run database out.

Stages are composed here and nowhere else: ingest/validate → align → gate + associate → fuse
(every selected method, plus the centralised measurement-level reference) → cluster → secondary
trackers on every fusion method's picture → conflict prediction on every picture, window by
window (:mod:`.streaming`); then on the whole run (:mod:`.whole_run`) evaluate (accuracy,
consistency, association, trackers, the posterior Cramér–Rao bound beside every picture, alerts
against truth, capacity from the measured accuracy) → store (:mod:`.runner`). Every input report
ends up in ``aligned`` or ``rejects`` (checked, not assumed). :func:`screen` applies every rule
that can reject a report, so ``tertiary validate`` reports exactly what ``tertiary run``
rejects; :func:`run` stores each stage's tables as soon as the stage completes, and a failing
stage still leaves the completed tables, the rejects and a run record saying so.
"""

from tertiary.pipeline.clock import Progress, StageClock
from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario, check_config, config_dict
from tertiary.pipeline.ingestion import Ingested, StreamedTruth, ingest, screen
from tertiary.pipeline.runner import StageError, fingerprint, process, run, scenario_text, versions
from tertiary.pipeline.stca_scoring import note_minima, reference_intervals
from tertiary.pipeline.streaming import (RunContext, StreamState, init_stream_state, pipeline_step, stream,
                                      track_identity, windowable)
from tertiary.pipeline.tables import (TABLE_MODES, PartTrim, Sink, StreamedTable, check_tables, make_storable, part_trim,
                                      store_sink)
from tertiary.pipeline.whole_run import Results, finalize

__all__ = ["PipelineConfig", "adapt_to_scenario", "check_config", "config_dict", "Progress", "StageClock",
           "Ingested", "StreamedTruth", "ingest", "screen", "RunContext", "StreamState", "init_stream_state",
           "pipeline_step", "stream", "track_identity", "windowable", "Results", "finalize", "StageError",
           "process", "run", "fingerprint", "scenario_text", "versions", "TABLE_MODES", "Sink", "StreamedTable",
           "check_tables", "store_sink", "make_storable", "note_minima", "reference_intervals", "PartTrim", "part_trim"]
