-- Track quality of the secondary trackers (the §1.7 indicators), one row per fusion method and
-- filter, from the metrics table (segment 'all'): confirmed tracks, completeness, breaks, swaps,
-- spurious tracks, real RMS position / velocity error, potential accuracy sqrt(tr P_pos), mean NEES
-- and NIS with the fraction of epochs inside their Monte-Carlo bands; most accurate first.
-- Columns: method, filter, tracks, completeness, breaks, swaps, spurious_tracks, rmse_pos_m,
-- rmse_vel_mps, potential_pos_m, nees_mean, nis_mean, nees_in_band_frac, nis_in_band_frac, n_runs.
-- param: filter = null   tracker filter, e.g. 'singer' (null: all)
-- param: method = null   fusion method whose picture was tracked (null: all)
SELECT split_part(method, '+', 1)                              AS method,
       split_part(method, '+', 2)                              AS filter,
       max(value) FILTER (WHERE metric = 'tracks')             AS tracks,
       max(value) FILTER (WHERE metric = 'completeness')       AS completeness,
       max(value) FILTER (WHERE metric = 'breaks')             AS breaks,
       max(value) FILTER (WHERE metric = 'swaps')              AS swaps,
       max(value) FILTER (WHERE metric = 'spurious_tracks')    AS spurious_tracks,
       max(value) FILTER (WHERE metric = 'rmse_pos_m')         AS rmse_pos_m,
       max(value) FILTER (WHERE metric = 'rmse_vel_mps')       AS rmse_vel_mps,
       max(value) FILTER (WHERE metric = 'potential_pos_m')    AS potential_pos_m,
       max(value) FILTER (WHERE metric = 'nees_mean')          AS nees_mean,
       max(value) FILTER (WHERE metric = 'nis_mean')           AS nis_mean,
       max(value) FILTER (WHERE metric = 'nees_in_band_frac')  AS nees_in_band_frac,
       max(value) FILTER (WHERE metric = 'nis_in_band_frac')   AS nis_in_band_frac,
       max(n_runs)                                             AS n_runs
FROM metrics
WHERE stage = 'tracker'
  AND segment = 'all'
  AND ($filter IS NULL OR split_part(method, '+', 2) = $filter)
  AND ($method IS NULL OR split_part(method, '+', 1) = $method)
GROUP BY ALL
ORDER BY rmse_pos_m NULLS LAST, method, filter;
