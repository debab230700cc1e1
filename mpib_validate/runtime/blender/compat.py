"""Blender API differences between 4.2 LTS and the newest 5.x, in one place.

Every ``bpy`` adapter of the project (:mod:`.cycles`, :mod:`.defocus_node`, the
add-on, the compositor node-group builder) goes through these helpers instead of
testing versions itself. Each helper looks for the API it needs (feature detection),
not at the version number, so a 4.x build with a back-ported API or a 5.x point
release that drops an alias takes the right branch. What differs (checked on bpy
4.2.23, 4.5.15, 5.0.1 and 5.3.0, ``tests/test_blender_compat.py``):

=====================  ==========================================  ==========================================
                       Blender 4.2, 4.5                            Blender 5.0 and later
=====================  ==========================================  ==========================================
compositor tree        ``scene.use_nodes = True`` creates          a ``CompositorNodeTree`` node group assigned
                       ``scene.node_tree``                         to ``scene.compositing_node_group``; 5.3
                                                                   adds ``scene.compositor_effects`` (each with
                                                                   a ``node_group``) and deprecates the former
tree output            a ``CompositorNodeComposite`` node          a ``NodeGroupOutput`` with an ``Image``
                                                                   (colour) interface socket
multilayer EXR         ``file_format = 'OPEN_EXR_MULTILAYER'``     ``media_type = 'MULTI_LAYER_IMAGE'``
Math, Map Range,       ``CompositorNodeMath``, ``...MapRange``,    ``ShaderNodeMath``, ``ShaderNodeMapRange``,
Mix, Value             ``CompositorNodeMixRGB``, ``...Value``      ``ShaderNodeMix`` (``data_type = 'RGBA'``),
                                                                   ``ShaderNodeValue``
node options           RNA properties (``node.filter_type``)       many became input sockets (menu sockets
                                                                   take the item's UI name: ``'Gaussian'``)
Cycles sample subset   4.2: ``sample_offset`` skips samples;       ``use_sample_subset``, ``sample_offset``,
                       4.5 as 5.x                                  ``sample_subset_length``
an ID's F-curves      ``action.fcurves``                          4.4+: slotted actions, the F-curves in the
                                                                   slot's channel bag (:func:`fcurve_value`)
multilayer EXR of      (not checked)                               5.0.1 refuses to write it ("Conflicting
non-square pixels                                                  attributes ... 'pixelAspectRatio'"):
                                                                   :func:`save_render` writes it as 1:1
=====================  ==========================================  ==========================================

The names here are used by other modules (``nodegroup.py`` builds the MPIB node
group with them): :func:`compositor_tree`, :func:`tree_output`,
:func:`set_multilayer_exr`, :data:`MATH`, :data:`MAP_RANGE`, :data:`MIX`,
:data:`VALUE`, :func:`node_idname`, :func:`new_node`, :func:`mix_inputs`, :func:`mix_output`,
:func:`set_option`, plus :func:`set_sample_subset` (Cycles), :func:`save_render`,
:func:`fcurve_value`,
:func:`has_compositing_node_group`,
:func:`has_compositor_effects`, :func:`legacy_compositor_api`,
:func:`module_teardown_crashes` and :func:`version`. No other module of the project
reads ``bpy.app.version`` (``tests/test_extension_conventions.py`` refuses it).

``bpy`` is imported lazily (inside the functions), so the package imports without it.
"""

from __future__ import annotations

#: Node kinds whose type name differs between 4.x and 5.x compositor trees.
MATH = "MATH"
MAP_RANGE = "MAP_RANGE"
MIX = "MIX"
VALUE = "VALUE"

#: ``kind -> (4.x compositor idname, 5.x idname)``.
_IDNAMES = {
    MATH: ("CompositorNodeMath", "ShaderNodeMath"),
    MAP_RANGE: ("CompositorNodeMapRange", "ShaderNodeMapRange"),
    MIX: ("CompositorNodeMixRGB", "ShaderNodeMix"),
    VALUE: ("CompositorNodeValue", "ShaderNodeValue"),
}

#: Name of the colour socket of the 5.x compositor tree's Group Output (and the
#: Composite node's input on 4.x).
IMAGE_SOCKET = "Image"


def _bpy():
    import bpy

    return bpy


def version() -> tuple[int, int, int]:
    """Blender's version, e.g. ``(4, 2, 23)``."""
    return tuple(_bpy().app.version)


def _scene_props():
    return _bpy().types.Scene.bl_rna.properties


def has_compositor_effects() -> bool:
    """True where a scene's compositing is a stack of ``scene.compositor_effects``,
    each with its own node group (Blender 5.3; ``scene.compositing_node_group``
    still works there but warns that it goes away in 6.0)."""
    return "compositor_effects" in _scene_props()


def legacy_compositor_api() -> bool:
    """True for the 4.2 to 4.5 compositor API (``scene.node_tree``, a Composite node,
    node options as RNA properties, no Convolve node); False for 5.x (a node group,
    options as input sockets). Detected as :func:`has_compositing_node_group` is."""
    return not has_compositing_node_group()


