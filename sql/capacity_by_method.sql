-- Capacity by method (seed fig. 5.3): the accuracy-versus-capacity rows of the metrics table — the
-- largest number of aircraft n_max with conflict probability ≤ P* under the seed model (5.21),
-- illustrative (as printed, odds-shaped), and under the sounder model; and the conflict
-- probability with a fixed number of aircraft in the zone (p_conflict_n<N>, both models) — beside
-- the measured RMSE σ each was computed from (rmse_range_m, else rmse_pos_m, segment 'all', of
-- the same stage and method). The run's parameters: safety.capacity.CAPACITY_P_STAR, _V_ZO_M3, _N.
-- Columns: method, stage, p_star, sigma_metric, sigma_m, n_max_seed, n_max_sound, n_aircraft,
-- p_conflict_seed, p_conflict_sound, n_runs.
WITH cap AS (
    SELECT method,
           max(regexp_extract(metric, '^capacity_n_([^_]+)', 1))
               FILTER (WHERE starts_with(metric, 'capacity_n_'))                    AS p_label,
           max(value) FILTER (WHERE starts_with(metric, 'capacity_n_') AND NOT ends_with(metric, '_sound'))
                                                                                   AS n_max_seed,
           max(value) FILTER (WHERE starts_with(metric, 'capacity_n_') AND ends_with(metric, '_sound'))
                                                                                   AS n_max_sound,
           max(TRY_CAST(regexp_extract(metric, '^p_conflict_n([0-9]+)', 1) AS INTEGER))
               FILTER (WHERE starts_with(metric, 'p_conflict_n'))                   AS n_aircraft,
           max(value) FILTER (WHERE starts_with(metric, 'p_conflict_n') AND NOT ends_with(metric, '_sound'))
                                                                                   AS p_conflict_seed,
           max(value) FILTER (WHERE starts_with(metric, 'p_conflict_n') AND ends_with(metric, '_sound'))
                                                                                   AS p_conflict_sound,
           max(n_runs)                                                             AS n_runs
    FROM metrics
    WHERE stage = 'safety' AND (starts_with(metric, 'capacity_n_') OR starts_with(metric, 'p_conflict_n'))
    GROUP BY method
),
sigma AS (
    SELECT stage, method, metric AS sigma_metric, value AS sigma_m,
           row_number() OVER (PARTITION BY stage, method
                              ORDER BY CASE metric WHEN 'rmse_range_m' THEN 0 ELSE 1 END) AS k
    FROM metrics
    WHERE metric IN ('rmse_range_m', 'rmse_pos_m') AND segment = 'all' AND stage <> 'safety'
      AND isfinite(value) AND value > 0
)
SELECT cap.method,
       s.stage,
       CAST(cap.p_label AS DOUBLE) AS p_star,
       s.sigma_metric,
       s.sigma_m,
       cap.n_max_seed,
       cap.n_max_sound,
       cap.n_aircraft,
       cap.p_conflict_seed,
       cap.p_conflict_sound,
       cap.n_runs
FROM cap
LEFT JOIN sigma AS s
       ON s.k = 1 AND (cap.method = s.method OR cap.method = s.stage || '/' || s.method)
ORDER BY s.stage, s.sigma_m, cap.method;
