-- Accuracy by method and segment: real RMS errors (N − 1 denominator, pooled over epochs) of every
-- fusion method and of every secondary tracker run on a fusion method's picture, per truth segment
-- (all, straight, turn), from the metrics table; most accurate (rmse_pos_m) first.
-- rmse_pos_m is the 3-D error; rmse_horizontal_m (east, north) and rmse_height_m (vertical) split
-- it, as surveillance specifications judge them (null where the metrics table has no such row).
-- pcrb_pos_m is the posterior Cramér–Rao bound for the same samples (stage 'bound') and gap_pos_m
-- = rmse_pos_m − pcrb_pos_m (> 0: above the bound); nees_mean and nees_in_band_frac are the
-- position NEES and the fraction of epochs inside its Monte-Carlo band (tertiary.evaluate).
-- Columns: stage, method, filter (null for fusion rows), segment, rmse_pos_m, rmse_horizontal_m,
-- rmse_height_m, rmse_range_m, rmse_x_m, rmse_y_m, rmse_z_m, rmse_vel_mps, pcrb_pos_m, gap_pos_m,
-- nees_mean, nees_in_band_frac, n_runs.
-- param: stage = null      'fusion' or 'tracker' (null: both)
-- param: method = null     fusion method, e.g. 'aposteriori' (null: all)
-- param: segment = null    'all', 'straight' or 'turn' (null: all three)
WITH bound AS (
    SELECT method, segment,
           max(value) FILTER (WHERE metric = 'pcrb_pos_m') AS pcrb_pos_m,
           max(value) FILTER (WHERE metric = 'gap_pos_m')  AS gap_pos_m
    FROM metrics
    WHERE stage = 'bound'
    GROUP BY method, segment
),
acc AS (
SELECT stage,
       metrics.method                                      AS picture,
       split_part(method, '+', 1)                          AS method,
       nullif(split_part(method, '+', 2), '')              AS filter,
       segment,
       max(value) FILTER (WHERE metric = 'rmse_pos_m')     AS rmse_pos_m,
       max(value) FILTER (WHERE metric = 'rmse_horizontal_m') AS rmse_horizontal_m,
       max(value) FILTER (WHERE metric = 'rmse_height_m')  AS rmse_height_m,
       max(value) FILTER (WHERE metric = 'rmse_range_m')   AS rmse_range_m,
       max(value) FILTER (WHERE metric = 'rmse_x_m')       AS rmse_x_m,
       max(value) FILTER (WHERE metric = 'rmse_y_m')       AS rmse_y_m,
       max(value) FILTER (WHERE metric = 'rmse_z_m')       AS rmse_z_m,
       max(value) FILTER (WHERE metric = 'rmse_vel_mps')   AS rmse_vel_mps,
       max(value) FILTER (WHERE metric = 'nees_mean')      AS nees_mean,
       max(value) FILTER (WHERE metric = 'nees_in_band_frac') AS nees_in_band_frac,
       max(n_runs)                                         AS n_runs
FROM metrics
WHERE stage IN ('fusion', 'tracker')
  AND (starts_with(metric, 'rmse_') OR metric IN ('nees_mean', 'nees_in_band_frac'))
  AND ($stage IS NULL OR stage = $stage)
  AND ($method IS NULL OR split_part(method, '+', 1) = $method)
  AND ($segment IS NULL OR segment = $segment)
GROUP BY stage, metrics.method, segment
HAVING max(value) FILTER (WHERE starts_with(metric, 'rmse_')) IS NOT NULL
)
SELECT acc.stage, acc.method, acc.filter, acc.segment, rmse_pos_m, rmse_horizontal_m, rmse_height_m,
       rmse_range_m, rmse_x_m, rmse_y_m, rmse_z_m, rmse_vel_mps, bound.pcrb_pos_m, bound.gap_pos_m,
       nees_mean, nees_in_band_frac, n_runs
FROM acc
LEFT JOIN bound ON bound.method = acc.picture AND bound.segment = acc.segment
ORDER BY acc.stage,
         CASE acc.segment WHEN 'all' THEN 0 WHEN 'straight' THEN 1 WHEN 'turn' THEN 2 ELSE 3 END,
         acc.segment, rmse_pos_m NULLS LAST, acc.method, acc.filter;
