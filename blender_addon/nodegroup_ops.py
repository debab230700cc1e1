"""The "MPIB Refocus" compositor node: an operator that generates it and wires it in.

The node is a node group of Blender's built-in nodes (``mpib_validate.runtime.blender.nodegroup``), so
it renders inside the compositor (F12, animation renders, render farms, the GPU
compositor) and keeps working when the .blend is opened where the extension is not
installed. This module only adapts Blender to it: where the slices go (the depth of
the last render, else the objects' bounding boxes), the aperture over the animation,
and the drivers from the scene camera.
"""

import os

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty

from . import calibrate

BLUR_ITEMS = (
    ("AUTO", "Auto", "On Blender 5.x Convolve for blurs from 12 px (fractional radii, the "
                     "same cost at any radius) and Bokeh Blur below (cheaper there); "
                     "Bokeh Blur on 4.x"),
    ("CONVOLVE", "Convolve", "FFT convolution with a disk built from nodes (Blender 5.x)"),
    ("BOKEH", "Bokeh Blur", "Bokeh Blur with a round Bokeh Image: whole-pixel radii, cost "
                            "growing with the radius (faster below about 13 px)"),
)
FILL_ITEMS = (
    ("INPAINT", "Inpaint", "Extend each slice under the nearer ones (hidden background)"),
    ("OFF", "Off", "No hidden background (cheaper; halos at blurred foreground edges)"),
)


def scene_cameras(scene):
    """The scene camera (:func:`mpib_validate.runtime.blender.camera.read_camera`) at the
    frames of the animation (at most :data:`FRAME_SAMPLES`, evenly spread), and now.
    Every frame is evaluated as Blender renders it (parents, constraints, drivers); the
    current frame is set back afterwards."""
    from mpib_validate.runtime.blender.camera import read_camera

    now = scene.frame_current
    try:
        frames = [read_camera(scene, f) for f in _frames(scene)]
    finally:
        scene.frame_set(now)
    return frames, read_camera(scene)


#: Most frames :func:`scene_cameras` evaluates (each is a whole scene evaluation).
FRAME_SAMPLES = 100


