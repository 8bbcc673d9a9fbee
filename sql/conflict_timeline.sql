-- Conflict timeline: per picture (fusion method) and epoch, the number of aircraft pairs evaluated
-- by conflict prediction, the number in alert, and the peak and mean severity of the alerts; t_s is
-- seconds since the run start (first report, whole second); Monte-Carlo runs pooled.
-- Columns: method, epoch, t_s, pairs, alerts, max_severity, mean_severity.
-- param: method = null   picture (fusion method) (null: all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports)
SELECT c.method,
       c.epoch,
       date_diff('microsecond', start.t0, c.epoch) / 1e6   AS t_s,
       count(*)                                             AS pairs,
       count(*) FILTER (WHERE c.alert)                      AS alerts,
       max(c.severity) FILTER (WHERE c.alert)               AS max_severity,
       avg(c.severity) FILTER (WHERE c.alert)               AS mean_severity
FROM conflicts AS c, start
WHERE $method IS NULL OR c.method = $method
GROUP BY c.method, c.epoch, start.t0
ORDER BY c.method, c.epoch;
