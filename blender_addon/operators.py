"""Operators: refocus the last render or an EXR file; pick the focus pixel."""

import os

import bpy
from bpy.props import IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import calibrate

SUFFIX = " (refocused)"


def _errors():
    """The error types that mean bad input (reported, never a traceback)."""
    from mpib_validate.runtime.io.atomic import OutputError
    from mpib_validate.runtime.io.exr import ExrError
    from mpib_validate.runtime.layers.passes import PassError

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


def load_render_passes(path: str, view_layer=None):
    """The passes of a rendered EXR: its depth-group layers (``mpib_group_<k>``, a
    Layered Render) when it has them, else its one view layer, or ``view_layer`` (the
    artist's) when it has several."""
    from mpib_validate.runtime.io.exr import ExrError
    from mpib_validate.runtime.refocus import load_layered_passes, load_passes

    layered = load_layered_passes(path)
    if layered is not None:
        return layered
    try:
        return load_passes(path)
    except ExrError:
        if view_layer is None:
            raise
        return load_passes(path, view_layer=view_layer)


def _output_path(scene, source: str) -> str:
    """Beside the render output (or the source file), never onto an input."""
    base = bpy.path.abspath(scene.render.filepath) if scene.render.filepath else source
    folder = base if base.endswith(os.sep) or os.path.isdir(base) else os.path.dirname(base)
    stem = os.path.splitext(os.path.basename(source))[0]
    if stem.startswith("mpib_last_render_"):
        stem = "render"
    return os.path.join(folder or os.path.dirname(source), f"{stem}_refocused.exr")


def prepare(context_or_scene, path: str, name: str, frame=None, save=None) -> dict:
    """Everything the refocus needs from Blender, read on the main thread: the camera
    (:func:`calibrate.camera_request`, at ``frame``, default the current one), the
    panel's settings and where to save (``save``: a path, or ``None`` for the panel's
    choice). Raises one of :func:`_errors`, naming the setting to change."""
    from mpib_validate.runtime.io.atomic import refuse_overwrite
    from mpib_validate.runtime.io.exr import image_size
    from mpib_validate.runtime.layers.passes import PassError

    scene = getattr(context_or_scene, "scene", context_or_scene)
    settings = scene.mpib
    if not path or not os.path.exists(path):
        raise PassError(f"'{path}' does not exist")
    cam = calibrate.camera_request(scene, settings, image_size(path), frame)
    pixel = None
    if not settings.use_camera_focus and settings.focus_mode == "PIXEL":
        pixel = tuple(settings.focus_pixel)
    out = save
    if out is None and settings.save_exr:
        out = _output_path(scene, path)
    if out is not None:
        refuse_overwrite(out, [path])
    from mpib_validate.runtime.blender.layers import artist_layer

    return {"path": path, "name": name, "camera": cam["camera"], "ortho": cam["ortho"],
            "pixel": pixel,
            "fit": {"region": cam["region"], "stretch": cam["stretch"],
                    "linear_far": None if cam["ortho"] is None else cam["ortho"]["far"]},
            "view_layer": artist_layer(scene).name,
            "camera_from": calibrate.camera_sources(settings, pixel),
            "preset": settings.preset, "save": out, "warnings": []}


def frame_fit(request: dict):
    """The request's :class:`mpib_validate.runtime.session.FrameFit` (render region,
    square pixels)."""
    from mpib_validate.runtime.session import FrameFit

    fit = request.get("fit") or {}
    region = fit.get("region")
    return FrameFit(None if region is None else tuple(region), tuple(fit.get("stretch", (1, 1))),
                    fit.get("linear_far"))


def request_camera(request: dict):
    """The :class:`mpib_validate.runtime.camera.Camera` (``A``, ``d_f``) of a request: a
    perspective camera's on disparity ``1/Z``, an orthographic one's on ``far - Z``."""
    from mpib_validate.runtime.camera import blender_camera, blender_orthographic_camera

    if request.get("ortho"):
        return blender_orthographic_camera(**request["ortho"])
    return blender_camera(**request["camera"])


