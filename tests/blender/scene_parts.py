"""Scene pieces shared by the headless Blender session scripts (run as scripts, so
this folder is on sys.path)."""

import bpy


def emitter(name, size, location, colour, checker=0.0):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location)
    obj = bpy.context.active_object
    obj.name = name
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender 4.x: materials start without nodes
        mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    em = nt.nodes.new("ShaderNodeEmission")
    outn = nt.nodes.new("ShaderNodeOutputMaterial")
    if checker:
        chk = nt.nodes.new("ShaderNodeTexChecker")
        chk.inputs["Scale"].default_value = checker
        chk.inputs["Color1"].default_value = (*colour, 1)
        chk.inputs["Color2"].default_value = (0.9, 0.9, 0.9, 1)
        nt.links.new(chk.outputs["Color"], em.inputs["Color"])
    else:
        em.inputs["Color"].default_value = (*colour, 1)
    nt.links.new(em.outputs["Emission"], outn.inputs["Surface"])
    obj.data.materials.append(mat)
    return obj


def checkout_compat():
    """This checkout's ``mpib_validate/runtime/blender/compat.py``, loaded by its path
    (it imports nothing of the project): for a session that may run without the project
    importable (a ``reopen`` session, or after the extension and its wheels are gone)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "mpib_validate" / "runtime" / "blender" / "compat.py"
    spec = importlib.util.spec_from_file_location("_mpib_checkout_compat", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cycles_cpu(sc, spp, w, h):
    """Cycles on the CPU at ``spp`` samples, seed 0, no denoising, no adaptive sampling,
    no bounces (emitters only); ``w x h`` at 100 %, a 0.01 px pixel filter, the Standard
    view transform and the Z pass."""
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = spp
    sc.cycles.seed = 0
    sc.cycles.use_denoising = False
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.max_bounces = 0
    sc.render.resolution_x, sc.render.resolution_y = w, h
    sc.render.resolution_percentage = 100
    sc.render.filter_size = 0.01
    sc.view_settings.view_transform = "Standard"
    sc.view_layers[0].use_pass_z = True


def black_world(sc):
    """A black world (Blender 5.0's new world has a grey Background node: strength 0)."""
    world = bpy.data.worlds.new("black")
    world.color = (0, 0, 0)
    if world.node_tree is not None:
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                node.inputs["Strength"].default_value = 0.0
    sc.world = world
    return world


def sharp_camera(sc, lens=100.0, focus=6.0):
    """The scene camera: ``lens`` mm on a 36 mm wide sensor (horizontal fit), depth of field
    off (sharp passes) with the lens held in its settings: f/1, a disk, focus at ``focus``."""
    cam_data = bpy.data.cameras.new("cam")
    cam_data.lens, cam_data.sensor_width, cam_data.sensor_fit = lens, 36.0, "HORIZONTAL"
    cam_data.dof.use_dof = False
    cam_data.dof.aperture_fstop = 1.0
    cam_data.dof.aperture_blades = 0
    cam_data.dof.focus_distance = focus
    cam = bpy.data.objects.new("cam", cam_data)
    sc.collection.objects.link(cam)
    sc.camera = cam
    return cam
