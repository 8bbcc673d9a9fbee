-- A-posteriori versus a-priori weights over time (seed fig. 4.11): at every epoch the real RMS
-- error σ(k) of each a-posteriori method (aposteriori = corrected recursion, aposteriori_seed = as
-- printed (4.86)) beside each a-priori reference (apriori = nominal-variance weights (4.87),
-- arithmetic = equal weights 1/N), and the gain 1 − σ_post(k)/σ_prior(k) (> 0: the a-posteriori
-- weights are better at that epoch), from accuracy_by_epoch. Edge-of-coverage rule: with
-- $min_sample_frac > 0, epochs where either method's N_k is below that fraction of its median N_k
-- are left out.
-- Columns: posterior, prior, epoch, t_s, sigma_post, sigma_prior, gain.
-- param: metric = "rmse_range_m"   accuracy metric of accuracy_by_epoch
-- param: min_sample_frac = 0       leave out epochs with N_k < this fraction of the median N_k (0: keep all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
e AS (
    SELECT method, epoch, value, n >= $min_sample_frac * median(n) OVER (PARTITION BY method) AS kept
    FROM accuracy_by_epoch
    WHERE metric = $metric
)
SELECT p.method                                          AS posterior,
       q.method                                          AS prior,
       p.epoch,
       date_diff('microsecond', start.t0, p.epoch) / 1e6 AS t_s,
       p.value                                           AS sigma_post,
       q.value                                           AS sigma_prior,
       1 - p.value / nullif(q.value, 0)                  AS gain
FROM e AS p
JOIN e AS q ON q.epoch = p.epoch
CROSS JOIN start
WHERE p.method IN ('aposteriori', 'aposteriori_seed')
  AND q.method IN ('apriori', 'arithmetic')
  AND p.kept AND q.kept
ORDER BY posterior, prior, p.epoch;
