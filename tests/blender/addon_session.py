"""Runs inside a fresh Python with the bpy module (started by tests/test_addon.py).

Installs the built extension zip into a throw-away repository, exercises it on a small
Cycles scene and on bad inputs, disables it, and prints one JSON line of findings.
Usage: python addon_session.py ZIP WORKDIR
"""

import json
import os
import sys
import tempfile

import bpy
import numpy as np
from scene_parts import checkout_compat, emitter  # noqa: E402  (this folder: the script's own)

zip_path, work = sys.argv[1], sys.argv[2]
other_zip = sys.argv[3] if len(sys.argv) > 3 else None  # another platform's zip
out = {}


def cycles_scene(dof: bool, spp: int, depth_pass: bool = True, pano: bool = False, empty=False):
    # a clean scene without resetting preferences (that would disable the add-on)
    for coll in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.cameras,
                 bpy.data.worlds):
        for item in list(coll):
            coll.remove(item)
    sc = bpy.context.scene
    sc.mpib.last_passes = ""
    sc.mpib.last_message = ""
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = spp
    sc.cycles.use_denoising = False
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.max_bounces = 0
    sc.render.resolution_x, sc.render.resolution_y = 64, 48
    sc.render.resolution_percentage = 100
    sc.render.filter_size = 0.01
    sc.view_settings.view_transform = "Standard"
    sc.view_layers[0].use_pass_z = depth_pass
    world = bpy.data.worlds.new("black")
    world.color = (0, 0, 0)
    sc.world = world
    cam_data = bpy.data.cameras.new("cam")
    cam_data.type = "PANO" if pano else "PERSP"
    cam_data.lens, cam_data.sensor_width, cam_data.sensor_fit = 100.0, 36.0, "HORIZONTAL"
    cam_data.dof.use_dof = dof
    cam_data.dof.aperture_fstop = 1.0
    cam_data.dof.focus_distance = 6.0
    cam = bpy.data.objects.new("cam", cam_data)
    sc.collection.objects.link(cam)
    sc.camera = cam
    if empty:
        return sc
    # emissive checker wall at 6 m (in focus) and an emissive square at 1.5 m in front:
    # f_px = 100/36*64 = 178 px, R = 0.1 m/(2*1) = 0.05 m, A = 8.9 px per 1/m, so the
    # square blurs with radius A (1/1.5 - 1/6) = 4.4 px
    for name, z, size, colour, scale in (("wall", -6.0, 8.0, (0.2, 0.8, 0.3), 6.0),
                                        ("card", -1.5, 0.25, (1.0, 0.3, 0.1), 0.0)):
        emitter(name, size, (0.08 if name == "card" else 0, 0, z), colour, scale)
    return sc


out["probe"] = bpy.app.version_string


def read_rgb(path):
    from mpib_validate.runtime.io.exr import read_exr, rgba_from
    from mpib_validate.runtime.refocus import _colour_prefix

    img = read_exr(path)
    return rgba_from(img, _colour_prefix(img))[..., :3]


def multilayer_exr_output(sc):
    """Render output as float multilayer EXR (Blender 5.0 and 4.2 name it differently)."""
    s = sc.render.image_settings
    if hasattr(s, "media_type"):
        s.media_type = "MULTI_LAYER_IMAGE"
    else:
        s.file_format = "OPEN_EXR_MULTILAYER"
    s.color_depth = "32"


def render_to(path, sc):
    sc.render.filepath = path
    multilayer_exr_output(sc)
    bpy.ops.render.render(write_still=True)
    return path


def call(op, **kw):
    """Run an operator; an ERROR report reaches a Python caller as RuntimeError."""
    try:
        return sorted(op(**kw))
    except RuntimeError as exc:
        return ["RuntimeError: " + str(exc).strip()]


# -- install ---------------------------------------------------------------------------
prefs = bpy.context.preferences
if other_zip:  # Blender refuses another platform's zip (its manifest names that platform)
    other_dir = tempfile.mkdtemp(dir=work)
    prefs.extensions.repos.new(name="mpib_other", module="mpib_other",
                               custom_directory=other_dir, source="USER")
    out["other_platform_install"] = call(bpy.ops.extensions.package_install_files,
                                         filepath=other_zip, repo="mpib_other",
                                         enable_on_install=True)
    out["other_platform_files"] = sorted(f for f in os.listdir(other_dir) if not f.startswith("."))
    out["other_platform_enabled"] = [a.module for a in prefs.addons
                                     if a.module.startswith("bl_ext.mpib_other.")]
