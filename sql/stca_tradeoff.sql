-- STCA trade-off curves per picture (safety_tradeoff stage of the metrics table): for each
-- threshold family (covariance thresholds by confidence, fixed thresholds by their estimation
-- term), look-ahead and warning requirement, the fraction of losses of separation alerted with
-- at least that warning against the nuisance + false alerts per hour; one row per curve point,
-- ordered along each curve by the alert rate.
-- Columns: method, threshold_mode, parameter, t_thr_s, warning_s, nuisance_false_per_hour,
-- alerted_fraction.
-- param: method = null       picture (fusion method) (null: all)
-- param: warning_s = null    required warning time in seconds (null: every value computed)
WITH p AS (
    SELECT method,
           regexp_extract(segment, 'mode=([a-z]+)', 1)                      AS threshold_mode,
           CAST(regexp_extract(segment, ';p=([^;]+)', 1) AS DOUBLE)          AS parameter,
           CAST(regexp_extract(segment, ';T=([^;]+)', 1) AS DOUBLE)          AS t_thr_s,
           CAST(regexp_extract(segment, ';X=([^;]+)', 1) AS DOUBLE)          AS warning_s,
           metric,
           value
    FROM metrics
    WHERE stage = 'safety_tradeoff'
      AND ($method IS NULL OR method = $method)
)
SELECT method,
       threshold_mode,
       parameter,
       t_thr_s,
       warning_s,
       max(value) FILTER (WHERE metric = 'nuisance_false_per_hour') AS nuisance_false_per_hour,
       max(value) FILTER (WHERE metric = 'alerted_fraction')        AS alerted_fraction
FROM p
WHERE ($warning_s IS NULL OR warning_s = $warning_s)
GROUP BY method, threshold_mode, parameter, t_thr_s, warning_s
ORDER BY method, t_thr_s, warning_s, threshold_mode, nuisance_false_per_hour, parameter;
