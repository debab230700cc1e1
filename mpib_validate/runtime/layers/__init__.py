"""Building the MPI: RGBA layers at fixed disparities from colour + depth passes (edge
unmixing, hidden-background fill, photo refinement) or from layered (per-group) renders."""
