-- Alert episodes: one row per STCA alert episode of a picture (the alerts table) — the pair of
-- picture ids and of aircraft (truth ids; null when the ids map to no two distinct aircraft),
-- first and last alert epoch, duration, alert epochs, flicker (dropouts inside the episode),
-- minimum predicted separation (horizontal R_min, vertical at the closest approach), predicted
-- time to the closest approach at the first alert, the loss of separation it warned of and the
-- warning time, and its classification (genuine, nuisance, undetermined or false); earliest first.
-- Columns: method, run, id_a, id_b, truth_a, truth_b, t_start, t_end, duration_s, alert_epochs,
-- flicker, r_min_pred_m, dz_min_pred_m, t_min_first_s, los_start, warning_s, classification.
-- param: method = null           picture (fusion method) (null: all)
-- param: classification = null   genuine, nuisance, undetermined or false (null: all)
SELECT method,
       run,
       id_a,
       id_b,
       truth_a,
       truth_b,
       t_start,
       t_end,
       duration_s,
       alert_epochs,
       flicker,
       r_min_pred_m,
       dz_min_pred_m,
       t_min_first_s,
       los_start,
       warning_s,
       classification
FROM alerts
WHERE ($method IS NULL OR method = $method)
  AND ($classification IS NULL OR classification = $classification)
ORDER BY method, run, t_start, id_a, id_b;
