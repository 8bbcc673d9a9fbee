"""Reading what a recording carries into the data contract: datasets on disk, real ADS-B
trajectories and their cleaning, and ASTERIX captures (:mod:`tertiary.io.asterix`)."""
