"""Sidebar panels in the Image Editor and the Compositor (tab "MPIB")."""

import bpy


def draw_settings(layout, context):
    s = context.scene.mpib
    col = layout.column(align=True)
    col.operator("mpib.refocus_render", icon="RENDER_RESULT")
    col.operator("mpib.refocus_file", icon="FILE_IMAGE")
    col.operator("mpib.add_refocus_node", icon="NODETREE")
    box = layout.box()
    box.label(text="Focus")
    box.prop(s, "use_camera_focus")
    sub = box.column()
    sub.enabled = not s.use_camera_focus
    sub.prop(s, "focus_mode", expand=True)
    if s.focus_mode == "DISTANCE":
        sub.prop(s, "focus_distance")
    else:
        sub.prop(s, "focus_pixel")
        sub.operator("mpib.pick_focus", icon="EYEDROPPER")
    row = box.row(align=True)
    row.operator("mpib.focus_pull", icon="RESTRICT_SELECT_OFF")
    row.prop(s, "live_focus", text="Live")
    box = layout.box()
    box.label(text="Aperture")
    box.prop(s, "use_camera_fstop")
    sub = box.column()
    sub.enabled = not s.use_camera_fstop
    sub.prop(s, "fstop")
    draw_layered(layout, context)
    layout.prop(s, "preset")
    layout.prop(s, "save_exr")
    layout.prop(s, "refocus_animation")
    if s.last_message:
        layout.label(text=s.last_message, icon="ERROR" if s.last_message.startswith("error") else "INFO")


def draw_layered(layout, context):
    s = context.scene.mpib
    box = layout.box()
    box.prop(s, "layered_render")
    if not s.layered_render:
        return
    box.prop(s, "group_source", expand=True)
    if s.group_source == "AUTO":
        box.prop(s, "max_groups")
    else:
        from mpib_validate.runtime.blender.layers import GROUP_PREFIX

        def walk(coll, depth):
            for child in coll.children:
                if not child.name.startswith(GROUP_PREFIX):
                    row = box.row()
                    row.separator(factor=depth)
                    row.prop(child, "mpib_depth_group", text=child.name)
                    walk(child, depth + 1.0)

        walk(context.scene.collection, 0.0)
    row = box.row(align=True)
    row.operator("mpib.setup_layers", icon="FILE_REFRESH")
    row.operator("mpib.remove_layers", icon="X")
    names = [vl.name for vl in context.scene.view_layers if vl.name.startswith("mpib_group_")]
    box.label(text=f"{len(names)} group view layers" if names else "single pass (no groups)")


class MPIB_PT_image(bpy.types.Panel):
    bl_label = "MPIB Refocus"
    bl_space_type = "IMAGE_EDITOR"
    bl_region_type = "UI"
    bl_category = "MPIB"

    def draw(self, context):
        draw_settings(self.layout, context)


class MPIB_PT_compositor(bpy.types.Panel):
    bl_label = "MPIB Refocus"
    bl_space_type = "NODE_EDITOR"
    bl_region_type = "UI"
    bl_category = "MPIB"

    @classmethod
    def poll(cls, context):
        return getattr(context.space_data, "tree_type", "") == "CompositorNodeTree"

    def draw(self, context):
        draw_settings(self.layout, context)


classes = (MPIB_PT_image, MPIB_PT_compositor)

register, unregister = bpy.utils.register_classes_factory(classes)
