"""Runs inside a fresh Python with the bpy module (started by tests/test_nodegroup.py and
scripts/measure_nodegroup.py), Blender 5.x or 4.2-4.5.

Usage: python nodegroup_session.py render JSON   (builds a small Cycles scene, adds the
       MPIB Refocus node with the extension's operator, renders, saves the .blend)
       python nodegroup_session.py reopen JSON   (opens a saved .blend and renders it; imports
       nothing of this project, so the extension is not installed)

Prints one line ``RESULT {json}``. ``MPIB_EXTRA_SITE`` (a site-packages folder) is added at
the end of ``sys.path`` for the project's dependencies (OpenEXR, SciPy) when this Blender's
Python lacks them (a second bpy environment of the same Python version).

The scenes are emissive (no lighting noise): a checker wall behind one or two foreground
objects; the camera sits at the origin looking down -Z with a 100 mm lens on a 36 mm
sensor (sensor fit horizontal) and f/1.
"""

import json
import os
import sys

if os.environ.get("MPIB_EXTRA_SITE"):
    sys.path.append(os.environ["MPIB_EXTRA_SITE"])

import bpy  # noqa: E402

command, args = sys.argv[1], json.loads(sys.argv[2])
out = {"version": bpy.app.version_string}


def emissive(name, colour, checker_scale=0.0, colour2=(0.9, 0.9, 0.9)):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    em = nt.nodes.new("ShaderNodeEmission")
    outn = nt.nodes.new("ShaderNodeOutputMaterial")
    if checker_scale:
        chk = nt.nodes.new("ShaderNodeTexChecker")
        chk.inputs["Scale"].default_value = checker_scale
        chk.inputs["Color1"].default_value = (*colour, 1)
        chk.inputs["Color2"].default_value = (*colour2, 1)
        nt.links.new(chk.outputs["Color"], em.inputs["Color"])
    else:
        em.inputs["Color"].default_value = (*colour, 1)
    nt.links.new(em.outputs["Emission"], outn.inputs["Surface"])
    return mat


def add(kind, location, size, mat, rotation=(0, 0, 0)):
    if kind == "plane":
        bpy.ops.mesh.primitive_plane_add(size=size, location=location, rotation=rotation)
    elif kind == "sphere":
        bpy.ops.mesh.primitive_uv_sphere_add(radius=size, location=location, segments=48,
                                             ring_count=24)
        bpy.ops.object.shade_smooth()
    ob = bpy.context.active_object
    ob.data.materials.append(mat)
    return ob


def build(scene_name, size, spp):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = spp
    sc.cycles.use_denoising = False
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.max_bounces = 0
    sc.cycles.seed = 0
    sc.render.threads_mode = "FIXED"
    sc.render.threads = 2
    sc.render.resolution_x, sc.render.resolution_y = size
    sc.render.resolution_percentage = 100
    sc.render.filter_size = 0.01
    sc.view_settings.view_transform = "Standard"
    sc.view_layers[0].use_pass_z = True
    world = bpy.data.worlds.new("black")
    world.color = (0, 0, 0)
    sc.world = world
    from scene_parts import sharp_camera  # this folder (the script's own)

    sharp_camera(sc)
    wall = emissive("wall", (0.2, 0.8, 0.3), 6.0)
    if scene_name == "cards":
        # checker wall at 6 m, an orange square at 1.5 m (A = 8.9 px per 1/m at 64 px)
        add("plane", (0, 0, -6.0), 8.0, wall)
        add("plane", (0.08, 0, -1.5), 0.25, emissive("card", (1.0, 0.3, 0.1)))
    elif scene_name == "sphere":
        # checker wall at 7 m, a striped sphere at 2.5 m and a small card at 1.2 m
        add("plane", (0, 0, -7.0), 10.0, wall)
        add("sphere", (-0.1, 0.02, -2.5), 0.28,
            emissive("ball", (0.9, 0.7, 0.1), 9.0, (0.1, 0.2, 0.9)))
        add("plane", (0.17, -0.06, -1.2), 0.1, emissive("card", (1.0, 0.2, 0.5)))
    elif scene_name == "tilted":
        # a checker floor receding from 2 m to 9 m under a card at 1.8 m
        add("plane", (0, -0.6, -5.5), 8.0, wall, rotation=(-1.45, 0, 0))
        add("plane", (0, 0, -12.0), 30.0, emissive("sky", (0.3, 0.4, 0.9), 3.0, (0.5, 0.6, 1.0)))
        add("plane", (-0.06, 0.04, -1.8), 0.3, emissive("card", (1.0, 0.3, 0.1), 4.0))
    else:
        raise SystemExit(f"unknown scene {scene_name}")
    return sc


def multilayer(sc, path):
    s = sc.render.image_settings
    if hasattr(s, "media_type"):
        s.media_type = "MULTI_LAYER_IMAGE"
    else:
        s.file_format = "OPEN_EXR_MULTILAYER"
    s.color_depth = "32"
    sc.render.filepath = path


def render_to(sc, path):
    multilayer(sc, path)
    bpy.ops.render.render(write_still=True)
    return path


