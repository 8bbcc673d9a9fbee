"""Association of aligned local tracks to system targets: gating, then the Hungarian assignment
carried across windows."""
