"""Focus pull: click a pixel or drag the focus distance, see a quarter-resolution preview
at once, then the full-resolution result.

The last render's passes are refocused through one
:class:`mpib_validate.runtime.session.RefocusSession`, kept here: its MPI is built on the first
pull and reused by every later one (a new focus only re-composites; see
``mpib_validate.runtime.session`` for what an f-stop change reuses). A new render drops it
(:func:`drop_session`, called by the render handler), and so does any change to the
passes file or the preset. Interactively the work runs on a worker thread (a newer pull
cancels an older one) and a timer shows each stage as it is ready; from a script or in
background mode both stages run before the call returns.
"""

import threading

import bpy

from . import operators

NAME = "Render Result" + operators.SUFFIX
PREVIEW_SCALE = 0.25


class State:
    """What the add-on keeps between pulls (module-level: one Blender process)."""

    session = None  # mpib_validate.runtime.session.RefocusSession of the last render's passes
    key = None  # (passes path, preset) the session was made for
    job = None  # the FocusPullJob in flight (interactive)
    last_preview_shape = None  # (H, W) of the last preview rendered
    last_full_info = None  # info of the last full-resolution result shown
    timer = None


def drop_session() -> None:
    """Forget the kept MPI (a new render arrived, or the add-on is disabled)."""
    if State.job is not None:
        State.job.cancel()
    State.job = None
    State.session = None
    State.key = None


def session_for(path: str, preset: str, fit=None):
    """The kept session if it was made from ``path`` (unchanged on disk) with ``preset``
    and ``fit`` (a :class:`mpib_validate.runtime.session.FrameFit`: render region, square
    pixels); else a new one (the old one and its MPI are dropped first)."""
    from mpib_validate.runtime.refocus import load_passes
    from mpib_validate.runtime.session import RefocusSession, file_stamps

    s = State.session
    key = (path, preset, fit)
    if s is not None and State.key == key and s.is_current():
        return s
    drop_session()
    if fit is None or fit.identity:
        State.session = RefocusSession.from_files(path, preset=preset)
    else:
        State.session = RefocusSession(fit.passes(load_passes(path)), preset=preset,
                                       stamps=file_stamps([path]))
    State.key = key
    return State.session


def upsample(preview, H: int, W: int):
    """Nearest-neighbour enlargement of a ``1/s`` preview to ``H x W`` for display."""
    import numpy as np

    s = int(round(1.0 / PREVIEW_SCALE))
    return np.repeat(np.repeat(preview, s, axis=0), s, axis=1)[:H, :W]


class FocusPullJob:
    """Preview, then full resolution, of one focus and aperture; :meth:`cancel` stops it
    at the next progress step. Run on a thread (:meth:`start`) or in place (:meth:`run`)."""

    def __init__(self, session, d_f: float, A: float, aperture=None):
        self.session, self.d_f, self.A, self.aperture = session, d_f, A, aperture
        self.preview = None
        self.preview_shown = False
        self.full = None
        self.error = None
        self.cancelled = False
        self._stop = threading.Event()
        self._thread = None

    def _progress(self, fraction):
        from mpib_validate.runtime.refocus import Cancelled

        if self._stop.is_set():
            raise Cancelled

    def run(self) -> "FocusPullJob":
        from mpib_validate.runtime.refocus import Cancelled

        try:
            # the MPI is built for the aperture's reach (A, or A / ratio for a ratio < 1)
            build_A = self.session.request(self.d_f, self.A, self.aperture).build_blur_parameter
            if not self.session.serves(build_A):
                # first pull after a render: a preview from subsampled passes while the
                # MPI is built (1/16 of its cost); the build itself is not cancelled, or
                # a slider dragged meanwhile would never let it finish
                self.preview = self.session.quick_preview(self.d_f, self.A, PREVIEW_SCALE,
                                                          self._progress, self.aperture)
                self.session.mpi_for(build_A)
                self._progress(0.0)
            else:
                self.preview = self.session.render(self.d_f, self.A, PREVIEW_SCALE,
                                                   self._progress, self.aperture)
            self.full = self.session.render(self.d_f, self.A, 1.0, self._progress,
                                            self.aperture)
        except Cancelled:
            self.cancelled = True
        except operators._errors() as exc:
            self.error = exc
        except Exception as exc:  # noqa: BLE001 - reported to the artist, not lost
            self.error = RuntimeError(f"unexpected {type(exc).__name__}: {exc}")
        return self

    def start(self) -> "FocusPullJob":
        self._thread = threading.Thread(target=self.run, name="mpib-focus-pull", daemon=True)
        self._thread.start()
        return self

    def cancel(self) -> None:
        self._stop.set()

    @property
    def done(self) -> bool:
        return self._thread is None or not self._thread.is_alive()


