"""Building the MPI: RGBA layers at fixed disparities, from exact cards, from colour + depth
passes (edge unmixing, hidden-background fill) or from layered (per-group) renders."""
