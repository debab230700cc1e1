"""Settings of the add-on, stored on the scene (``scene.mpib``)."""

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty,
                       IntVectorProperty, PointerProperty, StringProperty)


def _preset_items():
    """The compositor's named presets (one source of truth: mpib_validate.runtime.presets)."""
    from mpib_validate.runtime.presets import PRESETS

    return tuple((name, name.title(), p.description) for name, p in PRESETS.items())


PRESET_ITEMS = _preset_items()


def _live(settings, context):
    """A changed focus distance or f-stop: refocus at once (preview, then full)."""
    from . import focus_pull

    focus_pull.on_setting_changed(settings, context)


def _layered_toggle(settings, context):
    from .layered_ops import on_layered_toggle

    on_layered_toggle(settings, context)


class MPIB_Settings(bpy.types.PropertyGroup):
    use_camera_focus: BoolProperty(
        name="Camera Focus", default=True,
        description="Focus where the scene camera focuses (distance or focus object)")
    focus_mode: EnumProperty(
        name="Focus", default="DISTANCE",
        items=(("DISTANCE", "Distance", "Focus at a distance from the camera"),
               ("PIXEL", "Pixel", "Focus on what a pixel of the image shows")))
    focus_distance: FloatProperty(name="Focus Distance", default=10.0, min=1e-4,
                                  subtype="DISTANCE", unit="LENGTH", update=_live)
    focus_pixel: IntVectorProperty(name="Focus Pixel", size=2, default=(0, 0), min=0,
                                   description="Pixel (x, y from the top left) to focus on")
    use_camera_fstop: BoolProperty(name="Camera F-Stop", default=True,
                                   description="Use the scene camera's f-stop")
    fstop: FloatProperty(name="F-Stop", default=2.8, min=0.01, soft_max=64.0,
                         description="Aperture f-number (smaller = more blur)", update=_live)
    live_focus: BoolProperty(
        name="Live Focus Pull", default=True,
        description="Changing the focus distance or f-stop refocuses the last render at once "
                    "(a quarter-resolution preview, then the full result)")
    preset: EnumProperty(name="Quality", items=PRESET_ITEMS, default="default")
    save_exr: BoolProperty(name="Save EXR", default=False,
                           description="Also save the result as EXR beside the render output")
    refocus_animation: BoolProperty(
        name="Refocus Animation", default=False,
        description="Refocus every frame of an animation render as it is written "
                    "(needs multilayer EXR output with the Depth pass)")
    layered_render: BoolProperty(
        name="Layered Render", default=False, update=_layered_toggle,
        description="Render each depth group in its own view layer (the others Indirect "
                    "Only), so the refocus gets what nearer objects hide and exact coverage "
                    "at their edges; unticking removes those view layers again")
    group_source: EnumProperty(
        name="Groups", default="AUTO",
        items=(("AUTO", "Automatic", "From the objects' bounding boxes in camera space and "
                                     "where the depth jumps in the last render"),
               ("COLLECTIONS", "Collections", "One group per collection ticked as Depth "
                                              "Group (the other objects are one more group)")))
    max_groups: IntProperty(name="Max Groups", default=3, min=2, max=8,
                            description="Largest number of automatic depth groups (each is "
                                        "one more view layer to render; on the Blender "
                                        "scene suite 5 groups refocus as well as 3)")
    last_passes: StringProperty(name="Last Passes", subtype="FILE_PATH",
                                description="EXR with the passes of the last render")
    last_message: StringProperty(name="Status", description="What the last run reported")


classes = (MPIB_Settings,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    bpy.types.Scene.mpib = PointerProperty(type=MPIB_Settings)


def unregister():
    del bpy.types.Scene.mpib
    _unregister_classes()
