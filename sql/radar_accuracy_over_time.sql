-- Per-radar accuracy over time (the radar curves of seed fig. 4.10): the real RMS error σ(k) of
-- each radar's own track estimates, aligned to the common epochs (table aligned), against truth at
-- the same instant, with the N − 1 denominator over the aircraft and Monte-Carlo runs scored at
-- epoch k — the same definitions as accuracy_over_time (range measured from the processing
-- centre), so the curves compare directly with the tertiary estimate. Truth is matched exactly at
-- time = epoch (both on whole seconds); rows without a truth match and rows less than
-- $skip_first_s after the first epoch of their local track (the radar tracker's transient) are not
-- scored; epochs with fewer than two scored rows are left out.
-- Columns: radar_id, name, epoch, t_s, rmse_range_m, rmse_pos_m, n, n_runs.
-- param: skip_first_s = 20   transient left out at the start of each local track, s
-- param: radar_id = null     one radar (null: all)
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
           (a.x_m - t.x_m) * (a.x_m - t.x_m) + (a.y_m - t.y_m) * (a.y_m - t.y_m)
             + (a.z_m - t.z_m) * (a.z_m - t.z_m)                                      AS e2_pos
    FROM rows AS a
    JOIN truth AS t ON t.truth_id = a.truth_id AND t.time = a.epoch
    WHERE date_diff('microsecond', a.first_epoch, a.epoch) >= $skip_first_s * 1e6
)
SELECT s.radar_id,
       d.name,
       s.epoch,
       date_diff('microsecond', start.t0, s.epoch) / 1e6   AS t_s,
       sqrt(sum(s.e_range * s.e_range) / (count(*) - 1))    AS rmse_range_m,
       sqrt(sum(s.e2_pos) / (count(*) - 1))                 AS rmse_pos_m,
       count(*)                                             AS n,
       count(DISTINCT s.run)                                AS n_runs
FROM scored AS s
JOIN radars AS d USING (radar_id)
CROSS JOIN start
GROUP BY s.radar_id, d.name, s.epoch, start.t0
HAVING count(*) >= 2
ORDER BY s.radar_id, s.epoch;
