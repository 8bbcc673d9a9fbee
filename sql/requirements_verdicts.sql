-- Requirements with pass/fail (tertiary.evaluation.requirements): one row per requirement and picture, with
-- the measured value, the sample size, the one-sided confidence bound and the verdict (pass, fail,
-- or insufficient: the value meets the threshold but too few samples back it); failures first.
-- Columns: requirement, method, metric, breakdown, op, threshold, value, bound, n_samples, verdict.
-- param: verdict = null   'pass', 'fail' or 'insufficient' (null: all)
SELECT requirement, method, metric, breakdown, op, threshold, value, bound, n_samples, verdict
FROM requirements
WHERE $verdict IS NULL OR verdict = $verdict
ORDER BY CASE verdict WHEN 'fail' THEN 0 WHEN 'insufficient' THEN 1 ELSE 2 END, requirement, method;