def compute(request: dict, progress=None):
    """The refocus itself: no Blender calls, so it may run on a worker thread.
    ``progress(fraction)`` may raise ``mpib_validate.runtime.refocus.Cancelled`` to stop; nothing
    is written then. Returns the :class:`mpib_validate.runtime.refocus.RefocusResult`."""
    from mpib_validate.runtime.layers.passes import PassError
    from mpib_validate.runtime.refocus import focus_from_pixel, refocus, write_result
    from mpib_validate.runtime.request import RefocusRequest

    report = progress if progress is not None else (lambda fraction: None)
    full = load_render_passes(request["path"], request.get("view_layer"))
    fit = frame_fit(request)
    if fit.linear_far is not None and full.groups is not None:
        raise PassError("an orthographic camera's render is refocused as one pass: untick "
                        "Layered Render and render again")
    passes = fit.passes(full)
    report(0.05)
    cam = request_camera(request)
    d_f = cam.focus_disparity
    if request["pixel"] is not None:
        try:
            x, y = fit.pixel(*request["pixel"], full.depth.shape)
        except ValueError as exc:
            raise PassError(str(exc)) from None
        d_f = focus_from_pixel(passes, x, y)
    result = refocus(RefocusRequest(passes, cam.blur_parameter, d_f, request["preset"],
                                    aperture=cam.aperture),
                     progress=lambda f: report(0.05 + 0.9 * f))
    result.image = fit.image(result.image, full.depth.shape)
    result.info["camera"] = saved_camera(cam, d_f, request)
    if not fit.identity:
        result.info["frame_fit"] = {"region": fit.region, "stretch": list(fit.stretch)}
    if request["save"]:
        write_result(request["save"], result, preview=False)
        result.info["saved"] = request["save"]
    report(1.0)
    result.info["warnings"] = request["warnings"]
    return result


def saved_camera(cam, d_f: float, request: dict) -> dict:
    """The ``camera`` member of a saved refocus's ``mpib`` header: the lens fields and
    the ``A``, ``d_f`` used, and where each came from (camera_header's schema)."""
    from dataclasses import replace

    from mpib_validate.runtime.io.camera_header import LENS_FIELDS, ResolvedCamera

    lens = None if request["camera"] is None else {k: request["camera"][k] for k in LENS_FIELDS}
    used = ResolvedCamera(replace(cam, focus_disparity=d_f), lens, request["camera_from"])
    return used.header()


class RefocusJob:
    """:func:`compute` on a worker thread, so that Blender stays responsive; numpy and
    the FFT release the GIL for most of the work. :meth:`cancel` stops it at the next
    progress step (within one layer's blur); nothing is written then."""

    def __init__(self, request: dict):
        import threading

        self.request = request
        self.fraction = 0.0
        self.result = None
        self.error = None
        self.cancelled = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mpib-refocus", daemon=True)

    def start(self) -> "RefocusJob":
        self._thread.start()
        return self

    def _progress(self, fraction: float) -> None:
        from mpib_validate.runtime.refocus import Cancelled

        if self._stop.is_set():
            raise Cancelled
        self.fraction = fraction

    def _run(self) -> None:
        from mpib_validate.runtime.refocus import Cancelled

        try:
            self.result = compute(self.request, self._progress)
        except Cancelled:
            self.cancelled = True
        except _errors() as exc:
            self.error = exc
        except Exception as exc:  # noqa: BLE001 - reported to the artist, not lost
            self.error = RuntimeError(f"unexpected {type(exc).__name__}: {exc}")

    def cancel(self) -> None:
        self._stop.set()

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout=None) -> bool:
        self._thread.join(timeout)
        return self.done


def _summary(info) -> str:
    groups = f" ({info['groups']} depth groups)" if info.get("groups", 1) > 1 else ""
    return (f"refocused{groups}: {info['planes']} planes, largest blur {info['largest_radius_px']:.1f} px, "
            f"fill {100 * info['fill_fraction']:.1f} %, {info['seconds']:.2f} s"
            + (f", saved {info['saved']}" if "saved" in info else ""))