repo_dir = tempfile.mkdtemp(dir=work)
prefs.extensions.repos.new(name="mpib_test", module="mpib_test", custom_directory=repo_dir,
                           source="USER")
res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="mpib_test",
                                               enable_on_install=True)
out["install"] = sorted(res)
out["addon_enabled"] = [a.module for a in prefs.addons if a.module.endswith("mpib_refocus")]
out["operators"] = [n for n in ("refocus_render", "refocus_file", "pick_focus", "focus_pull")
                    if hasattr(bpy.ops.mpib, n)]
out["panels"] = [c for c in ("MPIB_PT_image", "MPIB_PT_compositor") if hasattr(bpy.types, c)]
import mpib_validate  # noqa: E402  (the add-on's bundled copy comes first on sys.path)

out["mpib_validate_from"] = mpib_validate.__file__
out["bundled_dir"] = bpy.utils.user_resource("EXTENSIONS", path=".local")

# -- refocus a real Cycles render --------------------------------------------------------
sc = cycles_scene(dof=False, spp=16)
bpy.ops.render.render(write_still=False)  # the add-on's handler keeps the passes
out["kept_passes"] = bool(sc.mpib.last_passes and os.path.exists(sc.mpib.last_passes))
kept_dir = os.path.dirname(sc.mpib.last_passes)
out["kept_dir"] = kept_dir
out["extension_user_dir"] = bpy.utils.user_resource("EXTENSIONS", path=".user")
sharp = read_rgb(sc.mpib.last_passes)
from mpib_validate.runtime.io.exr import find_pass, read_exr  # noqa: E402

_passes = read_exr(sc.mpib.last_passes)
np.save(os.path.join(work, "depth.npy"), _passes.channels[find_pass(_passes, "Depth")])
r = bpy.ops.mpib.refocus_render()
out["refocus_render"] = sorted(r)
out["message"] = sc.mpib.last_message
img = bpy.data.images.get("Render Result (refocused)")
out["image"] = [list(img.size), img.is_float] if img else None
refocused = np.array(img.pixels[:], np.float32).reshape(48, 64, 4)[::-1, :, :3]

# -- the modal operator's worker: the same result off the main thread; Esc stops it ----------
ops_mod = sys.modules[out["addon_enabled"][0] + ".operators"]
job_out = os.path.join(work, "job.exr")
request = ops_mod.prepare(sc, sc.mpib.last_passes, "job", save=job_out)
job = ops_mod.RefocusJob(request)
job.cancel()  # Esc before the first step
job.start().wait(120)
out["job_cancelled"] = {"cancelled": job.cancelled, "error": repr(job.error),
                        "result": job.result is not None, "written": os.path.exists(job_out)}
job = ops_mod.RefocusJob(request).start()
job.wait(120)
out["job_done"] = {"cancelled": job.cancelled, "error": repr(job.error),
                   "fraction": job.fraction, "written": os.path.exists(job_out),
                   "same_as_operator": bool(np.array_equal(job.result.image[..., :3], refocused))}
sc.camera.data.dof.use_dof = True
sc.cycles.samples = 256
dof_path = render_to(os.path.join(work, "dof.exr"), sc)
ref = read_rgb(dof_path)
np.save(os.path.join(work, "sharp.npy"), sharp)
np.save(os.path.join(work, "refocused.npy"), refocused)
np.save(os.path.join(work, "dof.npy"), ref)

# -- focus pull: a preview, then the full result from the kept MPI; a new render drops it ----
fp = sys.modules[out["addon_enabled"][0] + ".focus_pull"]
sc.camera.data.dof.use_dof = False  # sharp passes again
sc.cycles.samples = 16
bpy.ops.render.render(write_still=False)
call(bpy.ops.mpib.refocus_render)


