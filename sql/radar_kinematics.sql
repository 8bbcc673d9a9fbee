-- Range, range rate and line-of-sight acceleration per radar over time (seed figs. 4.5–4.7): each
-- radar's own track estimates of range D (est_range_m) and range rate V (est_range_rate_mps) in one
-- Monte-Carlo run, for the $max_aircraft aircraft seen by the most radars (then with the most
-- reports; ties: smallest truth_id), and the acceleration a = ΔV/Δt between consecutive reports of
-- the same local track (null for a track's first two reports: its first range rate is not yet
-- estimated).
-- Columns: radar_id, name, truth_id, local_track_id, time, t_s, est_range_m, est_range_rate_mps,
-- accel_mps2.
-- param: run = null          Monte-Carlo run (null: the first run)
-- param: max_aircraft = 3    number of aircraft
WITH start AS (SELECT date_trunc('second', min(time)) AS t0 FROM reports),
chosen_run AS (SELECT coalesce($run, min(run)) AS run FROM reports),
picked AS (
    SELECT r.truth_id
    FROM reports AS r JOIN chosen_run USING (run)
    WHERE r.truth_id IS NOT NULL
    GROUP BY r.truth_id
    ORDER BY count(DISTINCT r.radar_id) DESC, count(*) DESC, r.truth_id
    LIMIT $max_aircraft
)
SELECT r.radar_id,
       d.name,
       r.truth_id,
       r.local_track_id,
       r.time,
       date_diff('microsecond', start.t0, r.time) / 1e6 AS t_s,
       r.est_range_m,
       r.est_range_rate_mps,
       CASE WHEN row_number() OVER w > 2 THEN
           (r.est_range_rate_mps - lag(r.est_range_rate_mps) OVER w)
             / (date_diff('microsecond', lag(r.time) OVER w, r.time) / 1e6) END AS accel_mps2
FROM reports AS r
JOIN chosen_run USING (run)
JOIN picked USING (truth_id)
JOIN radars AS d USING (radar_id)
CROSS JOIN start
WINDOW w AS (PARTITION BY r.run, r.radar_id, r.local_track_id ORDER BY r.time)
ORDER BY r.truth_id, r.radar_id, r.time;
