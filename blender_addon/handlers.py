"""Render handlers: keep the passes of the last render; refocus animation frames."""

import atexit
import glob
import os
import tempfile

import bpy
from bpy.app.handlers import persistent


def passes_path(scene) -> str:
    """Where the last render's passes are kept (a per-scene temporary EXR)."""
    safe = "".join(ch if ch.isalnum() else "_" for ch in scene.name)
    return os.path.join(tempfile.gettempdir(), f"mpib_last_render_{os.getpid()}_{safe}.exr")


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
    try:
        if hasattr(s, "media_type"):  # Blender 5.0
            s.media_type = "MULTI_LAYER_IMAGE"
        else:  # Blender 4.2 - 4.5
            s.file_format = "OPEN_EXR_MULTILAYER"
        s.color_depth = "32"
        img.save_render(path, scene=scene)
    finally:
        if old[0] is not None:
            s.media_type = old[0]
        s.file_format = old[1]
        s.color_depth = old[2]
    return path


@persistent
def on_render_complete(scene, *_):
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


def remove_kept_passes() -> None:
    """Delete this Blender process's kept passes (they are only a cache of the last
    render; nothing else refers to them once the add-on is off or Blender quits)."""
    pattern = os.path.join(tempfile.gettempdir(), f"mpib_last_render_{os.getpid()}_*.exr")
    for path in glob.glob(pattern):
        try:
            os.remove(path)
        except OSError:
            pass


def register():
    bpy.app.handlers.render_complete.append(on_render_complete)
    bpy.app.handlers.render_write.append(on_render_write)
    atexit.register(remove_kept_passes)


def unregister():
    for lst, fn in ((bpy.app.handlers.render_complete, on_render_complete),
                    (bpy.app.handlers.render_write, on_render_write)):
        while fn in lst:
            lst.remove(fn)
    atexit.unregister(remove_kept_passes)
    remove_kept_passes()