if command == "render":
    work = args["out_dir"]
    sc = build(args["scene"], tuple(args["size"]), args["spp"])
    cam = sc.camera.data
    cam.dof.focus_distance = args.get("focus", 6.0)
    cam.dof.aperture_fstop = args.get("fstop", 1.0)
    if args.get("aperture"):  # [blades, rotation (radians), ratio]
        cam.dof.aperture_blades, cam.dof.aperture_rotation, cam.dof.aperture_ratio = \
            args["aperture"]
    if args.get("use_dof"):  # an artist who left depth of field on
        cam.dof.use_dof = True
    sys.path.insert(0, args["root"])
    import blender_addon  # the extension's modules, registered directly (not installed)

    blender_addon.register()
    sc.render.use_compositing = False
    bpy.ops.render.render()  # F12: the extension keeps the passes of the last render
    out["kept_passes"] = bool(sc.mpib.last_passes and os.path.exists(sc.mpib.last_passes))
    op = dict(max_slices=args.get("max_slices", 8), fill=args.get("fill", "INPAINT"),
              blur=args.get("blur", "AUTO"))
    try:
        out["operator"] = sorted(bpy.ops.mpib.add_refocus_node(**op))
    except RuntimeError:  # an ERROR report (a refusal) raises from bpy.ops
        out["operator"] = ["CANCELLED"]
    out["message"] = sc.mpib.last_message
    from mpib_validate.runtime.blender import nodegroup as ng

    if out["operator"] != ["FINISHED"]:  # refused: nothing to render
        blender_addon.unregister()
        print("RESULT " + json.dumps(out), flush=True)
        sys.stdout.flush()
        os._exit(0)
    tree = ng.compositor_tree(sc, create=False)
    node = tree.nodes[ng.GROUP_NAME]
    out["spec"] = json.loads(node.node_tree["mpib_spec"])
    out["drivers"] = {}
    ad = tree.animation_data
    for fc in (ad.drivers if ad else ()):
        out["drivers"][fc.data_path] = [fc.driver.expression, fc.driver.is_simple_expression,
                                        fc.driver.is_valid]
    if args.get("regenerate"):  # same operator again with a structural change
        op.update(args["regenerate"])
        bpy.ops.mpib.add_refocus_node(**op)
        out["first_spec"] = out["spec"]  # the frames below use the regenerated group
        out["spec"] = json.loads(tree.nodes[ng.GROUP_NAME].node_tree["mpib_spec"])
        out["groups"] = [g.name for g in bpy.data.node_groups]
    keys = args.get("keys")  # {"focus": [[frame, value], ...]}
    if keys:
        for f, v in keys["focus"]:
            cam.dof.focus_distance = v
            cam.dof.keyframe_insert("focus_distance", frame=f)
    frames = args.get("frames", [1])
    out["frames"] = {}
    for f in frames:
        sc.frame_set(f)
        values = {s.name: float(s.default_value) for s in node.inputs
                  if s.name not in ("Image", "Depth")}
        path = render_to(sc, os.path.join(work, f"node_{f}.exr"))
        out["frames"][str(f)] = {"path": path, "values": values,
                                 "focus_distance": cam.dof.focus_distance}
    blender_addon.unregister()  # (Blender 4.2 crashes at exit with it still registered)
    if args.get("save"):
        bpy.ops.wm.save_as_mainfile(filepath=args["save"])
        out["saved"] = args["save"]
    if args.get("dof_spp"):  # the truth: Cycles' own depth of field, compositor off
        sc.frame_set(frames[0])
        sc.render.use_compositing = False
        cam.dof.use_dof = True
        sc.cycles.samples = args["dof_spp"]
        out["dof"] = render_to(sc, os.path.join(work, "dof.exr"))
elif command == "drivers":
    # no render: the operator places the slices from the bounding boxes; the camera is
    # moved, turned, and focused on an object, with the sensor fit and size given
    sc = build(args["scene"], tuple(args["size"]), 1)
    cam_obj = sc.camera
    cam_obj.location = (0.3, -0.2, 0.5)
    cam_obj.rotation_euler = (0.05, -0.04, 0.02)
    cam = cam_obj.data
    cam.sensor_fit = args["fit"]
    cam.sensor_width, cam.sensor_height = 36.0, 20.0
    cam.dof.aperture_fstop = 2.0
    target = bpy.data.objects.new("focus_target", None)
    sc.collection.objects.link(target)
    target.location = (0.4, 0.3, -3.0)
    cam.dof.focus_object = target
    sc.render.resolution_percentage = 50
    sys.path.insert(0, args["root"])
    import blender_addon

    blender_addon.register()
    out["operator"] = sorted(bpy.ops.mpib.add_refocus_node())
    out["message"] = sc.mpib.last_message
    from mpib_validate.runtime.blender import nodegroup as ng

    node = ng.compositor_tree(sc, create=False).nodes[ng.GROUP_NAME]
    sc.frame_set(1)
    out["values"] = {s.name: float(s.default_value) for s in node.inputs
                     if s.name not in ("Image", "Depth")}
    cw = cam_obj.matrix_world
    view = cw.col[2].xyz.normalized()
    out["planar_depth"] = abs(view.dot(cw.translation - target.matrix_world.translation))
    out["spec"] = json.loads(node.node_tree["mpib_spec"])
    blender_addon.unregister()
elif command == "reopen":
    bpy.ops.wm.open_mainfile(filepath=args["blend"])
    sc = bpy.context.scene
    out["extension_loaded"] = any(m.startswith(("mpib", "blender_addon")) for m in sys.modules) \
        or hasattr(bpy.types, "MPIB_OT_add_refocus_node")
    sc.frame_set(args.get("frame", 1))
    out["path"] = render_to(sc, args["out"])
else:
    raise SystemExit(f"unknown command {command}")
print("RESULT " + json.dumps(out), flush=True)
from scene_parts import checkout_compat  # noqa: E402  (this folder: the script's own)

if checkout_compat().module_teardown_crashes():
    # bpy 4.2 as a Python module segfaults in its own teardown after this session has
    # rendered the node group (every result above is written by then; the session-start
    # graph exited 0). Skip the module's teardown: the result above is what the test
    # reads.
    sys.stdout.flush()
    os._exit(0)
