"""Units and the state vector's column names, defined once for every stage."""

from __future__ import annotations

#: metres per foot (the international foot)
FT = 0.3048
#: standard gravity (m/s²)
G0 = 9.80665
#: microseconds per second: times are int64 µs on the absolute epoch grid
US = 1_000_000
#: the kinematic state's columns, in the order of every state vector and covariance
STATE: tuple[str, ...] = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
