-- Accuracy over time: the real RMS error σ(k) = sqrt(Σ_j e_j(k)² / (N_k − 1)) of each fusion
-- method at every epoch k (seed figs. 4.10 and 4.11; aircraft and Monte-Carlo runs pooled), from
-- the accuracy_by_epoch table; t_s is seconds since the run start (first report, whole second).
-- n is N_k, the samples scored at the epoch; pooled marks an epoch with N_k < 2 whose σ(k) comes
-- from the pool of such epochs (tertiary.evaluate). Edge-of-coverage rule: with $min_sample_frac
-- > 0, epochs whose N_k is below that fraction of the median N_k of the same method and metric
-- are left out (thinly sampled epochs at the start and end of coverage, where σ(k) rests on a
-- handful of aircraft).
-- Columns: method, metric, epoch, t_s, value, n_runs, n, pooled.
-- param: metric = "rmse_range_m"   rmse_pos_m, rmse_horizontal_m, rmse_height_m, rmse_range_m, rmse_x_m, rmse_y_m, rmse_z_m, rmse_vel_mps (null: all)
-- param: method = null             fusion method (null: all)
-- param: min_sample_frac = 0       leave out epochs with N_k < this fraction of the median N_k (0: keep all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
sel AS (
    SELECT a.*, median(a.n) OVER (PARTITION BY a.method, a.metric) AS median_n
    FROM accuracy_by_epoch AS a
    WHERE ($metric IS NULL OR a.metric = $metric)
      AND ($method IS NULL OR a.method = $method)
)
SELECT s.method,
       s.metric,
       s.epoch,
       date_diff('microsecond', start.t0, s.epoch) / 1e6 AS t_s,
       s.value,
       s.n_runs,
       s.n,
       s.pooled
FROM sel AS s, start
WHERE s.n >= $min_sample_frac * s.median_n
ORDER BY s.method, s.metric, s.epoch;
