-- Stage timings: wall-clock seconds of each pipeline stage from the run record (timings), slowest
-- first; total_s is the whole in-memory pipeline, alignment_to_clustering_s the sum of align,
-- associate, fuse, centralized and cluster, store_s the database write.
-- Columns: stage, seconds.
SELECT regexp_replace(t.key, '_s$', '')   AS stage,
       CAST(t.value AS DOUBLE)            AS seconds
FROM run, json_each(run.value) AS t
WHERE run.key = 'timings'
ORDER BY seconds DESC, stage;
