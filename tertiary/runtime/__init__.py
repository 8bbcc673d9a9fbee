"""How a run executes: windows on the absolute epoch grid, parts written per window and resumed,
the local loop and the Dask engine, and the compiled-kernel warm-up."""
