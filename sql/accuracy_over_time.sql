-- Accuracy over time: the real RMS error σ(k) = sqrt(Σ_j e_j(k)² / (N_k − 1)) of each fusion
-- method at every epoch k (seed figs. 4.10 and 4.11; aircraft and Monte-Carlo runs pooled), from
-- the accuracy_by_epoch table; t_s is seconds since the run start (first report, whole second).
-- Columns: method, metric, epoch, t_s, value, n_runs.
-- param: metric = "rmse_range_m"   rmse_pos_m, rmse_range_m, rmse_x_m, rmse_y_m, rmse_z_m, rmse_vel_mps (null: all)
-- param: method = null             fusion method (null: all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports)
SELECT a.method,
       a.metric,
       a.epoch,
       date_diff('microsecond', start.t0, a.epoch) / 1e6 AS t_s,
       a.value,
       a.n_runs
FROM accuracy_by_epoch AS a, start
WHERE ($metric IS NULL OR a.metric = $metric)
  AND ($method IS NULL OR a.method = $method)
ORDER BY a.method, a.metric, a.epoch;
