"""Runs inside a fresh Python with the bpy module (started by tests/test_artist_scenes.py).

The extension in an artist's ordinary settings (issue 31): registers the extension from
this checkout, renders small emissive Cycles scenes (64 x 48, the camera of
tests/blender/addon_session.py: 100 mm on a 36 mm sensor, f/1) as sharp passes and as
Cycles' own depth of field of the same camera, runs the extension's operators and
compositor node, and saves the images (``.npy``) and the operators' reports.
Usage: python artist_session.py ROOT WORKDIR [CASE ...]   (default: every case)
Prints one line ``RESULT {json}``. ``MPIB_EXTRA_SITE`` (a site-packages folder) is added
at the end of ``sys.path`` for the project's dependencies when this Blender's Python lacks
them.
"""

import json
import os
import sys

if os.environ.get("MPIB_EXTRA_SITE"):  # the project's dependencies, after this Python's own
    sys.path.append(os.environ["MPIB_EXTRA_SITE"])

import bpy  # noqa: E402
import numpy as np  # noqa: E402

root, work = sys.argv[1], sys.argv[2]
wanted = set(sys.argv[3:])
sys.path.insert(0, root)
sys.path.insert(0, os.path.join(root, "tests", "blender"))
from scene_parts import black_world, cycles_cpu, emitter, sharp_camera  # noqa: E402

import blender_addon  # noqa: E402  (this checkout)

blender_addon.register()

from mpib_validate.runtime.blender import compat  # noqa: E402
from mpib_validate.runtime.io.exr import read_exr, rgba_from  # noqa: E402

out = {"version": bpy.app.version_string}
SHARP_SPP, DOF_SPP = 16, 256


def clean_scene(w=64, h=48, spp=SHARP_SPP):
    for coll in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.cameras,
                 bpy.data.worlds, bpy.data.node_groups, bpy.data.actions):
        for item in list(coll):
            coll.remove(item)
    for img in list(bpy.data.images):
        if img.name != "Render Result":
            bpy.data.images.remove(img)
    sc = bpy.context.scene
    sc.frame_start = sc.frame_end = 1
    sc.frame_set(1)
    cycles_cpu(sc, spp, w, h)
    sc.render.pixel_aspect_x = sc.render.pixel_aspect_y = 1.0
    sc.render.use_border = False
    sc.render.use_crop_to_border = False
    sc.render.film_transparent = False
    sc.render.use_compositing = False
    sc.render.use_stamp = False
    sc.unit_settings.scale_length = 1.0
    compat.set_multilayer_exr(sc.render.image_settings, color_depth="32")
    black_world(sc)
    sharp_camera(sc)
    tree = compat.compositor_tree(sc, create=False)
    if tree is not None:
        tree.nodes.clear()
    s = sc.mpib
    s.last_passes, s.last_message = "", ""
    s.refocus_animation = s.save_exr = False
    s.use_camera_focus = s.use_camera_fstop = True
    return sc


def wall_and_card(wall_size=8.0):
    """The checker wall at 6 m (in focus) and an orange card at 1.5 m: A = 8.9 px per 1/m,
    the card blurs by 4.4 px."""
    emitter("wall", wall_size, (0, 0, -6.0), (0.2, 0.8, 0.3), 6.0)
    emitter("card", 0.25, (0.08, 0, -1.5), (1.0, 0.3, 0.1))


def render_exr(sc, path, dof=False, spp=None):
    """Render to a multilayer EXR (the compositor as set); returns ``path``."""
    cam = sc.camera.data
    old = (cam.dof.use_dof, sc.cycles.samples)
    cam.dof.use_dof = dof
    sc.cycles.samples = spp or (DOF_SPP if dof else SHARP_SPP)
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
    cam.dof.use_dof, sc.cycles.samples = old
    return path


def rgba(path, layer=None):
    img = read_exr(path)
    if layer == "":  # a refocused result: plain R, G, B, A
        return rgba_from(img, "")
    if layer is None:
        layer = next(p for p in sorted({n.split(".")[0] for n in img.channels})
                     if p != "Composite")
    return rgba_from(img, f"{layer}.Combined.")


def save(name, array):
    np.save(os.path.join(work, name + ".npy"), np.asarray(array, np.float32))


def shown(name="Render Result (refocused)"):
    im = bpy.data.images.get(name)
    if im is None:
        return None
    return np.array(im.pixels[:], np.float32).reshape(im.size[1], im.size[0], 4)[::-1]


