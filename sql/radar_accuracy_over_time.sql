-- Per-radar accuracy over time (the radar curves of seed fig. 4.10): the real RMS error σ(k) of
-- each radar's own track estimates, aligned to the common epochs (table aligned), against truth at
-- the same instant, with the N − 1 denominator over the aircraft and Monte-Carlo runs scored at
-- epoch k — the same definitions as accuracy_over_time (range measured from the processing
-- centre; horizontal = east and north, height = ENU z, the height error to first order). Truth is
-- matched exactly at time = epoch (both on whole seconds); rows without a truth match and rows
-- less than $skip_first_s after the first epoch of their local track (the radar tracker's
-- transient) are not scored. Epochs with one scored row (N_k = 1) are pooled per radar as in
-- tertiary.evaluate: with M such rows, σ²(k) = e_k² · M / (M − 1); a pool of one row is left out.
-- Edge-of-coverage rule: with $min_sample_frac > 0, epochs whose n is below that fraction of the
-- radar's median n are left out.
-- Columns: radar_id, name, epoch, t_s, rmse_range_m, rmse_pos_m, rmse_horizontal_m,
-- rmse_height_m, n, n_runs, pooled.
-- param: skip_first_s = 20      transient left out at the start of each local track, s
-- param: radar_id = null        one radar (null: all)
-- param: min_sample_frac = 0    leave out epochs with n < this fraction of the radar's median n (0: keep all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
rows AS (
    SELECT run, radar_id, local_track_id, epoch, truth_id, x_m, y_m, z_m,
           min(epoch) OVER (PARTITION BY run, radar_id, local_track_id) AS first_epoch
    FROM aligned
    WHERE $radar_id IS NULL OR radar_id = $radar_id
),
scored AS (
    SELECT a.run, a.radar_id, a.epoch,
           sqrt(a.x_m * a.x_m + a.y_m * a.y_m + a.z_m * a.z_m)
             - sqrt(t.x_m * t.x_m + t.y_m * t.y_m + t.z_m * t.z_m)                    AS e_range,
           (a.x_m - t.x_m) * (a.x_m - t.x_m) + (a.y_m - t.y_m) * (a.y_m - t.y_m)      AS e2_h,
           (a.z_m - t.z_m) * (a.z_m - t.z_m)                                          AS e2_v
    FROM rows AS a
    JOIN truth AS t ON t.truth_id = a.truth_id AND t.time = a.epoch
    WHERE date_diff('microsecond', a.first_epoch, a.epoch) >= $skip_first_s * 1e6
),
per_epoch AS (
    SELECT radar_id, epoch,
           sum(e_range * e_range) AS s_range, sum(e2_h) AS s_h, sum(e2_v) AS s_v,
           count(*) AS n, count(DISTINCT run) AS n_runs
    FROM scored
    GROUP BY radar_id, epoch
),
pooled AS (
    SELECT *, n < 2 AS pooled,
           sum(CASE WHEN n < 2 THEN n ELSE 0 END) OVER (PARTITION BY radar_id) AS m,
           median(n) OVER (PARTITION BY radar_id) AS median_n
    FROM per_epoch
),
sigma AS (
    -- divisor of Σ e²: N_k − 1, or (M − 1)/M for a pooled epoch (N_k = 1)
    SELECT *, CASE WHEN pooled THEN (m - 1.0) / m ELSE n - 1.0 END AS dof
    FROM pooled
    WHERE NOT pooled OR m >= 2
)
SELECT s.radar_id,
       d.name,
       s.epoch,
       date_diff('microsecond', start.t0, s.epoch) / 1e6   AS t_s,
       sqrt(s.s_range / s.dof)                              AS rmse_range_m,
       sqrt((s.s_h + s.s_v) / s.dof)                        AS rmse_pos_m,
       sqrt(s.s_h / s.dof)                                  AS rmse_horizontal_m,
       sqrt(s.s_v / s.dof)                                  AS rmse_height_m,
       s.n,
       s.n_runs,
       s.pooled
FROM sigma AS s
JOIN radars AS d USING (radar_id)
CROSS JOIN start
WHERE s.n >= $min_sample_frac * s.median_n
ORDER BY s.radar_id, s.epoch;