def module_teardown_crashes() -> bool:
    """True where bpy as a Python module segfaults in its own teardown after a session
    that registered a property with an update callback (the extension) or rendered the
    MPIB node group: bpy 4.2.23 (found by bisecting; 4.5 not tried); 5.0.1 and 5.3.0
    exit 0. Not seen in Blender itself. No API shows it, so this one is a version test:
    the test sessions print their result and then leave with ``os._exit``."""
    return version() < (5, 0, 0)


def has_compositing_node_group() -> bool:
    """True where the compositor tree is a ``CompositorNodeTree`` node group (Blender
    5.0+: ``scene.compositing_node_group``, or the active compositor effect's
    ``node_group`` on 5.3+); False where it is ``scene.node_tree`` (4.2 to 4.5)."""
    props = _scene_props()
    return "compositing_node_group" in props or "compositor_effects" in props


def compositor_tree(scene, create: bool = True, name: str = "Compositor"):
    """The compositor node tree of ``scene``, or None when it has none and ``create``
    is False.

    With ``create`` a missing tree is made the way this Blender does it:

    - 5.3+: a new ``CompositorNodeTree`` node group named ``name`` on the active
      compositor effect (``scene.compositor_effects``; an effect named ``name`` is
      added when there is none), without the deprecated ``compositing_node_group``;
    - 5.0 to 5.2: a new node group assigned to ``scene.compositing_node_group``;
    - 4.x: ``scene.use_nodes = True`` (Blender then makes ``scene.node_tree`` with a
      Render Layers and a Composite node). ``create`` also switches ``use_nodes`` on
      for an existing tree, since a tree that is off is not run.

    An existing tree is returned as it is (never replaced).
    """
    bpy = _bpy()
    if has_compositor_effects():
        effects = scene.compositor_effects
        effect = effects.active
        if effect is None and len(effects):
            effect = effects[0]
        if effect is None:
            if not create:
                return None
            effect = effects.new(name=name)
        if effect.node_group is None and create:
            effect.node_group = bpy.data.node_groups.new(name, "CompositorNodeTree")
        return effect.node_group
    if has_compositing_node_group():
        tree = scene.compositing_node_group
        if tree is None and create:
            tree = bpy.data.node_groups.new(name, "CompositorNodeTree")
            scene.compositing_node_group = tree
        return tree
    if create and not scene.use_nodes:
        scene.use_nodes = True
    if not scene.use_nodes:
        return None
    return scene.node_tree


def tree_output(tree):
    """The node whose ``inputs["Image"]`` is the compositor's result, made if missing.

    5.x: the tree's ``NodeGroupOutput``, after making sure the tree's interface has a
    colour output socket named ``Image`` (the first output socket is what is rendered).
    4.x: the tree's ``CompositorNodeComposite`` node.
    """
    if has_compositing_node_group():
        outputs = [it for it in tree.interface.items_tree
                   if getattr(it, "item_type", "") == "SOCKET" and it.in_out == "OUTPUT"]
        if not any(it.name == IMAGE_SOCKET for it in outputs):
            tree.interface.new_socket(IMAGE_SOCKET, in_out="OUTPUT", socket_type="NodeSocketColor")
        node = next((n for n in tree.nodes if n.bl_idname == "NodeGroupOutput"), None)
        if node is None:
            node = tree.nodes.new("NodeGroupOutput")
        return node
    node = next((n for n in tree.nodes if n.bl_idname == "CompositorNodeComposite"), None)
    if node is None:
        node = tree.nodes.new("CompositorNodeComposite")
    return node


def set_multilayer_exr(image_settings, color_depth: str | None = "32",
                       codec: str | None = None) -> None:
    """Make ``image_settings`` (e.g. ``scene.render.image_settings``) write a multilayer
    OpenEXR: ``media_type = 'MULTI_LAYER_IMAGE'`` on 5.x (which also sets the file
    format), ``file_format = 'OPEN_EXR_MULTILAYER'`` on 4.x; then the bit depth
    (``'16'`` or ``'32'``; None keeps it) and the EXR codec (e.g. ``'ZIP'``; None keeps
    it)."""
    if hasattr(image_settings, "media_type"):
        image_settings.media_type = "MULTI_LAYER_IMAGE"
    image_settings.file_format = "OPEN_EXR_MULTILAYER"
    if color_depth is not None:
        image_settings.color_depth = color_depth
    if codec is not None:
        image_settings.exr_codec = codec


def fcurve_value(id_data, data_path: str, frame, default):
    """``data_path`` of ``id_data`` at ``frame`` from its keyframes (``default`` without
    one). Blender 4.4+ keeps an action's F-curves per slot (the channel bag of the ID's
    ``action_slot``); 4.2 and 4.3 in ``action.fcurves``."""
    ad = getattr(id_data, "animation_data", None)
    if frame is None or ad is None or ad.action is None:
        return default
    fcurves = None
    try:
        from bpy_extras import anim_utils

        bag = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
        fcurves = bag.fcurves if bag is not None else None
    except (ImportError, AttributeError):
        pass
    if fcurves is None:
        fcurves = getattr(ad.action, "fcurves", None)
    fc = fcurves.find(data_path) if fcurves is not None else None
    return fc.evaluate(frame) if fc is not None else default


