-- Radar sites: where each radar stands (WGS-84), its scan period, nominal accuracies and
-- instrumented range, and how many reports it contributed (for the scenario map).
-- Columns: radar_id, name, lat_deg, lon_deg, alt_m, scan_period_s, sigma_range_m,
-- sigma_azimuth_deg, max_range_m, reports.
SELECT d.radar_id,
       d.name,
       d.lat_deg,
       d.lon_deg,
       d.alt_m,
       d.scan_period_s,
       d.sigma_range_m,
       d.sigma_azimuth_deg,
       d.max_range_m,
       (SELECT count(*) FROM reports AS r WHERE r.radar_id = d.radar_id) AS reports
FROM radars AS d
ORDER BY d.radar_id;
