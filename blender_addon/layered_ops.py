"""Layered render: one view layer per depth group (``mpib_validate.runtime.blender.layers``).

Ticking "Layered Render" in the panel sets the view layers up (``mpib_group_<k>``, far
to near), unticking removes them again; the artist's own view layers and collections
are not touched (the film is transparent while the layers are set up, and given back).
Groups come automatically from the objects' bounding boxes in camera space, refined by
the Z pass of the last render where there is one (where the depth jumps), or from the
collections the artist ticks as Depth Groups. Where there is nothing to split (one
object, or all overlapping in depth) no layer is made and the report says so: the
render stays a single pass. Refocus Last Render and Refocus Animation read the group
layers of the rendered file when they are there.
"""

import os

import bpy
from bpy.props import BoolProperty

_busy = False  # the property's update and the operators call each other


def last_render_depth(scene):
    """Z pass (H, W) of the last render this session kept, or None."""
    path = getattr(scene.mpib, "last_passes", "")
    if not path or not os.path.exists(path):
        return None
    from .operators import _errors, load_render_passes

    try:
        from mpib_validate.runtime.blender.layers import artist_layer

        return load_render_passes(path, artist_layer(scene).name).depth
    except _errors():
        return None


def picked_collections(scene):
    """The collections of ``scene`` ticked as Depth Groups (depth first, our own skipped)."""
    from mpib_validate.runtime.blender.layers import GROUP_PREFIX

    out = []

    def walk(coll):
        for child in coll.children:
            if child.name.startswith(GROUP_PREFIX):
                continue
            if getattr(child, "mpib_depth_group", False):
                out.append(child)
            walk(child)

    walk(scene.collection)
    return out


def apply_layers(scene) -> list:
    """Set the group view layers up as the panel says; returns their names ([] for the
    single pass) and puts the report into ``scene.mpib.last_message``."""
    from mpib_validate.runtime.blender import layers

    s = scene.mpib
    if s.group_source == "COLLECTIONS":
        picked = picked_collections(scene)
        groups = layers.groups_from_collections(scene, picked)
        if len(groups) < 2:
            layers.remove_layers(scene)
            names = []
            report = (f"{len(picked)} collection(s) ticked as Depth Groups give {len(groups)} "
                      f"group(s) of visible objects: need two or more, single pass")
        else:
            names = layers.setup_layers(scene, groups)
            report = (f"{len(names)} depth groups from collections, far to near: "
                      + "; ".join(", ".join(o.name for o in g) for g in groups))
    else:
        names, report = layers.prepare(scene, s.max_groups, depth=last_render_depth(scene))
    s.last_message = ("layered render: " if names else "layered render: nothing to split, ") + report
    return names


def clear_layers(scene) -> int:
    from mpib_validate.runtime.blender import layers

    n = layers.remove_layers(scene)
    scene.mpib.last_message = f"layered render off: {n} group view layer(s) removed"
    return n


def on_layered_toggle(settings, context):
    """Update of ``scene.mpib.layered_render``."""
    global _busy
    if _busy:
        return
    scene = settings.id_data
    _busy = True
    try:
        if settings.layered_render:
            apply_layers(scene)
        else:
            clear_layers(scene)
    except (ValueError, RuntimeError) as exc:  # e.g. no view layer of the artist's own
        settings.last_message = f"error: {exc}"
    finally:
        _busy = False


def _set_quietly(scene, value: bool):
    global _busy
    _busy = True
    try:
        scene.mpib.layered_render = value
    finally:
        _busy = False


class _SceneOperator:
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.scene is not None


class MPIB_OT_setup_layers(_SceneOperator, bpy.types.Operator):
    """Split the scene into depth groups and set up one view layer per group (again, if
    they are there: after moving objects or rendering, the groups follow)"""

    bl_idname = "mpib.setup_layers"
    bl_label = "Update Depth Groups"

    def execute(self, context):
        scene = context.scene
        try:
            names = apply_layers(scene)
        except (ValueError, RuntimeError) as exc:
            scene.mpib.last_message = f"error: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _set_quietly(scene, True)
        self.report({"INFO"} if names else {"WARNING"}, scene.mpib.last_message)
        return {"FINISHED"}


class MPIB_OT_remove_layers(_SceneOperator, bpy.types.Operator):
    """Remove the depth-group view layers and collections (the artist's are kept)"""

    bl_idname = "mpib.remove_layers"
    bl_label = "Remove Depth Groups"

    def execute(self, context):
        scene = context.scene
        clear_layers(scene)
        _set_quietly(scene, False)
        self.report({"INFO"}, scene.mpib.last_message)
        return {"FINISHED"}


classes = (MPIB_OT_setup_layers, MPIB_OT_remove_layers)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    bpy.types.Collection.mpib_depth_group = BoolProperty(
        name="Depth Group", default=False,
        description="Render this collection's objects as their own depth group (MPIB "
                    "Layered Render, groups from collections)")


def unregister():
    del bpy.types.Collection.mpib_depth_group
    _unregister_classes()
