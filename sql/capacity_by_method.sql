-- Capacity by method (seed fig. 5.3): the accuracy-versus-capacity rows of the metrics table — the
-- largest number of aircraft n_max with conflict probability ≤ P* under the seed model (5.21) and
-- the sounder model — beside the measured RMSE σ each was computed from (rmse_range_m, else
-- rmse_pos_m, segment 'all', of the same stage and method).
-- Columns: method, stage, p_star, sigma_metric, sigma_m, n_max_seed, n_max_sound, n_runs.
WITH cap AS (
    SELECT method,
           regexp_extract(metric, '^capacity_n_([^_]+)', 1)                        AS p_label,
           max(value) FILTER (WHERE NOT ends_with(metric, '_sound'))               AS n_max_seed,
           max(value) FILTER (WHERE ends_with(metric, '_sound'))                   AS n_max_sound,
           max(n_runs)                                                             AS n_runs
    FROM metrics
    WHERE stage = 'safety' AND starts_with(metric, 'capacity_n_')
    GROUP BY method, p_label
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
       cap.n_runs
FROM cap
LEFT JOIN sigma AS s
       ON s.k = 1 AND (cap.method = s.method OR cap.method = s.stage || '/' || s.method)
ORDER BY s.stage, s.sigma_m, cap.method;
