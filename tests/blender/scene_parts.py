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