def shown():
    im = bpy.data.images.get("Render Result (refocused)")
    return np.array(im.pixels[:], np.float32).reshape(im.size[1], im.size[0], 4)[::-1]


def fresh_refocus(sc, pixel=None):
    """What a plain refocus of the kept passes gives at the panel's settings (or at a
    focus pixel): no session, no cache."""
    from mpib_validate.runtime.camera import blender_camera
    from mpib_validate.runtime.refocus import focus_from_pixel, load_passes, refocus
    from mpib_validate.runtime.request import RefocusRequest

    request = ops_mod.prepare(sc, sc.mpib.last_passes, "fresh", save=None)
    cam = blender_camera(**request["camera"])
    passes = load_passes(sc.mpib.last_passes)
    d_f = focus_from_pixel(passes, *pixel) if pixel else cam.focus_disparity
    return refocus(RefocusRequest(passes, cam.blur_parameter, d_f, sc.mpib.preset)).image


def pull_record(result, pixel=None):
    sess = fp.State.session
    return {"result": result, "preview_shape": list(fp.State.last_preview_shape or ()),
            "image_shape": list(shown().shape),
            "max_diff_to_fresh": float(np.abs(shown() - fresh_refocus(sc, pixel)).max()),
            "builds": None if sess is None else sess.builds,
            "mpi": (fp.State.last_full_info or {}).get("mpi"), "message": sc.mpib.last_message}


camera_focus = shown().copy()  # Refocus Last Render at the camera's focus (the wall, 6 m)
pulls = {}
# the card at 1.5 m covers x = 26..56 at y = 24: focus on it
pulls["click_card"] = pull_record(call(bpy.ops.mpib.focus_pull, x=41, y=24), (41, 24))
pulls["click_card"]["changed"] = float(np.abs(shown() - camera_focus).max())
pulls["click_wall"] = pull_record(call(bpy.ops.mpib.focus_pull, x=3, y=3), (3, 3))
sc.mpib.use_camera_focus = False
sc.mpib.focus_mode = "DISTANCE"
sc.mpib.focus_distance = 3.0  # the slider: its update callback pulls the focus
pulls["slider"] = pull_record("update")
session_before = fp.State.session  # kept referenced: a new one cannot take its place
bpy.ops.render.render(write_still=False)  # a new render: the kept MPI is dropped
pulls["after_render_dropped"] = fp.State.session is None
bpy.data.objects["card"].location.x += 0.1  # the card moves; render and pull again
bpy.ops.render.render(write_still=False)
pulls["new_render"] = pull_record(call(bpy.ops.mpib.focus_pull, x=48, y=24), (48, 24))
pulls["new_session"] = fp.State.session is not session_before
del session_before
out["focus_pull"] = pulls
sc.mpib.use_camera_focus = True

# -- layered render: tick it, render, refocus; untick removes only the group layers --------
from mpib_validate.runtime.refocus import view_layers  # noqa: E402


def pixels_of(name):
    im = bpy.data.images.get(name)
    return np.array(im.pixels[:], np.float32).reshape(im.size[1], im.size[0], 4)[::-1]


sc = cycles_scene(dof=False, spp=16)  # the same wall and card as the single pass above
own = sc.view_layers.new("ArtistExtra")  # an artist's second view layer: kept as it is
own.use = False
lay = {"before": [vl.name for vl in sc.view_layers],
       "collections_before": sorted(c.name for c in bpy.data.collections)}
sc.mpib.layered_render = True
lay["tick_message"] = sc.mpib.last_message
lay["layers"] = [vl.name for vl in sc.view_layers]
lay["film_while_set_up"] = sc.render.film_transparent
bpy.ops.render.render(write_still=False)
lay["kept_layers"] = view_layers(read_exr(sc.mpib.last_passes))
lay["refocus"] = sorted(bpy.ops.mpib.refocus_render())
lay["refocus_message"] = sc.mpib.last_message
np.save(os.path.join(work, "layered.npy"), pixels_of("Render Result (refocused)")[..., :3])
# the groups again, now with the last render's depth
lay["update"] = sorted(bpy.ops.mpib.setup_layers())
lay["update_message"] = sc.mpib.last_message
# Refocus Animation reads the group layers of each written frame
sc.frame_start = sc.frame_end = 1
sc.mpib.refocus_animation = True
multilayer_exr_output(sc)
sc.render.filepath = os.path.join(work, "anim_layered", "frame_")
bpy.ops.render.render(animation=True)
sib = os.path.join(work, "anim_layered", "frame_0001_refocused.exr")
lay["animation_groups"] = (json.loads(read_exr(sib).header["mpib"]).get("groups")
                           if os.path.exists(sib) else sc.mpib.last_message)
