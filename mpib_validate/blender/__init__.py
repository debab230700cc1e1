"""The harness's Blender: Cycles renders of card and 3D scenes (the references with
Cycles' own depth of field) and the Blender scene suite."""
