-- Scenario trajectories (seed fig. 4.4): truth positions of every aircraft in the system frame
-- (local ENU at the processing centre, m), thinned for maps to the first sample of each aircraft in
-- every $step_s-second bin (plus its last sample so tracks end where they end).
-- Columns: truth_id, time, t_s, x_m, y_m, z_m.
-- param: step_s = 10           thinning step, s
-- param: max_aircraft = null   the aircraft with the smallest truth ids only (null: all)
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
kept AS (
    SELECT DISTINCT truth_id FROM truth ORDER BY truth_id LIMIT coalesce($max_aircraft, 9223372036854775807)
),
ranked AS (
    SELECT t.truth_id, t.time, t.x_m, t.y_m, t.z_m,
           row_number() OVER (PARTITION BY t.truth_id, floor(date_diff('microsecond', start.t0, t.time) / 1e6 / $step_s)
                              ORDER BY t.time) AS k,
           t.time = max(t.time) OVER (PARTITION BY t.truth_id) AS last
    FROM truth AS t
    JOIN kept USING (truth_id)
    CROSS JOIN start
)
SELECT truth_id,
       time,
       date_diff('microsecond', (SELECT t0 FROM start), time) / 1e6 AS t_s,
       x_m, y_m, z_m
FROM ranked
WHERE k = 1 OR last
ORDER BY truth_id, time;
