"""Render handlers: record the camera in the render's metadata; keep the passes of the
last render; refocus animation frames."""

import atexit
import glob
import os
import tempfile

import bpy
from bpy.app.handlers import persistent


def kept_dir() -> str:
    """The folder of the last render's kept passes: the extension's user directory
    (``bpy.utils.extension_path_user``: ``<user extensions>/.user/<repository>/
    mpib_refocus/last_render``), Blender's place for an extension's own files, outside
    the extension's folder, which an update replaces. Registered without being installed
    as an extension (as some tests do), the system's temporary folder."""
    try:
        return bpy.utils.extension_path_user(__package__, path="last_render")
    except ValueError:  # not an extension: registered directly
        return tempfile.gettempdir()


def passes_path(scene) -> str:
    """Where the last render's passes are kept (one EXR per scene and Blender process)."""
    safe = "".join(ch if ch.isalnum() else "_" for ch in scene.name)
    return os.path.join(kept_dir(), f"mpib_last_render_{os.getpid()}_{safe}.exr")


def save_render_passes(scene) -> str:
    """Save the Render Result as a float multilayer EXR (every pass), headless-safe:
    Render Result pixels cannot be read directly, the EXR can. The scene's own output
    settings are restored afterwards."""
    img = bpy.data.images.get("Render Result")
    if img is None:
        return ""
    s = scene.render.image_settings
    old = (getattr(s, "media_type", None), s.file_format, s.color_depth)
    path = passes_path(scene)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    try:
        from mpib_validate.runtime.blender.compat import save_render, set_multilayer_exr

        set_multilayer_exr(s, color_depth="32")  # media_type on 5.x, file_format on 4.x
        save_render(img, path, scene)  # also with non-square pixels
    finally:
        if old[0] is not None:
            s.media_type = old[0]
        s.file_format = old[1]
        s.color_depth = old[2]
    return path


_notes = {}  # scene name -> (use_stamp_note, stamp_note_text) before the render


def stamp_camera(scene) -> str:
    """Put the scene camera (``mpib_validate.runtime.io.camera_header`` schema) into the render's
    stamp note, which Blender writes into the header (``Note``) of every EXR it saves of
    this render, so that ``mpib refocus`` needs no lens options. The artist's note is
    kept in front of it and the settings are restored after the render
    (:func:`restore_note`). Returns what was not done and why ("" when done)."""
    from mpib_validate.runtime.blender.camera import CameraError, read_camera
    from mpib_validate.runtime.io.camera_header import stamp_note

    r = scene.render
    if r.use_stamp:  # Burn Into Image would draw the note into the pixels
        return ("the camera is not recorded in the render's metadata while Burn Into Image "
                "is on (Output > Metadata)")
    try:  # the frame being rendered (an animation render leaves the scene at its first)
        cam = read_camera(scene, frame=scene.frame_current)
    except CameraError as exc:
        return f"the camera is not recorded in the render's metadata: {exc}"
    # the header's camera (read by `mpib refocus`) is a perspective camera on the whole
    # frame with square pixels: where the render is not that, it is not written
    why = None
    if cam.type != "PERSP":
        why = f"the camera '{cam.name}' is not a perspective camera"
    elif cam.pixel_aspect != 1.0:
        why = "the pixels are not square (Output > Format > Pixel Aspect)"
    elif cam.region is not None and not cam.region.crop:
        why = "the render region is not cropped (Output > Format > Crop to Render Region)"
    if why:
        return f"the camera is not recorded in the render's metadata: {why}"
    lens = cam.lens()
    own = r.stamp_note_text if r.use_stamp_note else ""
    try:
        text = stamp_note(lens, own)
    except ValueError as exc:  # e.g. a focus at depth 0
        return f"the camera is not recorded in the render's metadata: {exc}"
    if text is None:
        return ("the camera is not recorded in the render's metadata: the Metadata note is "
                "too long (Blender keeps 511 bytes)")
    _notes.setdefault(scene.name, (r.use_stamp_note, r.stamp_note_text))
    r.use_stamp_note = True
    r.stamp_note_text = text
    return ""


def restore_note(scene) -> None:
    """Give the artist back the stamp note settings :func:`stamp_camera` changed."""
    saved = _notes.pop(scene.name, None)
    if saved is not None:
        scene.render.use_stamp_note, scene.render.stamp_note_text = saved


@persistent
def on_render_pre(scene, *_):
    problem = stamp_camera(scene)
    if problem:
        scene.mpib.last_message = "note: " + problem


@persistent
def on_render_post(scene, *_):
    restore_note(scene)  # the render result keeps its stamp; the scene gets its note back


@persistent
def on_render_complete(scene, *_):
    from .focus_pull import drop_session

    drop_session()  # the kept MPI belongs to the previous render
    try:
        scene.mpib.last_passes = save_render_passes(scene)
    except (RuntimeError, OSError) as exc:
        scene.mpib.last_message = f"could not keep the render passes: {exc}"


@persistent
def on_render_write(scene, *_):
    """After each written frame of an animation: refocus it into a sibling file."""
    if not scene.mpib.refocus_animation:
        return
    from .operators import refocus_frame_file

    refocus_frame_file(scene, scene.render.frame_path(frame=scene.frame_current))


_kept = {"dir": None}  # kept_dir() at registration (bpy may be gone at exit)


def remove_kept_passes() -> None:
    """Delete this Blender process's kept passes (they are only a cache of the last
    render; nothing else refers to them once the add-on is off or Blender quits)."""
    folder = _kept["dir"] or kept_dir()
    pattern = os.path.join(folder, f"mpib_last_render_{os.getpid()}_*.exr")
    for path in glob.glob(pattern):
        try:
            os.remove(path)
        except OSError:
            pass


def _handlers():
    h = bpy.app.handlers
    return ((h.render_pre, on_render_pre), (h.render_post, on_render_post),
            (h.render_cancel, on_render_post), (h.render_complete, on_render_complete),
            (h.render_write, on_render_write))


def register():
    for lst, fn in _handlers():
        lst.append(fn)
    _kept["dir"] = kept_dir()
    atexit.register(remove_kept_passes)


def unregister():
    for lst, fn in _handlers():
        while fn in lst:
            lst.remove(fn)
    for name in list(_notes):
        scene = bpy.data.scenes.get(name)
        if scene is not None:
            restore_note(scene)
        _notes.pop(name, None)
    atexit.unregister(remove_kept_passes)
    remove_kept_passes()
