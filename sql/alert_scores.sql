-- Alert scores per picture: conflict alerts scored against the losses of separation in truth
-- (safety stage of the metrics table) — the losses (los_episodes), those alerted and missed,
-- genuine / nuisance / false alerts, those whose outcome the truth does not show (undetermined:
-- the recording, or an aircraft's trajectory, ends first), alerts per hour and the median and 5th-percentile warning
-- times; how many alerts (false, nuisance) and missed losses the picture causes (the truth picture
-- does not raise / does alert them), the missed losses under way when their aircraft were first
-- observed (no alert can precede them) and the valid alerts (followed by an avoiding manoeuvre).
-- Columns: method, los_episodes, alerted_los, missed_los, genuine_alerts, nuisance_alerts,
-- false_alerts, undetermined_alerts, alerts_per_hour, warning_median_s, warning_p05_s, alerts_picture_induced,
-- false_alerts_picture_induced, nuisance_alerts_picture_induced, missed_los_picture_induced,
-- missed_los_under_way, valid_alerts, n_runs.
-- param: method = null   picture (fusion method) (null: all)
SELECT method,
       max(value) FILTER (WHERE metric = 'los_episodes')     AS los_episodes,
       max(value) FILTER (WHERE metric = 'alerted_los')      AS alerted_los,
       max(value) FILTER (WHERE metric = 'missed_los')       AS missed_los,
       max(value) FILTER (WHERE metric = 'genuine_alerts')   AS genuine_alerts,
       max(value) FILTER (WHERE metric = 'nuisance_alerts')  AS nuisance_alerts,
       max(value) FILTER (WHERE metric = 'false_alerts')     AS false_alerts,
       max(value) FILTER (WHERE metric = 'undetermined_alerts') AS undetermined_alerts,
       max(value) FILTER (WHERE metric = 'alerts_per_hour')  AS alerts_per_hour,
       max(value) FILTER (WHERE metric = 'warning_median_s') AS warning_median_s,
       max(value) FILTER (WHERE metric = 'warning_p05_s')    AS warning_p05_s,
       max(value) FILTER (WHERE metric = 'alerts_picture_induced')          AS alerts_picture_induced,
       max(value) FILTER (WHERE metric = 'false_alerts_picture_induced')    AS false_alerts_picture_induced,
       max(value) FILTER (WHERE metric = 'nuisance_alerts_picture_induced') AS nuisance_alerts_picture_induced,
       max(value) FILTER (WHERE metric = 'missed_los_picture_induced')      AS missed_los_picture_induced,
       max(value) FILTER (WHERE metric = 'missed_los_under_way')            AS missed_los_under_way,
       max(value) FILTER (WHERE metric = 'valid_alerts')                    AS valid_alerts,
       max(n_runs)                                           AS n_runs
FROM metrics
WHERE stage = 'safety'
  AND metric IN ('los_episodes', 'alerted_los', 'missed_los', 'genuine_alerts', 'nuisance_alerts', 'false_alerts',
                 'undetermined_alerts', 'alerts_per_hour', 'warning_median_s', 'warning_p05_s', 'alerts_picture_induced',
                 'false_alerts_picture_induced', 'nuisance_alerts_picture_induced', 'missed_los_picture_induced',
                 'missed_los_under_way', 'valid_alerts')
  AND ($method IS NULL OR method = $method)
GROUP BY method
ORDER BY method;
