"""Truth trajectory generators, the start of a simulation: the monograph's big box and the flight
geometry shared by the generators (:mod:`.base`), terminal-area traffic that flies procedures
(:mod:`.terminal`) and the national day (:mod:`.national`), each a schedule whose truth is looked
up window by window.
"""

from tertiary.simulate.traffic.base import (BIG_BOX_SPEED, BIG_BOX_TURN_RATE, FT, GLIDE_DEG, TCH_M, THRESHOLD,
                                            TrafficTrajectories, big_box, flight_level_m, heights_to_enu)
from tertiary.simulate.traffic.national import (NationalTraffic, aerodromes, allocate_levels, allocate_levels_compiled,
                                                conflict_offsets, final_approaches, national_flights)
from tertiary.simulate.traffic.terminal import (AIRWAYS, ARRIVAL_CLEARED_M, ARRIVALS, SID_TOP_FL, TerminalTraffic,
                                                terminal_area, terminal_traffic)

__all__ = ["BIG_BOX_SPEED", "BIG_BOX_TURN_RATE", "FT", "GLIDE_DEG", "TCH_M", "THRESHOLD", "TrafficTrajectories", "big_box",
           "flight_level_m", "heights_to_enu", "NationalTraffic", "aerodromes", "allocate_levels",
           "allocate_levels_compiled", "conflict_offsets", "final_approaches", "national_flights", "AIRWAYS",
           "ARRIVAL_CLEARED_M", "ARRIVALS", "SID_TOP_FL", "TerminalTraffic", "terminal_area", "terminal_traffic"]
