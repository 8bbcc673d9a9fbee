-- Range residuals over time per radar (seed fig. 4.9): each radar's own range innovation
-- |ΔD| = |res_range_m| pooled over aircraft and runs in time bins of $bin_s seconds (bin start t_s,
-- seconds since the run start): the mean |ΔD|, its RMS and the mean predicted innovation SD
-- sqrt(res_range_var_m2). NaN innovations (a track's first report) are left out.
-- Columns: radar_id, name, t_s, n, mean_abs_res_m, rms_res_m, pred_sd_m.
-- param: bin_s = 10     bin width, s
-- param: run = null     Monte-Carlo run (null: all runs)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
binned AS (
    SELECT r.radar_id,
           floor(date_diff('microsecond', start.t0, r.time) / 1e6 / $bin_s) * $bin_s AS t_s,
           r.res_range_m,
           r.res_range_var_m2
    FROM reports AS r, start
    WHERE NOT isnan(r.res_range_m)
      AND ($run IS NULL OR r.run = $run)
)
SELECT b.radar_id,
       d.name,
       b.t_s,
       count(*)                                       AS n,
       avg(abs(b.res_range_m))                        AS mean_abs_res_m,
       sqrt(avg(b.res_range_m * b.res_range_m))       AS rms_res_m,
       avg(sqrt(b.res_range_var_m2))                  AS pred_sd_m
FROM binned AS b
JOIN radars AS d USING (radar_id)
GROUP BY b.radar_id, d.name, b.t_s
ORDER BY b.radar_id, b.t_s;
