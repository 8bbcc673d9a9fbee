-- Cluster statistics per fusion method (clustering stage, "укрупнение"): distinct clusters (run,
-- cluster_id), cluster rows (cluster × epoch), epochs with at least one cluster (counted per run),
-- clusters per such epoch (mean, max), members per cluster row (mean, max) and lead changes
-- (consecutive epochs of one cluster whose lead target differs).
-- Columns: method, clusters, cluster_rows, epochs, mean_clusters_per_epoch, max_clusters_per_epoch,
-- mean_members, max_members, lead_changes, n_runs.
-- param: method = null   fusion method (null: all)
WITH c AS (
    SELECT *,
           lag(lead_target_id) OVER (PARTITION BY run, method, cluster_id ORDER BY epoch) AS prev_lead
    FROM clusters
    WHERE $method IS NULL OR method = $method
),
per_epoch AS (
    SELECT method, run, epoch, count(*) AS n FROM c GROUP BY method, run, epoch
)
SELECT c.method,
       count(DISTINCT (c.run, c.cluster_id))                                          AS clusters,
       count(*)                                                                       AS cluster_rows,
       (SELECT count(*) FROM per_epoch AS p WHERE p.method = c.method)                AS epochs,
       (SELECT avg(n) FROM per_epoch AS p WHERE p.method = c.method)                  AS mean_clusters_per_epoch,
       (SELECT max(n) FROM per_epoch AS p WHERE p.method = c.method)                  AS max_clusters_per_epoch,
       avg(c.count)                                                                   AS mean_members,
       max(c.count)                                                                   AS max_members,
       count(*) FILTER (WHERE c.prev_lead IS NOT NULL AND c.prev_lead <> c.lead_target_id) AS lead_changes,
       count(DISTINCT c.run)                                                          AS n_runs
FROM c
GROUP BY c.method
ORDER BY c.method;