sc.mpib.refocus_animation = False
sc.mpib.layered_render = False
lay["untick_message"] = sc.mpib.last_message
lay["after"] = [vl.name for vl in sc.view_layers]
lay["collections_after"] = sorted(c.name for c in bpy.data.collections)
lay["film_after"] = sc.render.film_transparent
# groups from the collections the artist ticks: the card's collection against the rest
front = bpy.data.collections.new("Front")
sc.collection.children.link(front)
card = bpy.data.objects["card"]
for c in list(card.users_collection):
    c.objects.unlink(card)
front.objects.link(card)
front.mpib_depth_group = True
sc.mpib.group_source = "COLLECTIONS"
lay["collections_call"] = sorted(bpy.ops.mpib.setup_layers())
lay["collections_message"] = sc.mpib.last_message
lay["collections_ticked"] = sc.mpib.layered_render
lay["remove_call"] = sorted(bpy.ops.mpib.remove_layers())
lay["collections_removed"] = ([vl.name for vl in sc.view_layers], sc.mpib.layered_render,
                              "Front" in bpy.data.collections)
sc.mpib.group_source = "AUTO"
sc.view_layers.remove(own)
bpy.data.collections.remove(front)
# one object: nothing to split, the single pass with a report
sc = cycles_scene(dof=False, spp=4, empty=True)
emitter("wall", 8.0, (0, 0, -6.0), (0.2, 0.8, 0.3), 6.0)
sc.mpib.layered_render = True
lay["one_message"] = sc.mpib.last_message
lay["one_layers"] = [vl.name for vl in sc.view_layers]
bpy.ops.render.render(write_still=False)
lay["one_refocus"] = sorted(bpy.ops.mpib.refocus_render())
lay["one_refocus_message"] = sc.mpib.last_message
sc.mpib.layered_render = False
out["layered"] = lay

# -- animation: each written frame gets a refocused sibling, focus from the camera's keys ---
sc = cycles_scene(dof=True, spp=4)
cam = sc.camera.data
cam.dof.focus_distance = 6.0
cam.dof.keyframe_insert("focus_distance", frame=1)
cam.dof.focus_distance = 1.5
cam.dof.keyframe_insert("focus_distance", frame=2)
sc.frame_start, sc.frame_end = 1, 2
cam.dof.use_dof = False  # sharp passes; the refocus uses the (animated) DOF settings
sc.mpib.refocus_animation = True
multilayer_exr_output(sc)
sc.render.filepath = os.path.join(work, "anim", "frame_")
bpy.ops.render.render(animation=True)
anim = {}
for f in (1, 2):
    src = sc.render.frame_path(frame=f)
    sib = os.path.join(os.path.dirname(src), os.path.splitext(os.path.basename(src))[0] + "_refocused.exr")
    anim[f] = {"written": os.path.exists(src), "refocused": os.path.exists(sib)}
    if os.path.exists(sib):
        from mpib_validate.runtime.io.exr import read_exr as _r

        anim[f]["focus_disparity"] = json.loads(_r(sib).header["mpib"])["focus_disparity"]
out["animation"] = anim
out["animation_message"] = sc.mpib.last_message
sc.mpib.refocus_animation = False

# -- bad inputs ----------------------------------------------------------------------------
reports = {}


calls = {}


def refocus_bad_render(case, **scene):
    """Render a 2-spp scene with the given faults and refocus it; keep the reports."""
    sc = cycles_scene(spp=2, **{"dof": False, **scene})
    bpy.ops.render.render(write_still=False)
    calls[case] = call(bpy.ops.mpib.refocus_render)
    reports[case] = sc.mpib.last_message


