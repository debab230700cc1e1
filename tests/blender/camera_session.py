"""Runs inside a fresh Python with the bpy module (started by tests/test_camera_header.py).

Registers the extension from this checkout (its render handlers and operators, the code
the zip carries), renders tiny Cycles scenes to multilayer EXR as Blender writes them,
refocuses them with the extension's operator, and prints one JSON line of findings.
Usage: python camera_session.py WORKDIR
"""

import json
import os
import sys

import bpy
import numpy as np

work = sys.argv[1]
out = {"version": bpy.app.version_string}

import blender_addon  # noqa: E402  (this checkout, on PYTHONPATH)

blender_addon.register()

from mpib_validate.runtime.io.camera_header import read_camera  # noqa: E402
from mpib_validate.runtime.io.exr import read_exr  # noqa: E402
from scene_parts import black_world, cycles_cpu, emitter  # noqa: E402  (this folder: the script's own)


def clean_scene(w, h, spp=1):
    for coll in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.cameras,
                 bpy.data.worlds):
        for item in list(coll):
            coll.remove(item)
    sc = bpy.context.scene
    cycles_cpu(sc, spp, w, h)
    sc.render.film_transparent = False
    sc.render.use_stamp = False
    sc.render.use_stamp_note = False
    sc.render.stamp_note_text = ""
    sc.unit_settings.scale_length = 1.0
    s = sc.render.image_settings
    if hasattr(s, "media_type"):  # Blender 5.0
        s.media_type = "MULTI_LAYER_IMAGE"
    else:
        s.file_format = "OPEN_EXR_MULTILAYER"
    s.color_depth = "32"
    black_world(sc)
    cam_data = bpy.data.cameras.new("cam")
    cam_data.lens, cam_data.sensor_width, cam_data.sensor_height = 50.0, 36.0, 24.0
    cam_data.dof.use_dof = False  # sharp passes; the DOF settings hold the lens
    cam_data.dof.aperture_fstop = 1.0
    cam = bpy.data.objects.new("cam", cam_data)
    sc.collection.objects.link(cam)
    sc.camera = cam
    sc.mpib.last_message = ""
    return sc


def render_still(sc, path):
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
    return path


def header_camera(path):
    cam = read_camera(read_exr(path).header, path)
    return None if cam is None else {"source": cam.source, "blender": cam.blender}


# -- a portrait frame, 27x48 (1080x1920 / 40), each sensor fit ------------------------------
# a checker wall at 4 m and a card at 0.6 m; the focus object (an empty) sits at planar
# depth 3 m, off the axis (its distance is 3.04 m)
fits = {}
for fit in ("AUTO", "HORIZONTAL", "VERTICAL"):
    sc = clean_scene(27, 48, spp=4)
    sc.camera.data.sensor_fit = fit
    focus = bpy.data.objects.new("focus", None)
    focus.location = (0.4, 0.3, -3.0)
    sc.collection.objects.link(focus)
    sc.camera.data.dof.focus_object = focus
    emitter("wall", 8.0, (0, 0, -4.0), (0.2, 0.8, 0.3), checker=8.0)
    emitter("card", 0.12, (0.02, 0.05, -0.6), (1.0, 0.3, 0.1))
    bpy.context.view_layer.update()
    P = sc.camera.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=27, y=48)
    path = render_still(sc, os.path.join(work, f"portrait_{fit}.exr"))
    kept = sc.mpib.last_passes
    sc.mpib.save_exr = True
    r = bpy.ops.mpib.refocus_file(filepath=path)
    saved = os.path.join(work, f"portrait_{fit}_refocused.exr")
    fits[fit] = {
        # Blender's own projection: P[0][0] = 2 f_px / W, P[1][1] = 2 f_px / H
        "f_px_blender": [P[0][0] * 27 / 2, P[1][1] * 48 / 2],
        "operator": sorted(r), "message": sc.mpib.last_message,
        "render": path, "saved": saved if os.path.exists(saved) else None,
        "header": header_camera(path), "kept_passes_header": header_camera(kept),
        "saved_mpib": json.loads(read_exr(saved).header["mpib"]) if os.path.exists(saved) else None,
    }
    sc.mpib.save_exr = False
out["fits"] = fits

# -- Cycles' own blur of a small emitter in that portrait frame (AUTO fit, depth of field on):
# a 2 cm square at planar depth 0.5 m, focus at 10 m, f/1 ------------------------------------
sc = clean_scene(27, 48, spp=1024)
sc.camera.data.dof.use_dof = True
sc.camera.data.dof.focus_distance = 10.0
emitter("dot", 0.02, (0, 0, -0.5), (1, 1, 1))
out["dot"] = render_still(sc, os.path.join(work, "portrait_dot_dof.exr"))

# -- an animation with keyed focus, and the artist's own note kept -------------------------
sc = clean_scene(8, 6)
emitter("wall", 8.0, (0, 0, -4.0), (0.5, 0.5, 0.5))
cam = sc.camera.data
cam.dof.focus_distance = 6.0
cam.dof.keyframe_insert("focus_distance", frame=1)
cam.dof.focus_distance = 1.5
cam.dof.keyframe_insert("focus_distance", frame=2)
sc.frame_start, sc.frame_end = 1, 2
sc.frame_set(1)
sc.render.use_stamp_note = True
sc.render.stamp_note_text = "shot 12"
sc.render.filepath = os.path.join(work, "anim", "frame_")
bpy.ops.render.render(animation=True)
out["animation"] = {}
for f in (1, 2):
    p = sc.render.frame_path(frame=f)
    out["animation"][f] = {"note": read_exr(p).header.get("Note", ""), "camera": header_camera(p)}
out["note_after_animation"] = [sc.render.use_stamp_note, sc.render.stamp_note_text]

# -- Burn Into Image on: the note would be drawn into the pixels, so none is added ------------
sc = clean_scene(8, 6)
emitter("wall", 8.0, (0, 0, -4.0), (0.5, 0.5, 0.5))
sc.render.use_stamp = True
p = render_still(sc, os.path.join(work, "burn.exr"))
out["burn_in"] = {"camera": header_camera(p), "message": sc.mpib.last_message,
                  "note_after": [sc.render.use_stamp_note, sc.render.stamp_note_text]}
sc.render.use_stamp = False

# -- the scene's Unit Scale does not change Cycles' depth of field ---------------------------
unit = {}
for scale in (1.0, 0.1):
    sc = clean_scene(32, 32, spp=16)
    sc.render.film_transparent = True
    sc.unit_settings.scale_length = scale
    sc.camera.data.dof.use_dof = True
    sc.camera.data.dof.focus_distance = 10.0
    emitter("dot", 0.02, (0, 0, -0.5), (1, 1, 1))
    p = render_still(sc, os.path.join(work, f"unit_{scale}.exr"))
    img = read_exr(p)
    np.save(os.path.join(work, f"unit_{scale}.npy"), img.channels["ViewLayer.Combined.A"])
    unit[str(scale)] = header_camera(p)
out["unit_scale"] = unit

blender_addon.unregister()
print("RESULT " + json.dumps(out))
