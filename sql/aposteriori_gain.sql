-- A-posteriori gain summary (seed fig. 4.11, reproduction target 4): for each a-posteriori method
-- and a-priori reference, the gain g(k) = 1 − σ_post(k)/σ_prior(k) — its maximum over all epochs,
-- its maximum over the manoeuvre epochs (at least half of the aircraft in truth fly a turn), its
-- time average — and the pooled gain 1 − sqrt(mean σ_post²) / sqrt(mean σ_prior²).
-- Edge-of-coverage rule: with $min_sample_frac > 0, epochs where either method's N_k is below that
-- fraction of its median N_k are left out.
-- Columns: posterior, prior, epochs, max_gain, max_gain_manoeuvre, manoeuvre_epochs, mean_gain,
-- pooled_gain.
-- param: metric = "rmse_range_m"   accuracy metric of accuracy_by_epoch
-- param: min_sample_frac = 0       leave out epochs with N_k < this fraction of the median N_k (0: keep all)
WITH e AS (
    SELECT method, epoch, value, n >= $min_sample_frac * median(n) OVER (PARTITION BY method) AS kept
    FROM accuracy_by_epoch
    WHERE metric = $metric
),
turning AS (
    SELECT time AS epoch, avg(CASE WHEN segment = 'turn' THEN 1.0 ELSE 0.0 END) >= 0.5 AS manoeuvre
    FROM truth
    GROUP BY time
),
pairs AS (
    SELECT p.method AS posterior, q.method AS prior, p.epoch, p.value AS sigma_post, q.value AS sigma_prior,
           1 - p.value / nullif(q.value, 0) AS gain
    FROM e AS p
    JOIN e AS q ON q.epoch = p.epoch
    WHERE p.method IN ('aposteriori', 'aposteriori_seed')
      AND q.method IN ('apriori', 'arithmetic')
      AND p.kept AND q.kept
)
SELECT posterior,
       prior,
       count(*)                                                 AS epochs,
       max(gain)                                                AS max_gain,
       max(gain) FILTER (WHERE coalesce(t.manoeuvre, false))    AS max_gain_manoeuvre,
       count(*) FILTER (WHERE coalesce(t.manoeuvre, false))     AS manoeuvre_epochs,
       avg(gain)                                                AS mean_gain,
       1 - sqrt(avg(sigma_post * sigma_post)) / nullif(sqrt(avg(sigma_prior * sigma_prior)), 0) AS pooled_gain
FROM pairs
LEFT JOIN turning AS t USING (epoch)
GROUP BY posterior, prior
ORDER BY posterior, prior;
