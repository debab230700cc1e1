"""Blender at the edge: version adapters, Cycles renders of card and 3D scenes, view layers per
depth group, and the compositor node-group builder. Only these modules import ``bpy``."""
