"""The methods mpib is compared with: Blender's Defocus node, the official MPIB renderer's
computation, and the classical baselines (RVR, SteReFo, scatter, gather)."""
