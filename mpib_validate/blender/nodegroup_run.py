"""Running the generated compositor node group headless on given passes, in this
process's Blender: the tests' and the benchmarks' way to compare the group with its
numpy model (:func:`mpib_validate.runtime.blender.nodegroup.evaluate`). Harness code:
it writes the passes to a temporary folder and renders there, which the runtime never
does on a user's behalf."""

from __future__ import annotations

import numpy as np

from mpib_validate.runtime.blender.compat import compositor_tree, tree_output
from mpib_validate.runtime.blender.nodegroup import (Graph, build_group, evaluate,
                                                     is_legacy_api, node_id)


def _write_passes(folder, image: np.ndarray, depth: np.ndarray) -> tuple[str, str]:
    """Two EXR files an Image node reads exactly: the RGBA image, and the depth in R, G, B."""
    import os

    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    d = np.asarray(depth, np.float32)
    paths = (os.path.join(folder, "image.exr"), os.path.join(folder, "depth.exr"))
    write_exr(paths[0], channels_from_rgba(np.asarray(image, np.float32)))
    write_exr(paths[1], channels_from_rgba(np.stack([d, d, d, np.ones_like(d)], -1)))
    return paths


def run_on_passes(image: np.ndarray, depth: np.ndarray, graph: Graph, values: dict,
                  workdir=None) -> dict:
    """Render the group on given passes in this process's Blender (factory settings; do
    not mix with other ``bpy`` work): an Image node feeds ``image`` (premultiplied RGBA)
    and ``depth``, the group's scalar inputs get ``values``. Returns ``{"Image": (H, W,
    4), "seconds": compositing + render op}``. Works with the 5.x and the 4.x API."""
    import os
    import tempfile
    import time

    import bpy

    from mpib_validate.runtime.io.exr import read_exr, rgba_from

    image = np.asarray(image, np.float32)
    H, W = image.shape[:2]
    with tempfile.TemporaryDirectory(prefix="mpib-nodegroup-") as tmp:
        d = str(workdir or tmp)
        os.makedirs(d, exist_ok=True)
        paths = _write_passes(d, image, depth)
        bpy.ops.wm.read_factory_settings(use_empty=True)
        sc = bpy.context.scene
        sc.render.engine = "CYCLES"
        sc.cycles.samples = 1
        r = sc.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
        r.use_compositing = True
        sc.view_settings.view_transform = "Standard"
        s = r.image_settings
        if hasattr(s, "media_type"):
            s.media_type = "IMAGE"
        s.file_format, s.color_mode, s.color_depth = "OPEN_EXR", "RGBA", "32"
        tree = compositor_tree(sc, create=True)
        tree.nodes.clear()
        out = tree_output(tree)
        group = build_group(graph)
        node = tree.nodes.new(node_id("group", is_legacy_api(bpy)))
        node.node_tree = group
        srcs = []
        for path in paths:
            src = tree.nodes.new("CompositorNodeImage")
            src.image = bpy.data.images.load(path, check_existing=False)
            srcs.append(src)
        tree.links.new(srcs[0].outputs["Image"], node.inputs["Image"])
        sep = tree.nodes.new("CompositorNodeSeparateColor")
        tree.links.new(srcs[1].outputs["Image"], sep.inputs[0])
        tree.links.new(sep.outputs[0], node.inputs["Depth"])
        for name, v in values.items():
            node.inputs[name].default_value = float(v)
        if group.get("mpib_bokeh_angles"):  # 4.x: the angles the drivers would give
            scal = evaluate(graph, np.zeros((1, 1, 4), np.float32), np.ones((1, 1), np.float32),
                            values, keep=True)["nodes"]
            for op in graph.ops:
                if op.kind == "bokeh_polygon":
                    group.nodes[op.name].angle = float(scal[op.args[0].node])
        tree.links.new(node.outputs["Image"], out.inputs[0])
        r.filepath = os.path.join(d, "group_output.exr")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds = time.perf_counter() - t0
        res = rgba_from(read_exr(r.filepath))
    return {"Image": res, "seconds": seconds}
