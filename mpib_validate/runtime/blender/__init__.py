"""The runtime's side of Blender: the one version-compatibility module, layered-render
view layers per depth group, and the compositor node-group builder. Only these modules
(and the harness's Cycles references) import ``bpy``."""
