-- Alert scores per picture: conflict alerts scored against truth (safety stage of the metrics
-- table) — true-conflict episodes, hits, misses, false alerts, mean warning time and alert flicker.
-- Columns: method, episodes, hits, misses, false_alerts, mean_warning_s, flicker, flicker_per_hit,
-- n_runs.
-- param: method = null   picture (fusion method) (null: all)
SELECT method,
       max(value) FILTER (WHERE metric = 'episodes')         AS episodes,
       max(value) FILTER (WHERE metric = 'hits')             AS hits,
       max(value) FILTER (WHERE metric = 'misses')           AS misses,
       max(value) FILTER (WHERE metric = 'false_alerts')     AS false_alerts,
       max(value) FILTER (WHERE metric = 'mean_warning_s')   AS mean_warning_s,
       max(value) FILTER (WHERE metric = 'flicker')          AS flicker,
       max(value) FILTER (WHERE metric = 'flicker_per_hit')  AS flicker_per_hit,
       max(n_runs)                                           AS n_runs
FROM metrics
WHERE stage = 'safety'
  AND metric IN ('episodes', 'hits', 'misses', 'false_alerts', 'mean_warning_s', 'flicker', 'flicker_per_hit')
  AND ($method IS NULL OR method = $method)
GROUP BY method
ORDER BY method;