def call(op, **kw):
    """Run an operator; an ERROR report reaches a Python caller as RuntimeError."""
    try:
        return sorted(op(**kw))
    except RuntimeError as exc:
        return ["RuntimeError: " + str(exc).strip()]
    except Exception as exc:  # noqa: BLE001 - a raw traceback is what the tests look for
        return [f"Traceback: {type(exc).__name__}: {exc}"]


def refocus_last(sc, tag):
    """F12 (the extension keeps the passes), then Refocus Last Render."""
    bpy.data.images.get("Render Result (refocused)") and bpy.data.images.remove(
        bpy.data.images["Render Result (refocused)"])
    bpy.ops.render.render(write_still=False)
    res = {"kept": sc.mpib.last_passes, "kept_message": sc.mpib.last_message}
    res["call"] = call(bpy.ops.mpib.refocus_render)
    res["message"] = sc.mpib.last_message
    img = shown()
    if img is not None and res["call"] == ["FINISHED"]:
        save(tag, img)
    return res


def case(name):
    return not wanted or name in wanted


# -- the plain case: the reference figure of every row ---------------------------------------
if case("plain"):
    sc = clean_scene()
    wall_and_card()
    res = refocus_last(sc, "plain_refocused")
    save("plain_sharp", rgba(render_exr(sc, os.path.join(work, "plain_sharp.exr"))))
    save("plain_dof", rgba(render_exr(sc, os.path.join(work, "plain_dof.exr"), dof=True)))
    out["plain"] = res


# -- Refocus Animation: a focus object on a moving rig, and a camera dolly -----------------------
def animation_scene(kind):
    """Content at 1.5, 4 and 8 m; three frames focused at 1.5, 4 and 8 m (planar depth),
    by a focus empty parented to a keyed rig, or by the camera dollying against a fixed
    focus empty."""
    sc = clean_scene()
    emitter("wall", 10.0, (0, 0, -8.0), (0.2, 0.8, 0.3), 6.0)
    emitter("near", 0.2, (-0.12, 0.02, -1.5), (1.0, 0.3, 0.1))
    emitter("mid", 0.5, (0.3, -0.1, -4.0), (0.2, 0.3, 1.0), 4.0)
    target = bpy.data.objects.new("focus_target", None)
    sc.collection.objects.link(target)
    sc.camera.data.dof.focus_object = target
    focus = {1: 1.5, 2: 4.0, 3: 8.0}
    if kind == "rig":
        rig = bpy.data.objects.new("rig", None)
        sc.collection.objects.link(rig)
        target.parent = rig
        target.location = (0.05, 0.0, -1.5)
        for f, z in focus.items():
            rig.location = (0.0, 0.0, 1.5 - z)
            rig.keyframe_insert("location", frame=f)
    else:  # dolly: the camera moves back from 0 to 2.5 m and forward to -2.5 m
        target.location = (0.0, 0.0, -4.0)
        cam = sc.camera
        for f, z in ((1, -2.5), (2, 0.0), (3, 4.0)):  # focus 1.5, 4, 8 m
            cam.location = (0.0, 0.0, z)
            cam.keyframe_insert("location", frame=f)
    sc.frame_start, sc.frame_end = 1, 3
    sc.frame_set(1)
    return sc


for kind in ("rig", "dolly"):
    if not case("animation_" + kind):
        continue
    sc = animation_scene(kind)
    sc.mpib.refocus_animation = True
    folder = os.path.join(work, f"anim_{kind}")
    sc.render.filepath = os.path.join(folder, "frame_")
    bpy.ops.render.render(animation=True)
    sc.mpib.refocus_animation = False
    res = {"message": sc.mpib.last_message, "frames": {}}
    sources = {f: sc.render.frame_path(frame=f) for f in (1, 2, 3)}
    for f in (1, 2, 3):
        src = sources[f]
        sib = src[:-4] + "_refocused.exr"
        rec = {"written": os.path.exists(src), "refocused": os.path.exists(sib)}
        if rec["refocused"]:
            head = json.loads(read_exr(sib).header["mpib"])
            rec["focus_disparity"] = head["focus_disparity"]
            save(f"anim_{kind}_{f}_refocused", rgba(sib, layer=""))
        if rec["written"]:
            save(f"anim_{kind}_{f}_sharp", rgba(src))
            note = read_exr(src).header.get("Note", "")
            rec["note"] = note
        sc.frame_set(f)
        save(f"anim_{kind}_{f}_dof",
             rgba(render_exr(sc, os.path.join(work, f"anim_{kind}_{f}_dof.exr"), dof=True)))
        res["frames"][f] = rec
    sc.frame_set(1)
    out["animation_" + kind] = res