def _frames(scene, limit=FRAME_SAMPLES):
    f0, f1 = scene.frame_start, scene.frame_end
    step = max(1, (f1 - f0 + 1) // limit)
    return range(f0, f1 + 1, step)


def _last_depth(scene):
    """The Depth pass of the last render this session kept, or None."""
    path = getattr(getattr(scene, "mpib", None), "last_passes", "")
    if not path or not os.path.exists(path):
        return None
    from mpib_validate.runtime.blender.layers import artist_layer

    from .operators import load_render_passes

    passes = load_render_passes(path, artist_layer(scene).name)
    r = scene.render
    W = int(r.resolution_x * r.resolution_percentage / 100)
    H = int(r.resolution_y * r.resolution_percentage / 100)
    return passes.depth if passes.depth.shape == (H, W) else None


#: The refusal for a ratio the node group cannot draw (the issue's wording).
ANAMORPHIC_REFUSAL = ("the node group cannot draw an anamorphic aperture ratio; use Refocus "
                      "Last Render")


def shape_refusal(apertures, legacy: bool, blur: str) -> str | None:
    """Why the node group cannot draw the camera's aperture over the animation, or None.
    Blades are fixed when the group is made (one count for every frame); an anamorphic
    ratio needs Convolve (Bokeh Blur's Bokeh Image is square), so Blender 5.0 or later
    and Blur Auto or Convolve. Blades work on 4.2-4.5 too (Bokeh Blur; drivers turn the
    Bokeh Images)."""
    blades = sorted({a.blades for a in apertures})
    anamorphic = any(a.ratio != 1.0 for a in apertures)
    if len(blades) > 1:
        return (f"the camera's aperture blades change over the animation ({blades}): the "
                f"node group draws one blade count; use Refocus Animation")
    if anamorphic and legacy:
        return ANAMORPHIC_REFUSAL + " (Blender 4.x has no Convolve node to stretch its kernels)"
    if anamorphic and blur == "BOKEH":
        return ("Bokeh Blur cannot draw an anamorphic aperture ratio (its Bokeh Image is "
                "square): choose Blur: Convolve or Auto, or use Refocus Last Render")
    return None


class MPIB_OT_add_refocus_node(bpy.types.Operator):
    """Add (or regenerate) the MPIB Refocus node group between Render Layers and the
    compositor output, driven by the scene camera's focus and aperture"""

    bl_idname = "mpib.add_refocus_node"
    bl_label = "Add Refocus Node"
    bl_options = {"REGISTER", "UNDO"}

    max_slices: IntProperty(name="Slices", default=5, min=1, max=32,
                            description="Largest number of depth slices (more: slower, finer)")
    tolerance_px: FloatProperty(name="Tolerance", default=0.5, min=0.05, max=16.0,
                                description="Blur-radius error the slice spacing allows (px); "
                                            "raised as needed to stay within Slices")
    fill: EnumProperty(name="Fill", items=FILL_ITEMS, default="INPAINT")
    blur: EnumProperty(name="Blur", items=BLUR_ITEMS, default="AUTO")
    drivers: BoolProperty(name="Camera Drivers", default=True,
                          description="Drive focus, f-stop, lens, sensor and resolution from "
                                      "the scene camera (delete a driver to set it by hand)")

    @classmethod
    def poll(cls, context):
        sc = context.scene
        if sc is None or sc.camera is None or sc.camera.type != "CAMERA":
            cls.poll_message_set("The scene needs a camera")
            return False
        return True

    def execute(self, context):
        from mpib_validate.runtime.blender import nodegroup as ng
        from mpib_validate.runtime.camera import blender_camera

        scene = context.scene
        legacy = ng.is_legacy_api(bpy)
        if self.blur == "CONVOLVE" and legacy:
            self.report({"ERROR"}, "Convolve needs Blender 5.0 or later; choose Bokeh Blur")
            return {"CANCELLED"}
        from mpib_validate.runtime.blender.camera import refusal

        try:
            frames, current = scene_cameras(scene)
            for c in (current, *frames):
                problem = refusal(c, dof=False, orthographic=False)
                if problem:
                    raise calibrate.CalibrationError(problem)
            if current.pixel_aspect != 1.0:
                raise calibrate.CalibrationError(
                    f"the MPIB Refocus node blurs with round kernels, but Output > Format > "
                    f"Pixel Aspect X:Y is {current.pixel_aspect:.4g}:1: set them equal, or "
                    f"use Refocus Last Render (it refocuses non-square pixels)")
            cams = [blender_camera(**c.lens()) for c in frames]
            now = blender_camera(**current.lens())
            apertures = [c.aperture for c in cams] + [now.aperture]
            problem = shape_refusal(apertures, legacy, self.blur)
            if problem:
                raise calibrate.CalibrationError(problem)
        except (calibrate.CalibrationError, ValueError) as exc:
            if hasattr(scene, "mpib"):
                scene.mpib.last_message = f"error: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        A = max(c.blur_parameter for c in cams)  # the widest aperture of the animation
        from .operators import _errors

        try:
            depth = _last_depth(scene)
        except _errors():  # an unreadable kept render: the bounding boxes instead
            depth = None
        try:
            if depth is not None:
                d, tol = ng.place_slices(depth, now.blur_parameter, self.tolerance_px,
                                         self.max_slices)
                source = "the last render's depth"
            else:
                d, tol = ng.slices_for_intervals(ng.scene_disparity_intervals(scene),
                                                 now.blur_parameter, self.tolerance_px,
                                                 self.max_slices)
                source = "the objects' bounding boxes (render once and regenerate for " \
                         "slices on the rendered depth)"
        except ValueError as exc:
            self.report({"ERROR"}, f"cannot place slices: {exc}")
            return {"CANCELLED"}
        r_max = max(c.blur_parameter * max(abs(x - c.focus_disparity) for x in d) for c in cams)
        blur = ("bokeh" if legacy else "convolve") if self.blur == "AUTO" else self.blur.lower()
        spec = ng.make_spec(d, A, fill=self.fill.lower(), blur=blur,
                            max_radius_px=max(r_max, now.blur_parameter * float(d[-1])),
                            # Auto: Bokeh Blur for the slices that stay small (cheaper)
                            focus_disparity=([c.focus_disparity for c in cams]
                                             if self.blur == "AUTO" else None),
                            aperture=apertures)
        graph = ng.describe(spec)
        tree = ng.compositor_tree(scene, create=True)
        node = tree.nodes.get(ng.GROUP_NAME)
        group = node.node_tree if node is not None and ng.spec_of(node.node_tree) else None
        if group is not None:  # the aperture inputs may go (a disk now): their drivers first
            for name, *_ in ng.SHAPE_INPUTS:
                if name in node.inputs:
                    node.inputs[name].driver_remove("default_value")
        group = ng.build_group(graph, group=group)
        wiring = []
        node = ng.install(scene, group, changes=wiring)
        scene.render.use_compositing = True
        if self.drivers:
            ng.add_camera_drivers(node, scene)
        n_conv = sum(op.kind == "convolve" for op in graph.ops)
        n_bokeh = sum(op.kind == "bokeh_blur" for op in graph.ops)
        msg = (f"MPIB Refocus node: {len(d)} slices from {source}, tolerance {tol:.2g} px, "
               f"fill {self.fill.lower()}, {n_conv + n_bokeh} blurs ({n_conv} Convolve, "
               f"{n_bokeh} Bokeh Blur)")
        if spec.shaped:
            ap = now.aperture
            msg += (f"; aperture {'a disk' if not ap.blades else f'{ap.blades} blades'}"
                    f"{', ratio driven' if spec.anamorphic else ''}"
                    f"{', rotation driven' if ap.blades else ''}"
                    f" (blades are fixed: regenerate the node after changing them)")
        if wiring:
            msg += "; " + "; ".join(wiring)
        if legacy and blur == "bokeh":
            side = max(now.width, now.height)
            if r_max > 0.1 * side:
                msg += (f"; blur radii up to {r_max:.0f} px are cut to {0.1 * side:.0f} px "
                        f"(Bokeh Blur's limit in Blender 4.x, 10 % of the larger side)")
        if current.region is not None and not current.region.crop:
            warn = ("the render region is not cropped: the node blurs the empty frame around "
                    "it into its rim; tick Output > Format > Crop to Render Region")
            msg += "; " + warn
            self.report({"WARNING"}, warn)
        cam = scene.camera.data
        if cam.dof.use_dof:  # the renderer blurs, then the node blurs again
            warn = (f"depth of field is on in the camera '{scene.camera.name}': the render "
                    f"comes out blurred and the node blurs it again; turn Camera > Depth of "
                    f"Field off (its f-stop and focus still drive the node)")
            msg += "; " + warn
            self.report({"WARNING"}, warn)
        if hasattr(scene, "mpib"):
            scene.mpib.last_message = msg
        self.report({"INFO"}, msg)
        return {"FINISHED"}


def draw_add_menu(self, context):
    if getattr(context.space_data, "tree_type", "") == "CompositorNodeTree":
        self.layout.operator(MPIB_OT_add_refocus_node.bl_idname, text="MPIB Refocus",
                             icon="NODETREE")


_MENU = "NODE_MT_category_compositor_filter_blur"


classes = (MPIB_OT_add_refocus_node,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    menu = getattr(bpy.types, _MENU, None)
    if menu is not None:
        menu.append(draw_add_menu)


def unregister():
    menu = getattr(bpy.types, _MENU, None)
    if menu is not None:
        menu.remove(draw_add_menu)
    _unregister_classes()

