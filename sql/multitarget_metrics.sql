-- The field's standard multi-target metrics per picture beside its horizontal RMSE (evaluation
-- stage, segment 'all'; tertiary.evaluation.multitarget): OSPA and GOSPA (mean over epochs; GOSPA's
-- localisation, missed and false parts in m^p), and SIAP completeness, ambiguity, spuriousness,
-- position accuracy and ID continuity (track number changes per hour, longest segment fraction).
-- Columns: method, rmse_horizontal_m, ospa_m, gospa_m, gospa_localisation, gospa_missed, gospa_false,
-- siap_completeness, siap_ambiguity, siap_spuriousness, siap_position_accuracy_m,
-- siap_track_changes_per_hour, siap_longest_segment_frac, epochs.
SELECT method,
       max(value) FILTER (WHERE metric = 'rmse_horizontal_m')           AS rmse_horizontal_m,
       max(value) FILTER (WHERE metric = 'ospa_m')                      AS ospa_m,
       max(value) FILTER (WHERE metric = 'gospa_m')                     AS gospa_m,
       max(value) FILTER (WHERE metric = 'gospa_localisation')          AS gospa_localisation,
       max(value) FILTER (WHERE metric = 'gospa_missed')                AS gospa_missed,
       max(value) FILTER (WHERE metric = 'gospa_false')                 AS gospa_false,
       max(value) FILTER (WHERE metric = 'siap_completeness')           AS siap_completeness,
       max(value) FILTER (WHERE metric = 'siap_ambiguity')              AS siap_ambiguity,
       max(value) FILTER (WHERE metric = 'siap_spuriousness')           AS siap_spuriousness,
       max(value) FILTER (WHERE metric = 'siap_position_accuracy_m')    AS siap_position_accuracy_m,
       max(value) FILTER (WHERE metric = 'siap_track_changes_per_hour') AS siap_track_changes_per_hour,
       max(value) FILTER (WHERE metric = 'siap_longest_segment_frac')   AS siap_longest_segment_frac,
       max(value) FILTER (WHERE metric = 'multitarget_epochs')          AS epochs
FROM metrics
WHERE stage = 'evaluation'
  AND segment = 'all'
GROUP BY method
HAVING max(value) FILTER (WHERE metric = 'ospa_m') IS NOT NULL
ORDER BY rmse_horizontal_m NULLS LAST, method;
