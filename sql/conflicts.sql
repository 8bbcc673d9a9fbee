-- Conflicts with severity: every aircraft pair that raised an alert in a picture (fusion method),
-- collapsed over its alerting epochs — first and last alert epoch, number of alert epochs, closest
-- predicted horizontal approach min R_min, shortest time to it min T_min, smallest current vertical
-- separation min |Δh| and peak severity (1 − R_min / R_threshold: 1 = collision course); most
-- severe first.
-- Columns: method, run, id_a, id_b, first_epoch, last_epoch, alert_epochs, min_r_min_m,
-- min_t_min_s, min_abs_dz_m, max_severity.
-- param: method = null         picture (fusion method) (null: all)
-- param: min_severity = null   keep pairs whose peak severity is at least this (null: all)
SELECT method,
       run,
       id_a,
       id_b,
       min(epoch)       AS first_epoch,
       max(epoch)       AS last_epoch,
       count(*)         AS alert_epochs,
       min(r_min_m)     AS min_r_min_m,
       min(t_min_s)     AS min_t_min_s,
       min(abs(dz_m))   AS min_abs_dz_m,
       max(severity)    AS max_severity
FROM conflicts
WHERE alert
  AND ($method IS NULL OR method = $method)
GROUP BY method, run, id_a, id_b
HAVING $min_severity IS NULL OR max(severity) >= $min_severity
ORDER BY max_severity DESC, alert_epochs DESC, method, run, id_a, id_b;
