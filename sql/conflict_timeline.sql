-- Conflict timeline: per picture (fusion method) and epoch, the number of aircraft pairs evaluated
-- by conflict prediction, the number in alert, the number of new alerts (pairs in alert at this
-- epoch that were not in alert at their previous evaluated epoch, or had none), and the peak and
-- mean severity of the alerts; t_s is seconds since the run start (first report, whole second);
-- Monte-Carlo runs pooled.
-- Columns: method, epoch, t_s, pairs, alerts, new_alerts, max_severity, mean_severity.
-- param: method = null   picture (fusion method) (null: all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
c AS (
    SELECT *, alert AND NOT coalesce(lag(alert) OVER (PARTITION BY run, method, id_a, id_b ORDER BY epoch), false)
                AS onset
    FROM conflicts
    WHERE $method IS NULL OR method = $method
)
SELECT c.method,
       c.epoch,
       date_diff('microsecond', start.t0, c.epoch) / 1e6   AS t_s,
       count(*)                                             AS pairs,
       count(*) FILTER (WHERE c.alert)                      AS alerts,
       count(*) FILTER (WHERE c.onset)                      AS new_alerts,
       max(c.severity) FILTER (WHERE c.alert)               AS max_severity,
       avg(c.severity) FILTER (WHERE c.alert)               AS mean_severity
FROM c, start
GROUP BY c.method, c.epoch, start.t0
ORDER BY c.method, c.epoch;
