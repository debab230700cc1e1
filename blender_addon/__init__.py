"""MPIB Refocus: refocus rendered passes (Combined + Depth) with the MPI compositor.

The algorithms live in the project's ``mpib_validate`` package, bundled as a wheel (see
``blender_manifest.toml``); this add-on only adapts Blender to it: it keeps the passes of
the last render, calibrates focus and aperture from the scene camera, runs
``mpib_validate.runtime.refocus`` and shows the result as a float image.
"""

from . import focus_pull, handlers, layered_ops, nodegroup_ops, operators, properties, ui

_modules = (properties, operators, focus_pull, layered_ops, nodegroup_ops, ui, handlers)


def register():
    for m in _modules:
        m.register()


def unregister():
    for m in reversed(_modules):
        m.unregister()
