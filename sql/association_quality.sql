-- Association quality: the evaluation's association metrics against truth (fraction of correctly
-- associated reports, target swaps, targets per aircraft, all-clutter targets) and the assignment
-- counters (gated pairs, ambiguous components, targets, reassignments) from the metrics table,
-- followed by counts from the associations table itself (association rows, mean assignment cost,
-- mean reports per target and epoch, mean radars per target and epoch).
-- Columns: metric, value, n_runs, source ('metrics' or 'associations').
SELECT metric, value, n_runs, 'metrics' AS source
FROM metrics
WHERE stage = 'association'
UNION ALL
SELECT unnest(['association_rows', 'mean_cost', 'reports_per_target_epoch', 'radars_per_target_epoch']) AS metric,
       unnest([rows, mean_cost, reports_per_target, radars_per_target])                                    AS value,
       n_runs,
       'associations' AS source
FROM (
    SELECT sum(n)::DOUBLE                          AS rows,
           sum(cost_sum) / sum(n)                  AS mean_cost,
           avg(n)                                  AS reports_per_target,
           avg(radars)                             AS radars_per_target,
           count(DISTINCT run)::UINTEGER           AS n_runs
    FROM (
        SELECT run, epoch, target_id, count(*) AS n, sum(cost) AS cost_sum, count(DISTINCT radar_id) AS radars
        FROM associations
        GROUP BY run, epoch, target_id
    )
)
ORDER BY source DESC, metric;