refocus_bad_render("no_depth_pass", depth_pass=False)
refocus_bad_render("depth_all_infinite", empty=True)
from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr  # noqa: E402

nan_path = os.path.join(work, "nan.exr")
depth = np.full((8, 8), 5.0, np.float32)
depth[2, 3] = np.nan
write_exr(nan_path, {**channels_from_rgba(np.ones((8, 8, 4), np.float32)), "Depth.Z": depth})
sc = cycles_scene(dof=False, spp=2)
calls["nan"] = call(bpy.ops.mpib.refocus_file, filepath=nan_path)
reports["nan"] = sc.mpib.last_message
# a layered render whose group colour holds a NaN, saved beside it: one report line,
# no refocused file (the NaN came out as an all-NaN channel with exit 0 on the CLI)
group_nan = os.path.join(work, "group_nan.exr")
layers = {}
for k, z in enumerate((8.0, 2.0)):
    rgba = np.ones((8, 8, 4), np.float32)
    rgba[..., :3] = 0.2 + 0.6 * k
    if k == 1:
        rgba[:4] = 0
        rgba[5, 5, 1] = np.nan
    layers.update(channels_from_rgba(rgba, f"mpib_group_{k}.Combined."))
    layers[f"mpib_group_{k}.Depth.Z"] = np.full((8, 8), z, np.float32)
write_exr(group_nan, layers)
sc.mpib.save_exr = True
sc.render.filepath = work + os.sep  # the refocused EXR goes beside the render output
calls["group_nan"] = call(bpy.ops.mpib.refocus_file, filepath=group_nan)
reports["group_nan"] = sc.mpib.last_message
out["group_nan_written"] = sorted(n for n in os.listdir(work) if n.startswith(("group_nan_", ".group_nan")))
# the same render without the NaN is saved there (the check above sees a written file)
clean = os.path.join(work, "group_ok.exr")
layers["mpib_group_1.Combined.G"][5, 5] = 0.0
write_exr(clean, layers)
calls["group_ok"] = call(bpy.ops.mpib.refocus_file, filepath=clean)
out["group_ok_written"] = sorted(n for n in os.listdir(work) if n.startswith("group_ok_"))
sc.mpib.save_exr = False
# no camera in the scene
camera = sc.camera
sc.camera = None
calls["no_camera"] = call(bpy.ops.mpib.refocus_file, filepath=nan_path)
reports["no_camera"] = sc.mpib.last_message
sc.camera = camera
calls["missing_file"] = call(bpy.ops.mpib.refocus_file, filepath=os.path.join(work, "missing.exr"))
reports["missing_file"] = sc.mpib.last_message
refocus_bad_render("camera_without_dof", dof=False)  # the documented workflow: no warning
refocus_bad_render("camera_with_dof", dof=True)
refocus_bad_render("panoramic", pano=True)
out["reports"] = reports
out["calls"] = calls

# -- unregister leaves nothing behind ------------------------------------------------------
bpy.ops.preferences.addon_disable(module=out["addon_enabled"][0])
out["after_disable"] = {
    "types": [c for c in dir(bpy.types) if c.startswith("MPIB")],
    "scene_property": hasattr(bpy.types.Scene, "mpib"),
    "collection_property": hasattr(bpy.types.Collection, "mpib_depth_group"),
    "handlers": [f.__name__ for f in bpy.app.handlers.render_complete + bpy.app.handlers.render_write
                 if f.__module__.startswith("bl_ext")],
    "kept_passes": [p for p in os.listdir(kept_dir)
                    if p.startswith(f"mpib_last_render_{os.getpid()}_")],
    "temporary_files": [p for p in os.listdir(tempfile.gettempdir())
                        if p.startswith(f"mpib_last_render_{os.getpid()}_")],
}
print("RESULT " + json.dumps(out), flush=True)
if checkout_compat().module_teardown_crashes():
    # bpy 4.2 as a Python module segfaults in its own teardown, after everything above has
    # run, once an add-on has registered a property with an update callback (found by
    # bisecting: the extension without its two update callbacks exits 0). Skip the
    # module's teardown: the result above is what the test reads.
    sys.stdout.flush()
    os._exit(0)
