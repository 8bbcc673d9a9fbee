"""Reading what a recording carries into the data contract, the pipeline's input: datasets on disk
(:mod:`tertiary.io.dataset`), real ADS-B trajectories and their cleaning (:mod:`tertiary.io.adsb`),
and ASTERIX captures (:mod:`tertiary.io.asterix`)."""