class _RefocusBase:
    """Invoked from the interface, runs modally on a worker thread (Esc cancels, progress
    in the status bar); executed from a script or in background mode, it blocks."""

    _job = None
    _timer = None
    _interactive = False
    running = 0  # modal refocus jobs in flight (one at a time)

    @classmethod
    def poll(cls, context):
        if _RefocusBase.running:
            cls.poll_message_set("A refocus is running (Esc cancels it)")
            return False
        return context.scene is not None

    def _want_modal(self, context) -> bool:
        return self._interactive and not bpy.app.background and context.window is not None

    def run(self, context, path, name):
        settings = context.scene.mpib
        try:
            request = prepare(context, path, name)
        except _errors() as exc:
            return self._fail(settings, exc)
        if not self._want_modal(context):
            wm = context.window_manager
            wm.progress_begin(0, 100)
            try:
                result = compute(request, lambda f: wm.progress_update(int(100 * f)))
            except _errors() as exc:
                return self._fail(settings, exc)
            finally:
                wm.progress_end()
            return self._show(context, _to_image(name, result.image), result.info)
        self._job = RefocusJob(request).start()
        _RefocusBase.running += 1
        wm = context.window_manager
        wm.progress_begin(0, 100)
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        settings.last_message = "refocusing... (Esc to cancel)"
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        context.window_manager.progress_update(int(100 * job.fraction))
        if context.workspace is not None:
            context.workspace.status_text_set(
                f"MPIB refocus: {100 * job.fraction:.0f} %  (Esc to cancel)")
        if not job.done:
            return {"RUNNING_MODAL"}
        self._end(context)
        settings = context.scene.mpib
        if job.cancelled:
            settings.last_message = "cancelled; nothing was written"
            self.report({"WARNING"}, "Refocus cancelled; nothing was written")
            return {"CANCELLED"}
        if job.error is not None:
            return self._fail(settings, job.error)
        return self._show(context, _to_image(job.request["name"], job.result.image),
                          job.result.info)

    def cancel(self, context):  # Blender ends the modal (e.g. the file is closed)
        if self._job is not None:
            self._job.cancel()
            self._job.wait(5.0)
        self._end(context)

    def _end(self, context):
        if self._job is not None:
            _RefocusBase.running = max(0, _RefocusBase.running - 1)
            self._job = None
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)

    def _fail(self, settings, exc):
        settings.last_message = f"error: {exc}"
        self.report({"ERROR"}, str(exc))
        return {"CANCELLED"}

    def _show(self, context, image, info):
        settings = context.scene.mpib
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
        if not super().poll(context):
            return False
        path = context.scene.mpib.last_passes
        if not path or not os.path.exists(path):
            cls.poll_message_set("Render an image first (with the Depth pass enabled)")
            return False
        return True

    def invoke(self, context, event):
        self._interactive = True
        return self.execute(context)

    def execute(self, context):
        return self.run(context, context.scene.mpib.last_passes, "Render Result" + SUFFIX)


class MPIB_OT_refocus_file(_RefocusBase, bpy.types.Operator, ImportHelper):
    """Refocus a multilayer EXR (Combined + Depth) from disk"""

    bl_idname = "mpib.refocus_file"
    bl_label = "Refocus EXR File"
    bl_options = {"REGISTER"}
    filename_ext = ".exr"
    filter_glob: StringProperty(default="*.exr", options={"HIDDEN"})

    def invoke(self, context, event):
        self._interactive = True  # the file browser calls execute on this instance
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        name = os.path.basename(self.filepath) + SUFFIX
        return self.run(context, self.filepath, name)


def pixel_under_mouse(context, event):
    """``(x, y)`` (from the top left) of the image pixel under the mouse in an Image
    Editor's main region (found from the window coordinates, so it works wherever the
    operator was started, e.g. from the sidebar); None when the mouse is not over an
    image there."""
    def inside(region):
        return (0 <= event.mouse_x - region.x < region.width
                and 0 <= event.mouse_y - region.y < region.height)

    screen = context.screen
    for area in (screen.areas if screen is not None else ()):
        if area.type != "IMAGE_EDITOR" or area.spaces.active.image is None:
            continue
        # sidebar, header and toolbar may overlap the main region: a click there is theirs
        if any(r.type != "WINDOW" and r.width > 1 and inside(r) for r in area.regions):
            return None
        for region in area.regions:
            if region.type != "WINDOW" or not inside(region):
                continue
            u, v = region.view2d.region_to_view(event.mouse_x - region.x,
                                                event.mouse_y - region.y)
            if not (0.0 <= u < 1.0 and 0.0 <= v < 1.0):
                return None
            W, H = area.spaces.active.image.size
            return (min(int(u * W), max(W - 1, 0)), min(int((1.0 - v) * H), max(H - 1, 0)))
    return None


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
        xy = pixel_under_mouse(context, event)
        if xy is not None:
            self.x, self.y = xy
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
    if not os.path.exists(frame_path):
        r = scene.render
        why = ("Blender cannot write a multilayer EXR with non-square pixels: set Output > "
               "Format > Pixel Aspect X and Y equal" if r.pixel_aspect_x != r.pixel_aspect_y
               else "the frame was not written")
        settings.last_message = f"error: frame {scene.frame_current}: {why}"
        return
    stem = os.path.splitext(os.path.basename(frame_path))[0]
    out = os.path.join(os.path.dirname(frame_path), f"{stem}_refocused.exr")
    try:
        request = prepare(scene, frame_path, stem + SUFFIX, frame=scene.frame_current, save=out)
        info = compute(request).info
        settings.last_message = f"frame {scene.frame_current}: " + _summary(info)
    except _errors() as exc:
        settings.last_message = f"error: frame {scene.frame_current}: {exc}"


classes = (MPIB_OT_refocus_render, MPIB_OT_refocus_file, MPIB_OT_pick_focus)

register, unregister = bpy.utils.register_classes_factory(classes)
