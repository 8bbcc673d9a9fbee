"""The core every other part builds on: errors, units, geodesy (WGS-84, ENU frames, radar polar
coordinates), the χ² and normal quantiles. It imports nothing else from the package."""
