"""Operators: refocus the last render or an EXR file; pick the focus pixel."""

import os

import bpy
from bpy.props import IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import calibrate

SUFFIX = " (refocused)"


def _errors():
    """The error types that mean bad input (reported, never a traceback)."""
    from mpib_validate.atomic import OutputError
    from mpib_validate.exr import ExrError
    from mpib_validate.passes import PassError

    return (calibrate.CalibrationError, PassError, ExrError, OutputError, ValueError, OSError)


def _to_image(name: str, rgba) -> "bpy.types.Image":
    """Show an ``(H, W, 4)`` float result as a float Image datablock (rows bottom-up)."""
    import numpy as np

    H, W = rgba.shape[:2]
    img = bpy.data.images.get(name)
    if img is not None and (tuple(img.size) != (W, H) or not img.is_float):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, W, H, alpha=True, float_buffer=True)
    img.alpha_mode = "STRAIGHT"
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
    img.update()
    return img


def _output_path(scene, source: str) -> str:
    """Beside the render output (or the source file), never onto an input."""
    base = bpy.path.abspath(scene.render.filepath) if scene.render.filepath else source
    folder = base if base.endswith(os.sep) or os.path.isdir(base) else os.path.dirname(base)
    stem = os.path.splitext(os.path.basename(source))[0]
    if stem.startswith("mpib_last_render_"):
        stem = "render"
    return os.path.join(folder or os.path.dirname(source), f"{stem}_refocused.exr")


def refocus_file(context_or_scene, path: str, name: str, frame=None):
    """Refocus the passes in ``path`` with the scene's camera and panel settings.
    Returns ``(image, info)``; raises one of :func:`_errors` on bad input."""
    from mpib_validate.atomic import refuse_overwrite
    from mpib_validate.camera import blender_camera
    from mpib_validate.passes import PassError
    from mpib_validate.refocus import focus_from_pixel, load_passes, refocus, write_result

    scene = getattr(context_or_scene, "scene", context_or_scene)
    wm = bpy.context.window_manager
    settings = scene.mpib
    if not path or not os.path.exists(path):
        raise PassError(f"'{path}' does not exist")
    wm.progress_begin(0, 3)
    try:
        passes = load_passes(path)
        wm.progress_update(1)
        H, W = passes.depth.shape
        warnings = []
        cam = blender_camera(**calibrate.camera_settings(scene, settings, W, H, warnings, frame))
        d_f = cam.focus_disparity
        if not settings.use_camera_focus and settings.focus_mode == "PIXEL":
            d_f = focus_from_pixel(passes, settings.focus_pixel[0], settings.focus_pixel[1])
        result = refocus(passes, cam.blur_parameter, d_f, settings.preset)
        wm.progress_update(2)
        image = _to_image(name, result.image)
        if settings.save_exr:
            out = _output_path(scene, path)
            refuse_overwrite(out, [path])
            write_result(out, result, preview=False)
            result.info["saved"] = out
        wm.progress_update(3)
    finally:
        wm.progress_end()
    result.info["warnings"] = warnings
    return image, result.info


def _summary(info) -> str:
    return (f"refocused: {info['planes']} planes, largest blur {info['largest_radius_px']:.1f} px, "
            f"fill {100 * info['fill_fraction']:.1f} %, {info['seconds']:.2f} s"
            + (f", saved {info['saved']}" if "saved" in info else ""))


class _RefocusBase:
    def run(self, context, path, name):
        settings = context.scene.mpib
        try:
            image, info = refocus_file(context, path, name)
        except _errors() as exc:
            settings.last_message = f"error: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        settings.last_message = _summary(info)
        for w in info.get("warnings", []):
            self.report({"WARNING"}, w)
            settings.last_message = "warning: " + w + "; " + settings.last_message
        self.report({"INFO"}, _summary(info))
        for area in (context.screen.areas if context.screen else ()):
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
        return {"FINISHED"}


class MPIB_OT_refocus_render(_RefocusBase, bpy.types.Operator):
    """Refocus the last render (its Combined and Depth passes) with layered bokeh"""

    bl_idname = "mpib.refocus_render"
    bl_label = "Refocus Last Render"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        path = context.scene.mpib.last_passes
        if not path or not os.path.exists(path):
            cls.poll_message_set("Render an image first (with the Depth pass enabled)")
            return False
        return True

    def execute(self, context):
        return self.run(context, context.scene.mpib.last_passes, "Render Result" + SUFFIX)


class MPIB_OT_refocus_file(_RefocusBase, bpy.types.Operator, ImportHelper):
    """Refocus a multilayer EXR (Combined + Depth) from disk"""

    bl_idname = "mpib.refocus_file"
    bl_label = "Refocus EXR File"
    bl_options = {"REGISTER"}
    filename_ext = ".exr"
    filter_glob: StringProperty(default="*.exr", options={"HIDDEN"})

    def execute(self, context):
        name = os.path.basename(self.filepath) + SUFFIX
        return self.run(context, self.filepath, name)


class MPIB_OT_pick_focus(bpy.types.Operator):
    """Focus on the pixel under the mouse (click in the Image Editor)"""

    bl_idname = "mpib.pick_focus"
    bl_label = "Pick Focus"
    bl_options = {"REGISTER", "UNDO"}
    x: IntProperty(name="X", min=0)
    y: IntProperty(name="Y", min=0, description="Row from the top")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def invoke(self, context, event):
        space = context.space_data
        if context.area is None or context.area.type != "IMAGE_EDITOR" or space.image is None:
            return self.execute(context)
        u, v = context.region.view2d.region_to_view(event.mouse_region_x, event.mouse_region_y)
        W, H = space.image.size
        self.x = min(max(int(u * W), 0), max(W - 1, 0))
        self.y = min(max(int((1.0 - v) * H), 0), max(H - 1, 0))
        return self.execute(context)

    def execute(self, context):
        s = context.scene.mpib
        s.use_camera_focus = False
        s.focus_mode = "PIXEL"
        s.focus_pixel = (self.x, self.y)
        s.last_message = f"focus on pixel ({self.x}, {self.y})"
        self.report({"INFO"}, s.last_message)
        return {"FINISHED"}


def refocus_frame_file(scene, frame_path: str) -> None:
    """Refocus one written animation frame into ``<frame>_refocused.exr`` (focus follows
    the camera's animated settings at the current frame)."""
    settings = scene.mpib
    if not frame_path.lower().endswith(".exr"):
        settings.last_message = ("error: Refocus Animation needs OpenEXR MultiLayer output "
                                 "with the Depth pass")
        return
    stem = os.path.splitext(os.path.basename(frame_path))[0]
    old = settings.save_exr
    try:
        settings.save_exr = False  # the sibling below is this mode's output
        image, info = refocus_file(scene, frame_path, stem + SUFFIX, frame=scene.frame_current)
        from mpib_validate.refocus import RefocusResult, write_result

        out = os.path.join(os.path.dirname(frame_path), f"{stem}_refocused.exr")
        import numpy as np

        rgba = np.array(image.pixels[:], np.float32).reshape(image.size[1], image.size[0], 4)[::-1]
        write_result(out, RefocusResult(rgba, info), preview=False)
        bpy.data.images.remove(image)
        settings.last_message = f"frame {scene.frame_current}: " + _summary(info)
    except _errors() as exc:
        settings.last_message = f"error: frame {scene.frame_current}: {exc}"
    finally:
        settings.save_exr = old


classes = (MPIB_OT_refocus_render, MPIB_OT_refocus_file, MPIB_OT_pick_focus)

register, unregister = bpy.utils.register_classes_factory(classes)
