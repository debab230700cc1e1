"""Rendering an MPI or a Z-buffer to depth of field: Eq. 1 with disk kernels, its backends,
and the baselines it is compared with (RVR, SteReFo, Blender's Defocus node)."""
