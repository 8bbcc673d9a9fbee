-- Per-radar report statistics: volume, local tracks, time span, false reports (no truth id,
-- simulation only) and the range-innovation consistency of each radar's own tracker
-- (innovation mean and standard deviation, and the SD of innovations normalised by their
-- predicted SD: about 1 for a consistent tracker).
-- Columns: radar_id, name, reports, local_tracks, first_time, last_time, reports_without_truth,
-- res_range_mean_m, res_range_sd_m, res_range_normalised_sd.
SELECT r.radar_id,
       d.name,
       count(*)                                                      AS reports,
       count(DISTINCT (r.run, r.local_track_id))                     AS local_tracks,
       min(r.time)                                                   AS first_time,
       max(r.time)                                                   AS last_time,
       count(*) FILTER (WHERE r.truth_id IS NULL)                    AS reports_without_truth,
       avg(r.res_range_m) FILTER (WHERE NOT isnan(r.res_range_m))    AS res_range_mean_m,
       stddev_samp(r.res_range_m) FILTER (WHERE NOT isnan(r.res_range_m)) AS res_range_sd_m,
       stddev_samp(r.res_range_m / sqrt(r.res_range_var_m2))
           FILTER (WHERE NOT isnan(r.res_range_m))                   AS res_range_normalised_sd
FROM reports AS r
JOIN radars AS d USING (radar_id)
GROUP BY r.radar_id, d.name
ORDER BY r.radar_id;
