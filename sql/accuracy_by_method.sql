-- Accuracy by method and segment: real RMS errors (N − 1 denominator, pooled over epochs) of every
-- fusion method and of every secondary tracker run on a fusion method's picture, per truth segment
-- (all, straight, turn), from the metrics table; most accurate (rmse_pos_m) first.
-- rmse_pos_m is the 3-D error; rmse_horizontal_m (east, north) and rmse_height_m (vertical) split
-- it, as surveillance specifications judge them (null where the metrics table has no such row).
-- Columns: stage, method, filter (null for fusion rows), segment, rmse_pos_m, rmse_horizontal_m,
-- rmse_height_m, rmse_range_m, rmse_x_m, rmse_y_m, rmse_z_m, rmse_vel_mps, n_runs.
-- param: stage = null      'fusion' or 'tracker' (null: both)
-- param: method = null     fusion method, e.g. 'aposteriori' (null: all)
-- param: segment = null    'all', 'straight' or 'turn' (null: all three)
SELECT stage,
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
       max(n_runs)                                         AS n_runs
FROM metrics
WHERE stage IN ('fusion', 'tracker')
  AND starts_with(metric, 'rmse_')
  AND ($stage IS NULL OR stage = $stage)
  AND ($method IS NULL OR split_part(method, '+', 1) = $method)
  AND ($segment IS NULL OR segment = $segment)
GROUP BY stage, metrics.method, segment
ORDER BY stage,
         CASE segment WHEN 'all' THEN 0 WHEN 'straight' THEN 1 WHEN 'turn' THEN 2 ELSE 3 END,
         segment, rmse_pos_m NULLS LAST, method, filter;