def save_render(image, path: str, scene) -> None:
    """``image.save_render(path, scene=scene)`` (e.g. the Render Result as the scene's
    output format).

    Blender 5.0.1 writes each pass of a multilayer EXR as its own part with the scene's
    pixel aspect ratio and then refuses its own file when the ratio is not 1 ("Conflicting
    attributes found for header :: ViewLayer.Depth 'pixelAspectRatio'", reported as
    "Error writing render result, Success"). The pixels are the same whatever the
    header's ratio, so where the write fails with non-square pixels it is done again
    with Pixel Aspect X and Y set to 1 for the write (the file then says 1:1; the
    scene's ratio is given back)."""
    try:
        image.save_render(path, scene=scene)
        return
    except RuntimeError:
        r = scene.render
        if r.pixel_aspect_x == r.pixel_aspect_y:
            raise
    old = (r.pixel_aspect_x, r.pixel_aspect_y)
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    try:
        image.save_render(path, scene=scene)
    finally:
        r.pixel_aspect_x, r.pixel_aspect_y = old


def set_sample_subset(cycles_settings, offset: int, length: int) -> None:
    """Make Cycles render only the samples ``[offset, offset + length)`` of its sequence
    (``offset = 0``: a plain render of ``length`` samples).

    4.5+: ``use_sample_subset`` with ``sample_offset`` (the first index) and
    ``sample_subset_length``, the sample count being the sequence length
    ``offset + length``. 4.2 has no subset properties (and assigning them is silently
    ignored, since ``scene.cycles`` is a Python property group): there
    ``sample_offset`` skips the first ``offset`` samples and ``samples = length``
    renders the next ``length``.
    """
    c = cycles_settings
    offset, length = int(offset), int(length)
    if "use_sample_subset" in c.bl_rna.properties:
        c.use_sample_subset = True
        c.samples = offset + length
        c.sample_offset = offset
        c.sample_subset_length = length
    else:
        c.samples = length
        c.sample_offset = offset


def node_idname(kind: str) -> str:
    """The node type name of ``kind`` (:data:`MATH`, :data:`MAP_RANGE`, :data:`MIX`,
    :data:`VALUE`) in this Blender's compositor trees: the ``CompositorNode*`` type
    where it exists (4.x), else the ``ShaderNode*`` one (5.x)."""
    try:
        old, new = _IDNAMES[kind]
    except KeyError:
        raise ValueError(f"unknown node kind {kind!r}; one of {sorted(_IDNAMES)}") from None
    return old if hasattr(_bpy().types, old) else new


def new_node(tree, kind: str, name: str | None = None):
    """Add a node of ``kind`` to a compositor ``tree`` (see :func:`node_idname`). A 5.x
    Mix node is set to colour mixing (``data_type = 'RGBA'``), as 4.x's Mix RGB is, so
    that its ``A``/``B`` colour sockets are the active ones (look them up with
    :func:`mix_inputs`)."""
    node = tree.nodes.new(node_idname(kind))
    if kind == MIX and hasattr(node, "data_type"):
        node.data_type = "RGBA"
    if name is not None:
        node.name = node.label = name
    return node


def _active(sockets):
    return [s for s in sockets if s.enabled]


def mix_inputs(node) -> tuple:
    """``(factor, a, b)`` input sockets of a colour Mix node on either version (5.x's
    ``ShaderNodeMix`` has one socket per data type under the same names; the enabled
    ones are the colour ones after :func:`new_node`; 4.x's Mix RGB names them
    ``Fac``, ``Image``, ``Image``)."""
    ins = _active(node.inputs)
    fac = next(s for s in ins if s.name in ("Factor", "Fac"))
    a, b = [s for s in ins if s is not fac][:2]
    return fac, a, b


def mix_output(node):
    """The result socket of a Mix node (5.x: the enabled one of its per-type outputs)."""
    return _active(node.outputs)[0]


def set_option(node, prop: str, value, socket: str | None = None, socket_value=None) -> None:
    """Set a node option that is the RNA property ``prop`` on 4.x and the input socket
    ``socket`` on 5.x.

    The socket wins where it exists (5.x), with ``socket_value`` if given (a menu
    socket takes its item's UI name, e.g. ``'Gaussian'`` where the 4.x property took
    ``'GAUSS'``), else ``value``. Otherwise the property is set to ``value``. Raises
    AttributeError naming both when the node has neither.
    """
    if socket is not None:
        s = node.inputs.get(socket)
        if s is not None:
            s.default_value = value if socket_value is None else socket_value
            return
    if prop in node.bl_rna.properties:
        setattr(node, prop, value)
        return
    raise AttributeError(f"{node.bl_idname} has neither a property {prop!r}"
                         + (f" nor an input socket {socket!r}" if socket else ""))
