-- Row accounting: every input report must end up aligned or rejected, exactly once. The input
-- count from the run record, the valid reports, the reports rejected per stage, the distinct reports
-- in aligned, the unaccounted balance (in − aligned − rejected; must be 0) and reports both aligned
-- and rejected (must be 0); then the row counts of the output tables.
-- Columns: item, rows.
WITH rej AS (
    SELECT stage, count(*) AS n FROM rejects WHERE input_table = 'reports' GROUP BY stage
),
counts AS (
    SELECT CAST(json_extract(value, '$.reports_in') AS BIGINT)          AS reports_in,
           (SELECT count(*) FROM reports)                              AS reports_valid,
           (SELECT coalesce(sum(n), 0) FROM rej)                       AS reports_rejected,
           (SELECT count(DISTINCT report_id) FROM aligned)             AS reports_aligned,
           (SELECT count(*) FROM (SELECT DISTINCT report_id FROM aligned) AS a
                JOIN (SELECT report_id FROM rejects WHERE input_table = 'reports') AS r USING (report_id)) AS both_aligned_and_rejected
    FROM run WHERE key = 'rows'
)
SELECT item, CAST(rows AS BIGINT) AS rows FROM (
    SELECT 1 AS k, 'reports_in' AS item, reports_in AS rows FROM counts
    UNION ALL SELECT 2, 'reports_valid', reports_valid FROM counts
    UNION ALL SELECT 3, 'reports_rejected', reports_rejected FROM counts
    UNION ALL SELECT 4, 'reports_rejected_at_' || stage, n FROM rej
    UNION ALL SELECT 5, 'reports_aligned', reports_aligned FROM counts
    UNION ALL SELECT 6, 'unaccounted', reports_in - reports_aligned - reports_rejected FROM counts
    UNION ALL SELECT 7, 'both_aligned_and_rejected', both_aligned_and_rejected FROM counts
    UNION ALL SELECT 8, 'aligned_rows', count(*) FROM aligned
    UNION ALL SELECT 9, 'associations_rows', count(*) FROM associations
    UNION ALL SELECT 10, 'fused_rows', count(*) FROM fused
    UNION ALL SELECT 11, 'clusters_rows', count(*) FROM clusters
    UNION ALL SELECT 12, 'tracks_rows', count(*) FROM tracks
    UNION ALL SELECT 13, 'conflicts_rows', count(*) FROM conflicts
)
ORDER BY k, item;
