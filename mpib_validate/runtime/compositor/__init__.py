"""Rendering an MPI to depth of field: Eq. 1 with the aperture's kernels, the sub-aperture
middle setting, and their compute backends (numpy / SciPy FFTs, Dr.Jit)."""
