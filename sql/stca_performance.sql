-- STCA performance per picture, as safety people read it (safety stage of the metrics table):
-- losses of separation in the truth, how many were alerted and missed, genuine / nuisance /
-- false / undetermined (the truth ends before their outcome) alert episodes, alerts and nuisance + false alerts per hour, the warning-time
-- distribution over alerted losses (median, 5th percentile), alert duration and flicker.
-- Columns: method, los_episodes, alerted_los, missed_los, alerted_fraction, genuine_alerts,
-- nuisance_alerts, false_alerts, undetermined_alerts, alert_episodes, alerts_per_hour, nuisance_false_per_hour,
-- warning_median_s, warning_p05_s, alert_duration_median_s, flicker_per_alert, picture_hours, n_runs.
-- param: method = null   picture (fusion method) (null: all)
WITH m AS (
    SELECT method, metric, value, n_runs
    FROM metrics
    WHERE stage = 'safety' AND segment = 'all'
      AND ($method IS NULL OR method = $method)
)
SELECT method,
       max(value) FILTER (WHERE metric = 'los_episodes')             AS los_episodes,
       max(value) FILTER (WHERE metric = 'alerted_los')              AS alerted_los,
       max(value) FILTER (WHERE metric = 'missed_los')               AS missed_los,
       max(value) FILTER (WHERE metric = 'alerted_los')
         / nullif(max(value) FILTER (WHERE metric = 'los_episodes'), 0) AS alerted_fraction,
       max(value) FILTER (WHERE metric = 'genuine_alerts')           AS genuine_alerts,
       max(value) FILTER (WHERE metric = 'nuisance_alerts')          AS nuisance_alerts,
       max(value) FILTER (WHERE metric = 'false_alerts')             AS false_alerts,
       max(value) FILTER (WHERE metric = 'undetermined_alerts')      AS undetermined_alerts,
       max(value) FILTER (WHERE metric = 'alert_episodes')           AS alert_episodes,
       max(value) FILTER (WHERE metric = 'alerts_per_hour')          AS alerts_per_hour,
       max(value) FILTER (WHERE metric = 'nuisance_false_per_hour')  AS nuisance_false_per_hour,
       max(value) FILTER (WHERE metric = 'warning_median_s')         AS warning_median_s,
       max(value) FILTER (WHERE metric = 'warning_p05_s')            AS warning_p05_s,
       max(value) FILTER (WHERE metric = 'alert_duration_median_s')  AS alert_duration_median_s,
       max(value) FILTER (WHERE metric = 'flicker_per_alert')        AS flicker_per_alert,
       max(value) FILTER (WHERE metric = 'picture_hours')            AS picture_hours,
       max(n_runs)                                                   AS n_runs
FROM m
GROUP BY method
HAVING max(value) FILTER (WHERE metric = 'los_episodes') IS NOT NULL
ORDER BY method;