# -- render regions -------------------------------------------------------------------------
REGION = (0.25, 0.75, 0.25, 0.75)  # min x, max x, min y, max y (fractions, y up)
for crop in (True, False):
    name = "region_crop" if crop else "region_nocrop"
    if not case(name):
        continue
    sc = clean_scene()
    wall_and_card()
    r = sc.render
    r.use_border, r.use_crop_to_border = True, crop
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = REGION
    res = refocus_last(sc, name + "_refocused")
    if not crop:  # the focus pull on the region: on the card, and outside the region
        res["pull"] = [call(bpy.ops.mpib.focus_pull, x=41, y=24), sc.mpib.last_message,
                       list(shown().shape)]
        res["pull_outside"] = [call(bpy.ops.mpib.focus_pull, x=2, y=2), sc.mpib.last_message]
        sc.mpib.use_camera_focus = True
    save(name + "_sharp", rgba(render_exr(sc, os.path.join(work, name + "_sharp.exr"))))
    save(name + "_dof", rgba(render_exr(sc, os.path.join(work, name + "_dof.exr"), dof=True)))
    out[name] = res


# -- the compositor node: plain, Unit Scale 0.01, film transparent ---------------------------
def node_render(sc, tag, **op):
    """F12 for the slices, Add Refocus Node, render through it; the node's output and the
    truth (Cycles' depth of field, compositor off) are saved."""
    bpy.ops.render.render(write_still=False)
    res = {"call": call(bpy.ops.mpib.add_refocus_node, **op), "message": sc.mpib.last_message}
    if res["call"] != ["FINISHED"]:
        return res
    sc.render.use_compositing = True
    path = render_exr(sc, os.path.join(work, tag + "_node.exr"))
    save(tag + "_node", rgba(path, layer="Composite"))
    save(tag + "_sharp", rgba(path))
    sc.render.use_compositing = False
    save(tag + "_dof", rgba(render_exr(sc, os.path.join(work, tag + "_dof.exr"), dof=True)))
    return res


if case("node_plain"):
    sc = clean_scene()
    wall_and_card()
    out["node_plain"] = node_render(sc, "node_plain")
if case("node_unit"):
    sc = clean_scene()
    wall_and_card()
    sc.unit_settings.scale_length = 0.01
    out["node_unit"] = node_render(sc, "node_unit")
if case("film"):
    for transparent, tag in ((True, "film"), (False, "film_off")):  # and the same scene opaque
        sc = clean_scene()
        wall_and_card(wall_size=1.2)  # the wall covers part of the frame: film shows around it
        sc.render.film_transparent = transparent
        out[tag + "_node"] = node_render(sc, tag)
        out[tag + "_operator"] = refocus_last(sc, tag + "_refocused")


# -- depth of field left on: every operator says so; the documented workflow is quiet ----------
if case("dof_on"):
    sc = clean_scene(spp=4)
    wall_and_card()
    res = {}
    bpy.ops.render.render(write_still=False)
    sc.mpib.last_message = ""
    res["off_render"] = [call(bpy.ops.mpib.refocus_render), sc.mpib.last_message]
    sc.camera.data.dof.use_dof = True
    bpy.ops.render.render(write_still=False)
    kept = sc.mpib.last_passes
    sc.mpib.last_message = ""
    res["render"] = [call(bpy.ops.mpib.refocus_render), sc.mpib.last_message]
    sc.mpib.last_message = ""
    res["file"] = [call(bpy.ops.mpib.refocus_file, filepath=kept), sc.mpib.last_message]
    sc.mpib.last_message = ""
    res["focus_pull"] = [call(bpy.ops.mpib.focus_pull, x=40, y=24), sc.mpib.last_message]
    sc.mpib.last_message = ""
    res["node"] = [call(bpy.ops.mpib.add_refocus_node), sc.mpib.last_message]
    sc.mpib.refocus_animation = True
    sc.render.filepath = os.path.join(work, "dof_anim", "frame_")
    sc.mpib.last_message = ""
    bpy.ops.render.render(animation=True)
    res["animation"] = [os.path.exists(os.path.join(work, "dof_anim", "frame_0001_refocused.exr")),
                        sc.mpib.last_message]
    sc.mpib.refocus_animation = False
    out["dof_on"] = res


