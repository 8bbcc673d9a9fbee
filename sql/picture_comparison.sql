-- Pictures side by side (the evaluation stage, segment 'all' unless given): per picture the
-- surveillance metrics of tertiary.evaluation.picture_metrics — horizontal RMS and 95th percentile, height
-- RMS, along- and across-track RMS, latency, probability of update, ID changes per hour, false
-- and duplicate tracks per hour, split and merged tracks, Mode S correctness — so that "ours
-- against the existing system" is one table.
-- Columns: method, segment, rmse_horizontal_m, p95_horizontal_m, rmse_height_m, along_track_rms_m,
-- across_track_rms_m, latency_s, prob_update, id_changes_per_hour, false_tracks_per_hour,
-- duplicate_tracks_per_hour, split_tracks, merged_tracks, mode_s_correct_frac, n_points.
-- param: segment = null    breakdown cell, e.g. 'alt:0-3000m', 'range:0-50km', 'phase:turn' (null: 'all')
SELECT method,
       segment,
       max(value) FILTER (WHERE metric = 'rmse_horizontal_m')      AS rmse_horizontal_m,
       max(value) FILTER (WHERE metric = 'p95_horizontal_m')       AS p95_horizontal_m,
       max(value) FILTER (WHERE metric = 'rmse_height_m')          AS rmse_height_m,
       max(value) FILTER (WHERE metric = 'along_track_rms_m')      AS along_track_rms_m,
       max(value) FILTER (WHERE metric = 'across_track_rms_m')     AS across_track_rms_m,
       max(value) FILTER (WHERE metric = 'latency_s')              AS latency_s,
       max(value) FILTER (WHERE metric = 'prob_update')            AS prob_update,
       max(value) FILTER (WHERE metric = 'id_changes_per_hour')    AS id_changes_per_hour,
       max(value) FILTER (WHERE metric = 'false_tracks_per_hour')  AS false_tracks_per_hour,
       max(value) FILTER (WHERE metric = 'duplicate_tracks_per_hour') AS duplicate_tracks_per_hour,
       max(value) FILTER (WHERE metric = 'split_tracks')           AS split_tracks,
       max(value) FILTER (WHERE metric = 'merged_tracks')          AS merged_tracks,
       max(value) FILTER (WHERE metric = 'mode_s_correct_frac')    AS mode_s_correct_frac,
       max(value) FILTER (WHERE metric = 'n_points')               AS n_points
FROM metrics
WHERE stage = 'evaluation'
  AND segment = coalesce($segment, 'all')
GROUP BY method, segment
ORDER BY rmse_horizontal_m NULLS LAST, method;
