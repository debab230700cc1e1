"""mpib_validate.runtime.blender.compat on the running Blender (real bpy, real compositor renders).

The default run checks it on the pinned bpy 5.0.1; `make test-blender-versions` runs
this file on 4.2 LTS, 4.5 LTS and the newest 5.x as well. Each test states the fact
(``docs/camera.md``, "Blender versions") that decides which branch the helper takes, so a
Blender that changes its API fails here first, with the reason.
"""

from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from mpib_validate.runtime.blender import compat as bc
from mpib_validate.runtime.io import exr

pytestmark = pytest.mark.blender

V = bc.version()


def _empty_scene(w=6, h=4):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = w, h
    sc.render.resolution_percentage = 100
    sc.render.use_compositing = True
    sc.view_settings.view_transform = "Standard"
    return sc


def test_api_branch_matches_the_version():
    """Node-group compositor and ShaderNode* math from 5.0 on; scene.node_tree and
    CompositorNode* math on 4.2 and 4.5."""
    new_api = V >= (5, 0, 0)
    assert bc.has_compositing_node_group() == new_api
    expect = {bc.MATH: ("ShaderNodeMath", "CompositorNodeMath"),
              bc.MAP_RANGE: ("ShaderNodeMapRange", "CompositorNodeMapRange"),
              bc.MIX: ("ShaderNodeMix", "CompositorNodeMixRGB"),
              bc.VALUE: ("ShaderNodeValue", "CompositorNodeValue")}
    for kind, (new, old) in expect.items():
        assert bc.node_idname(kind) == (new if new_api else old), kind
    with pytest.raises(ValueError, match="unknown node kind"):
        bc.node_idname("BLUR")


def test_compositor_tree_is_made_once_and_found_again():
    sc = _empty_scene()
    assert bc.compositor_tree(sc, create=False) is None
    tree = bc.compositor_tree(sc, create=True, name="T")
    assert tree is not None and tree.bl_idname == "CompositorNodeTree"
    assert bc.compositor_tree(sc, create=True) == tree  # not replaced
    assert bc.compositor_tree(sc, create=False) == tree
    out = bc.tree_output(tree)
    assert bc.tree_output(tree) == out  # found, not duplicated
    assert bc.IMAGE_SOCKET in out.inputs
    if bc.has_compositing_node_group():
        assert out.bl_idname == "NodeGroupOutput"
        names = [it.name for it in tree.interface.items_tree if it.in_out == "OUTPUT"]
        assert names == [bc.IMAGE_SOCKET]
    else:
        assert out.bl_idname == "CompositorNodeComposite" and sc.use_nodes


def test_no_deprecated_compositor_api_is_used(recwarn):
    """5.3 warns that Scene.compositing_node_group (and use_nodes) go away in 6.0; the
    helper must not touch them where compositor effects exist."""
    sc = _empty_scene()
    bc.tree_output(bc.compositor_tree(sc, create=True))
    bc.compositor_tree(sc, create=False)
    deprecated = [str(w.message) for w in recwarn if issubclass(w.category, DeprecationWarning)
                  and "Blender 6.0" in str(w.message)]
    assert deprecated == []


def test_multilayer_exr_setting():
    sc = _empty_scene()
    s = sc.render.image_settings
    bc.set_multilayer_exr(s, color_depth="32", codec="ZIP")
    assert s.file_format == "OPEN_EXR_MULTILAYER" and s.color_depth == "32"
    assert s.exr_codec == "ZIP"
    if hasattr(s, "media_type"):
        assert s.media_type == "MULTI_LAYER_IMAGE"


def test_set_option_property_or_socket():
    """A property where the node has one (Math operation, everywhere), an input socket
    where 5.x moved the option there (Blur filter type, a menu socket taking the UI
    name), and a clear error where neither exists."""
    sc = _empty_scene()
    tree = bc.compositor_tree(sc)
    m = bc.new_node(tree, bc.MATH)
    bc.set_option(m, "operation", "MULTIPLY")
    assert m.operation == "MULTIPLY"
    blur = tree.nodes.new("CompositorNodeBlur")
    bc.set_option(blur, "filter_type", "GAUSS", socket="Type", socket_value="Gaussian")
    if "Type" in blur.inputs:
        assert blur.inputs["Type"].default_value == "Gaussian"
    else:
        assert blur.filter_type == "GAUSS"
    with pytest.raises(AttributeError, match="neither a property 'nope' nor an input socket"):
        bc.set_option(blur, "nope", 1, socket="Nope")


def test_math_map_range_mix_value_render_exactly(tmp_path):
    """A real compositor render through every kind: out = mix(fac, image, grey) with
    grey = Value(0.5) * 3 (Math) and fac = MapRange(0.5, [0, 2] -> [0, 1]) = 0.25, so
    out = 0.75 image + 0.375, to float32 rounding (a few ulps: 1e-6 relative)."""
    h, w = 4, 6
    rng = np.random.default_rng(0)
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = rng.random((h, w, 3), dtype=np.float32) * 4.0  # HDR values too
    src_path = tmp_path / "in.exr"
    exr.write_exr(src_path, exr.channels_from_rgba(rgba, "ViewLayer.Combined."))
    sc = _empty_scene(w, h)
    s = sc.render.image_settings
    s.file_format = "OPEN_EXR"
    s.color_mode = "RGBA"
    s.color_depth = "32"
    tree = bc.compositor_tree(sc)
    tree.nodes.clear()  # 4.x starts with Render Layers -> Composite
    img = tree.nodes.new("CompositorNodeImage")
    img.image = bpy.data.images.load(str(src_path), check_existing=False)
    colour = img.outputs.get("Combined") or img.outputs["Image"]
    val = bc.new_node(tree, bc.VALUE)
    val.outputs[0].default_value = 0.5
    mul = bc.new_node(tree, bc.MATH)
    bc.set_option(mul, "operation", "MULTIPLY")
    tree.links.new(val.outputs[0], mul.inputs[0])
    mul.inputs[1].default_value = 3.0
    rng_node = bc.new_node(tree, bc.MAP_RANGE)
    rng_node.inputs["Value"].default_value = 0.5
    rng_node.inputs["From Min"].default_value = 0.0
    rng_node.inputs["From Max"].default_value = 2.0
    rng_node.inputs["To Min"].default_value = 0.0
    rng_node.inputs["To Max"].default_value = 1.0
    mix = bc.new_node(tree, bc.MIX)
    fac, a, b = bc.mix_inputs(mix)
    tree.links.new(rng_node.outputs[0], fac)
    tree.links.new(colour, a)
    tree.links.new(mul.outputs[0], b)
    out = bc.tree_output(tree)
    tree.links.new(bc.mix_output(mix), out.inputs[bc.IMAGE_SOCKET])
    sc.render.filepath = str(tmp_path / "out.exr")
    bpy.ops.render.render(write_still=True, scene=sc.name)
    got = exr.rgba_from(exr.read_exr(tmp_path / "out.exr"))[..., :3]
    want = 0.75 * rgba[..., :3] + 0.25 * 1.5
    assert np.allclose(got, want, rtol=1e-6, atol=1e-6), np.abs(got - want).max()