# -- the artist's compositor tree: Render Layers -> Glare -> output --------------------------
if case("tree"):
    sc = clean_scene(spp=4)
    wall_and_card()
    tree = compat.compositor_tree(sc, create=True)
    tree.nodes.clear()
    rl = tree.nodes.new("CompositorNodeRLayers")
    glare = tree.nodes.new("CompositorNodeGlare")
    glare.name = "Glare"
    outn = compat.tree_output(tree)
    tree.links.new(rl.outputs["Image"], glare.inputs["Image"])
    tree.links.new(glare.outputs["Image"], outn.inputs[0])
    bpy.ops.render.render(write_still=False)
    res = {"call": call(bpy.ops.mpib.add_refocus_node), "message": sc.mpib.last_message}
    res["links"] = sorted(f"{l.from_node.name}.{l.from_socket.name} -> {l.to_node.name}."
                          f"{l.to_socket.name}" for l in tree.links)
    out["tree"] = res


# -- pixel aspect 2:1 ----------------------------------------------------------------------------
if case("aspect"):
    sc = clean_scene(w=32, h=48)  # 2:1 pixels: the frame is shown 64 x 48
    wall_and_card()
    sc.render.pixel_aspect_x = 2.0
    res = refocus_last(sc, "aspect_refocused")
    res["pull"] = [call(bpy.ops.mpib.focus_pull, x=20, y=24), sc.mpib.last_message,
                   list(shown().shape)]
    sc.mpib.use_camera_focus = True
    res["node"] = [call(bpy.ops.mpib.add_refocus_node), sc.mpib.last_message]
    # the truth: Blender cannot write a multilayer EXR with non-square pixels, a plain one
    s = sc.render.image_settings
    if hasattr(s, "media_type"):
        s.media_type = "IMAGE"
    s.file_format, s.color_mode, s.color_depth = "OPEN_EXR", "RGBA", "32"
    p = render_exr(sc, os.path.join(work, "aspect_dof.exr"), dof=True)
    save("aspect_dof", rgba_from(read_exr(p), ""))
    compat.set_multilayer_exr(s, color_depth="32")
    out["aspect"] = res


# -- an orthographic camera ----------------------------------------------------------------------
if case("ortho"):
    # the frame 2.16 m wide (as the perspective camera's at 6 m), f/2: R = 1/(2 N) = 0.25 m,
    # 29.6 px per metre, the card at 1.5 m blurs by 29.6 * 0.25 * 4.5 / 6 = 5.6 px
    sc = clean_scene()
    wall_and_card()
    cam = sc.camera.data
    cam.type, cam.ortho_scale = "ORTHO", 2.16
    cam.dof.aperture_fstop = 2.0
    res = refocus_last(sc, "ortho_refocused")
    save("ortho_sharp", rgba(render_exr(sc, os.path.join(work, "ortho_sharp.exr"))))
    save("ortho_dof", rgba(render_exr(sc, os.path.join(work, "ortho_dof.exr"), dof=True)))
    res["node"] = [call(bpy.ops.mpib.add_refocus_node), sc.mpib.last_message]
    out["ortho"] = res

# -- read_camera off the main thread (as in an interface render job): the camera's keys --
if case("thread"):
    import threading

    from mpib_validate.runtime.blender.camera import read_camera

    sc = clean_scene()
    cam = sc.camera.data
    cam.dof.focus_distance, cam.lens = 6.0, 100.0
    cam.dof.keyframe_insert("focus_distance", frame=1)
    cam.keyframe_insert("lens", frame=1)
    cam.dof.focus_distance, cam.lens = 1.5, 50.0
    cam.dof.keyframe_insert("focus_distance", frame=2)
    cam.keyframe_insert("lens", frame=2)
    sc.frame_end = 2
    sc.frame_set(1)
    got = {}

    def job():
        c = read_camera(sc, frame=2)
        got["thread"] = [c.focus_distance, c.lens_mm, sc.frame_current]

    t = threading.Thread(target=job)
    t.start()
    t.join()
    c = read_camera(sc, frame=2)
    got["main"] = [c.focus_distance, c.lens_mm, sc.frame_current]
    sc.frame_set(1)
    out["thread"] = got

blender_addon.unregister()
print("RESULT " + json.dumps(out), flush=True)
if compat.module_teardown_crashes():
    # bpy 4.2 as a Python module segfaults in its own teardown once an add-on has
    # registered a property with an update callback (see addon_session.py); the result
    # above is what the test reads.
    sys.stdout.flush()
    os._exit(0)
