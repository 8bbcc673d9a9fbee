-- Per-radar residual statistics: each radar's own range innovation res_range_m (the ΔD of seed
-- fig. 4.9) and its predicted variance res_range_var_m2 — count, mean, sample SD, RMS, mean and
-- 95th percentile of |ΔD|, the mean normalised innovation squared ΔD²/S (about 1 for a consistent
-- radar tracker) and the fraction of innovations beyond 3 predicted SDs. NaN innovations (a track's
-- first report) are left out.
-- Columns: radar_id, name, n, mean_m, sd_m, rms_m, mean_abs_m, p95_abs_m, max_abs_m, nis_mean,
-- frac_beyond_3sd.
-- param: run = null   Monte-Carlo run (null: all runs)
SELECT r.radar_id,
       d.name,
       count(*)                                                         AS n,
       avg(r.res_range_m)                                               AS mean_m,
       stddev_samp(r.res_range_m)                                       AS sd_m,
       sqrt(avg(r.res_range_m * r.res_range_m))                         AS rms_m,
       avg(abs(r.res_range_m))                                          AS mean_abs_m,
       quantile_cont(abs(r.res_range_m), 0.95)                          AS p95_abs_m,
       max(abs(r.res_range_m))                                          AS max_abs_m,
       avg(r.res_range_m * r.res_range_m / r.res_range_var_m2)          AS nis_mean,
       avg(CASE WHEN abs(r.res_range_m) > 3 * sqrt(r.res_range_var_m2) THEN 1.0 ELSE 0.0 END) AS frac_beyond_3sd
FROM reports AS r
JOIN radars AS d USING (radar_id)
WHERE NOT isnan(r.res_range_m)
  AND ($run IS NULL OR r.run = $run)
GROUP BY r.radar_id, d.name
ORDER BY r.radar_id;
