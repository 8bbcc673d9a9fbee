-- Run summary: the run record (scenario, versions, input fingerprints, row accounting, timings)
-- as key/value pairs.
-- Columns: key, value.
SELECT key, value
FROM run
ORDER BY key;