def _show(scene, rgba, H, W):
    image = operators._to_image(NAME, rgba)
    for window in getattr(bpy.context.window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
                area.tag_redraw()
    return image


def _present(scene, job, H, W, back=None) -> bool:
    """Show what ``job`` has made so far (the preview once, then the full result); True
    when nothing more will come. ``back``: maps an ``H x W`` result onto the render's
    pixels (render region, square pixels)."""
    back = back or (lambda img: img)
    settings = scene.mpib
    if job.error is not None:
        settings.last_message = f"error: {job.error}"
        return True
    if job.cancelled:
        return True
    if job.full is not None:
        _show(scene, back(job.full.image), H, W)
        State.last_full_info = i = job.full.info
        settings.last_message = (f"focus pull: d_f = {i['focus_disparity']:.4g}, "
                                 f"{i['composite_seconds']:.2f} s ({i['mpi']} MPI, "
                                 f"{i['cache_bytes'] / 1e6:.0f} MB kept)")
        return True
    if job.preview is not None and not job.preview_shown:
        job.preview_shown = True
        State.last_preview_shape = job.preview.image.shape[:2]
        _show(scene, back(upsample(job.preview.image, H, W)), H, W)
        settings.last_message = (f"focus pull: preview {job.preview.image.shape[1]}x"
                                 f"{job.preview.image.shape[0]}, full resolution next...")
    return False


def pull(scene, blocking: bool | None = None) -> bool:
    """Refocus the last render at the panel's focus (pixel or distance) and f-stop:
    preview first, then full resolution. ``blocking=None``: block in background mode
    only. Returns False (with the reason in the panel's status) when it cannot run."""
    from mpib_validate.runtime.io.exr import image_size

    settings = scene.mpib
    try:
        request = operators.prepare(scene, settings.last_passes, NAME, save=None)
        fit = operators.frame_fit(request)
        session = session_for(request["path"], request["preset"], fit)
        cam = operators.request_camera(request)
        d_f = cam.focus_disparity
        shape = tuple(image_size(request["path"]))[::-1]
        if request["pixel"] is not None:
            d_f = session.focus_at_pixel(*fit.pixel(*request["pixel"], shape))
    except operators._errors() as exc:
        settings.last_message = f"error: {exc}"
        return False
    H, W = session.passes.depth.shape

    def back(img):
        return fit.image(img, shape)
    if State.job is not None:
        State.job.cancel()
    job = FocusPullJob(session, d_f, cam.blur_parameter, cam.aperture)
    if blocking is None:
        blocking = bpy.app.background
    if blocking:
        State.job = None
        full, job.full = job.run().full, None
        _present(scene, job, H, W, back)  # the preview, as the timer would show it first
        job.full = full
        _present(scene, job, H, W, back)
        return job.error is None
    State.job = job.start()
    scene_name = scene.name

    def poll():
        sc = bpy.data.scenes.get(scene_name)
        if State.job is not job or sc is None:
            return None  # superseded, or the scene is gone
        if _present(sc, job, H, W, back):  # the full result (or an error) is shown: done
            State.job = None
            return None
        return 0.03

    bpy.app.timers.register(poll, first_interval=0.01)
    settings.last_message = "focus pull: rendering the preview..."
    return True


def on_setting_changed(settings, context) -> None:
    """Update callback of the focus distance and f-stop: a live focus pull."""
    if not settings.live_focus or not settings.last_passes:
        return
    scene = settings.id_data  # the scene these settings belong to
    if isinstance(scene, bpy.types.Scene):
        pull(scene)


class MPIB_OT_focus_pull(bpy.types.Operator):
    """Click in the Image Editor to focus on that pixel: a preview at once, then the full
    result (right-click or Esc ends)"""

    bl_idname = "mpib.focus_pull"
    bl_label = "Focus Pull"
    bl_options = {"REGISTER"}
    x: bpy.props.IntProperty(name="X", min=0)
    y: bpy.props.IntProperty(name="Y", min=0, description="Row from the top")

    @classmethod
    def poll(cls, context):
        import os

        path = context.scene.mpib.last_passes if context.scene else ""
        if not path or not os.path.exists(path):
            cls.poll_message_set("Render an image first (with the Depth pass enabled)")
            return False
        return True

    def invoke(self, context, event):
        if context.area is None or context.area.type != "IMAGE_EDITOR":
            return self.execute(context)
        context.window_manager.modal_handler_add(self)
        if context.workspace is not None:
            context.workspace.status_text_set("Focus pull: click to focus, right-click or "
                                              "Esc to end")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type in {"RIGHTMOUSE", "ESC"} and event.value == "PRESS":
            if context.workspace is not None:
                context.workspace.status_text_set(None)
            return {"FINISHED"}
        if event.type == "LEFTMOUSE" and event.value == "PRESS":
            xy = operators.pixel_under_mouse(context, event)
            if xy is None:
                return {"PASS_THROUGH"}
            self.x, self.y = xy
            self._pull(context, blocking=False)
            return {"RUNNING_MODAL"}
        return {"PASS_THROUGH"}

    def execute(self, context):
        return self._pull(context, blocking=None)

    def _pull(self, context, blocking):
        s = context.scene.mpib
        s.use_camera_focus = False
        s.focus_mode = "PIXEL"
        s.focus_pixel = (self.x, self.y)
        if not pull(context.scene, blocking):
            self.report({"ERROR"}, s.last_message.removeprefix("error: "))
            return {"CANCELLED"}
        return {"FINISHED"}


classes = (MPIB_OT_focus_pull,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()


def unregister():
    drop_session()
    _unregister_classes()
