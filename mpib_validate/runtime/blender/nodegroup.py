"""MPIB Refocus as a compositor node group made only of Blender's built-in nodes.

A Python-defined node cannot execute in a compositor tree, but a node group of built-in
nodes runs in Blender 4.2 to 5.x and keeps working when the .blend is opened without the
extension (checked here on the CPU compositor of 5.0.1, 4.2.23 and 5.3.0; every node used also
has a GPU implementation, not checked here). This module writes Eq. 1 of the
supplement as such a group. The graph is described ONCE, as data (:func:`describe`:
a list of :class:`Op`), and that one description is

- emitted for the 5.x API or the 4.2-4.5 API (:func:`build_group`), and
- evaluated by a numpy model of the same nodes (:func:`evaluate`), so that the group's
  output can be checked against it pixel for pixel.

The graph (slices ``i = 0..N-1`` far to near at disparities ``d_i``, fixed when the
group is generated; everything else is computed inside the graph, so drivers may
animate focus and aperture):

1. Blur parameter from the lens, as :func:`mpib_validate.runtime.camera.blender_camera`:
   ``R = f_mm 1e-3 / (unit 2 N)`` (scene units), ``f_px = f_mm / sensor * W``,
   ``A = R f_px``; focus ``d_f = 1 / z_f``; slice radius ``r_i = A |d_i - d_f|`` px.
   "Sensor Width" is the sensor size across the image width for the camera's fit (the
   drivers of :mod:`blender_addon.nodegroup_ops` compute it for AUTO and VERTICAL fits).
2. Per pixel ``d = 1/Z`` from the Depth pass and the additive split between
   neighbouring slices of :func:`mpib_validate.runtime.layers.mpi.split_between_planes`
   (``additive=True``, as the numpy default preset): with ``u = clamp((d - d_i) /
   (d_{i+1} - d_i))`` the near slice gets ``u alpha`` and the far slice ``(1 - u)
   alpha``; the two shares add up to the pixel (and Eq. 16 gives its disparity). The
   intervals ``[d_i, d_{i+1})`` (and, last, the content on the nearest slice) are grouped
   into slabs (:func:`slabs_for`: consecutive ones while their blur radii span at most
   ``SLAB_PX``); a slab has one layer per slice it touches (a slice between two slabs
   has one in each), the image times the shares of the slab's pixels (premultiplied
   colour and alpha). An "over" split would count a small out-of-focus highlight up to
   twice (the far slice's opaque backing is hardly hidden by the blurred near share).
   Edge pixels: the Depth pass holds the surface at the pixel centre, but an
   anti-aliased pixel next to nearer content (within a pixel, by more than
   ``EDGE_JUMP_PX`` of blur radius: a Dilate/Erode of ``d``) mixes in the nearer colour,
   which the far slice would smear into a halo when it blurs. ``"soft"`` edges (with the
   fill; only where the nearer content is in a nearer slab, and not for highlights):
   the far slice takes the fill's clean colour ``F`` there, and the nearer slice
   (that of the dilated ``d``) the rest, ``max(I - (1 - b) F, 0)`` at alpha ``b =
   EDGE_ALPHA``, in front: their pinhole composite is the pixel. ``"hard"`` edges
   (without fill): the pixel goes wholly to the nearer slice (``d`` dilated).
3. Hidden background (optional), per slab but the nearest: the Inpaint node extends the
   slab's own pixels (not edge pixels, not highlights: :data:`HDR_LIMIT`) outwards by
   ``D = ceil(A (d_max - d_0)) + 1`` px, ``d_0`` the slab's farthest slice (the largest
   parallax between the slab and the nearest content); the extension is kept only
   where nearer slabs cover it, under the layer of the slab's last interval's far slice.
   Its alpha is the share of the hidden background the slab is likely to cover
   (``density_px``): with ``m_s`` the slab's pixels (by their own depth) and ``b_s =
   sum_{t <= s} m_t`` the visible pixels on it or behind it, both blurred over a disk of
   :data:`DENSITY_PX`, ``(B m_s + eps) / (B b_s + eps)``, clamped to [0, 1]
   (:data:`DENSITY_EPS`). A wall's fill stays opaque (``m = b``); a wire fence's, seen
   behind a nearer strand, takes the fence's local coverage, so the wall behind it
   shows through as it does around the strand; where the window sees no visible pixel
   the Inpaint colour keeps full alpha.
4. A disk blur of radius ``r_i`` per slice: Bokeh Blur with a round Bokeh Image (both
   APIs; the radius is truncated to whole pixels, 5.x: Size in pixels, 4.x: Size in
   percent of the larger image side, at most 10 %), or on 5.x the Convolve node with an
   anti-aliased disk kernel ``clamp(r + 1/2 - |x|, 0, 1)`` built from nodes (fractional
   radii; FFT, zero padded borders). With a shaped aperture (``GroupSpec.blades``,
   ``anamorphic``: 5.x only) the Bokeh Image draws the camera's polygon (4.x: its angle
   driven from the camera, :func:`add_camera_drivers`) and the Convolve
   kernel is the polygon (or the stretched disk) built from nodes, turned over per slice
   in front of the focus for odd blades (:class:`_ApertureOps`).
5. The blurred layers of a slab summed (Math nodes), then Eq. 1 over the slabs far to
   near with Alpha Over (premultiplied): ``acc <- acc (1 - a_s) + (c_s, a_s)`` with
   ``(c_s, a_s)`` the slab's sum; output colour ``acc_rgb / acc_a`` (clamped >= 0),
   alpha 1; the second output "Alpha" is ``acc_a``, the coverage of Eq. 1. With the
   input "Film Transparent" at 1 (a render whose world is transparent: alpha 0 at
   infinity) the output is ``(acc_rgb, acc_a)`` itself, premultiplied, as Cycles' depth of
   field gives it (the normalisation would divide by a coverage that is ~0 there). Not
   normalised, a Convolve slice (zero-padded) then also fades within its blur radius of
   the frame's border; Bokeh Blur extends the border and does not.

Slices are placed from the depth of the last render (:func:`place_slices`): the
adaptive planes of :func:`mpib_validate.runtime.layers.mpi.adaptive_planes` (only where content is,
spaced for a blur-radius quantisation error of ``tolerance_px``), with the tolerance
raised until at most ``max_slices`` remain.

The numpy model follows the nodes as Blender 5.0 implements them on the CPU (float32
arithmetic, Bokeh Blur's sampled kernel and extended borders, Convolve's zero-padded
FFT, Inpaint's jump flooding and smoothing; the sources were read and each node checked
against Blender), and the 4.2-4.5 Bokeh Blur for the legacy API (the same weights, as
measured with impulses, except on the disk's rim at some radii: 4, 9, 13, 16 ... px);
the 4.x Inpaint node is a different algorithm and is not modelled.

``bpy`` is imported inside the functions only, so the package imports without it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

GROUP_NAME = "MPIB Refocus"

# --------------------------------------------------------------------------------------
# Version-dependent helpers: the compositor tree and its output come from the shared
# module (mpib_validate.runtime.blender.compat: 5.3's compositor effects, 5.0's node group, 4.x's
# scene.node_tree); the node idnames this graph needs are here.
from mpib_validate.runtime.blender.compat import (  # noqa: E402,F401
    compositor_tree, legacy_compositor_api, tree_output)


def is_legacy_api(bpy=None) -> bool:
    """True for Blender 4.2-4.5 (``scene.node_tree``, Composite node, node options as
    properties); False for 5.x (``scene.compositing_node_group``, options as sockets):
    :func:`~mpib_validate.runtime.blender.compat.legacy_compositor_api`."""
    return legacy_compositor_api()


#: Node idnames per API: (5.x, 4.2-4.5).
NODE_IDS = {
    "math": ("ShaderNodeMath", "CompositorNodeMath"),
    "separate": ("CompositorNodeSeparateColor", "CompositorNodeSeparateColor"),
    "combine": ("CompositorNodeCombineColor", "CompositorNodeCombineColor"),
    "over": ("CompositorNodeAlphaOver", "CompositorNodeAlphaOver"),
    "bokeh_image": ("CompositorNodeBokehImage", "CompositorNodeBokehImage"),
    "bokeh_blur": ("CompositorNodeBokehBlur", "CompositorNodeBokehBlur"),
    "inpaint": ("CompositorNodeInpaint", "CompositorNodeInpaint"),
    "dilate": ("CompositorNodeDilateErode", "CompositorNodeDilateErode"),
    "convolve": ("CompositorNodeConvolve", None),
    "crop": ("CompositorNodeCrop", "CompositorNodeCrop"),
    "image_coordinates": ("CompositorNodeImageCoordinates", None),
    "separate_xyz": ("ShaderNodeSeparateXYZ", None),
    "group": ("CompositorNodeGroup", "CompositorNodeGroup"),
    "render_layers": ("CompositorNodeRLayers", "CompositorNodeRLayers"),
}


def node_id(kind: str, legacy: bool) -> str:
    idname = NODE_IDS[kind][1 if legacy else 0]
    if idname is None:
        raise ValueError(f"the {kind} node does not exist in Blender 4.2-4.5")
    return idname


def set_option(node, socket: str, value, prop: str | None = None) -> None:
    """Set a node option: the input socket ``socket`` (5.x) or else the property
    ``prop`` (4.x; default: ``socket`` lower-cased with underscores)."""
    if socket in node.inputs and not node.inputs[socket].is_linked:
        node.inputs[socket].default_value = value
    else:
        setattr(node, prop or socket.lower().replace(" ", "_"), value)


def _interface_sockets(tree):
    return [item for item in tree.interface.items_tree if item.item_type == "SOCKET"]


# --------------------------------------------------------------------------------------
# The group's interface

#: Group inputs: (name, socket type, default, description). Lengths in scene units,
#: the lens in millimetres.
INPUTS = (
    ("Image", "NodeSocketColor", (0.0, 0.0, 0.0, 1.0), "All-in-focus render (Render Layers Image)"),
    ("Depth", "NodeSocketFloat", 1e10, "Depth pass (Render Layers Depth), scene units"),
    ("Focus Distance", "NodeSocketFloat", 10.0, "Planar distance in focus, scene units"),
    ("F-Stop", "NodeSocketFloat", 2.8, "Aperture f-number"),
    ("Focal Length", "NodeSocketFloat", 50.0, "Lens focal length, mm"),
    ("Sensor Width", "NodeSocketFloat", 36.0,
     "Sensor size across the image width for the camera's sensor fit, mm"),
    ("Resolution X", "NodeSocketFloat", 1920.0, "Rendered image width, pixels"),
    ("Resolution Y", "NodeSocketFloat", 1080.0, "Rendered image height, pixels"),
    ("Unit Scale", "NodeSocketFloat", 1.0,
     "Metres per unit of depth as the lens sees it: 1 for Blender renders (Cycles' depth "
     "of field ignores the scene's Unit Scale)"),
    ("Film Transparent", "NodeSocketFloat", 0.0,
     "1: the render's film is transparent; the output keeps the refocused coverage as "
     "alpha (premultiplied). 0: opaque output, colour normalised by the coverage"),
)
#: Group inputs of a group made for a shaped aperture (``GroupSpec.blades`` or
#: ``GroupSpec.anamorphic``), after :data:`INPUTS`; a disk's group has none of them.
SHAPE_INPUTS = (
    ("Aperture Rotation", "NodeSocketFloat", 0.0,
     "The camera's aperture rotation (radians, counter-clockwise on screen, as Cycles)"),
    ("Aperture Ratio", "NodeSocketFloat", 1.0,
     "The camera's anamorphic ratio (the aperture's width is divided by it, as Cycles)"),
)


def interface_inputs(spec) -> tuple:
    """The group inputs of ``spec``: :data:`INPUTS`, plus :data:`SHAPE_INPUTS` when its
    aperture is not a disk of ratio 1."""
    return INPUTS + (SHAPE_INPUTS if spec is not None and spec.shaped else ())


OUTPUTS = (
    ("Image", "NodeSocketColor", "Refocused image (normalised Eq. 1, alpha 1; with Film "
     "Transparent the premultiplied Eq. 1 and its coverage)"),
    ("Alpha", "NodeSocketFloat", "Coverage of Eq. 1 (acc_a)"),
)

#: Pixels within this many pixels of nearer content are edge pixels (see step 2).
EDGE_PX = 1
#: An edge pixel's nearer neighbour is nearer by more than this blur-radius step (px).
EDGE_JUMP_PX = 1.0
#: The share of an edge pixel given to the nearer side ("soft" edges). Measured on the
#: Blender scene suite (PSNR_ob, 8 slices): 0.5 32.25 dB on suzanne-near, 0.25 33.37, 0.1
#: 33.66, 0 33.48 (the far-side pixel's mix with the nearer colour is mostly small; a
#: larger share keeps the far surface's texture sharp on the nearer slice).
EDGE_ALPHA = 0.1
#: Smallest normaliser the final division uses (below it the colour is ~0 anyway).
NORM_FLOOR = 1e-6
#: The Bokeh Image node's fixed resolution (5.x and 4.x).
BOKEH_IMAGE_SIZE = 512
#: Pixels with a colour channel at or above this (linear radiance; the brightest diffuse
#: white under unit light is 1) are highlights or emitters: they feed no hidden-background
#: fill (the fill guesses ordinary background; Inpaint copies its nearest source pixel
#: outwards, so one emitter on an occluding edge would be smeared along the whole edge)
#: and are never split as anti-aliased edge pixels (a mix is no brighter than its parts).
HDR_LIMIT = 1.0
#: With Convolve, slices whose blur radius (at the focus the group is made for) is below
#: this use Bokeh Blur (whole-pixel radii, an effective disk of radius s + 1/2; its cost
#: grows with the radius, the Convolve FFT's is the same at any radius: Blender pads the
#: image to twice its size each way). Measured at 1920x1080 on 2 cores (5.0.1, CPU
#: compositor, 3 runs each, net of loading): Convolve 2.6 s at any radius; Bokeh Blur
#: 0.48 s at 5 px, 1.03 s at 8, 1.56 s at 10, 2.1 s at 12. Both costs grow with the pixel
#: count, so the crossover (about 13 px) holds at any resolution. On the Blender scene
#: suite the radius truncation below 12 px changed mean PSNR_ob by less than 0.01 dB
#: (threshold 4 px: 31.81 dB; 12 px: 31.81 dB).
BOKEH_BELOW_PX = 12.0
#: Radius (px) of the window that estimates a slab's coverage of the background it hides
#: (see step 3 of the module docstring); one Bokeh Blur for up to four slabs. Measured on
#: the Blender scene suite (mean PSNR_ob): 5 px 31.81 dB (fence-near 32.21); without the
#: estimate 31.53 (fence-near 29.74). The radius hardly matters (with masks that left out
#: edge pixels: 2 px 31.77, 4 px 31.80, 8 px 31.81): the estimate is local, and where
#: the window sees nothing, DENSITY_EPS keeps the Inpaint colour.
DENSITY_PX = 5
#: Where the window sees less than this fraction of visible background, the estimate falls
#: back to the Inpaint colour at full alpha (no evidence): ``(m + eps) / (b + eps)``.
DENSITY_EPS = 0.01
#: Consecutive slices whose blur radii span at most this many pixels form one slab
#: (additive split inside, as the numpy default preset's ``slab_px``).
SLAB_PX = 4.0
#: Default largest number of slices (the operator's and the bench's): each slice costs
#: one or two blurs of the whole frame. On the Blender scene suite 5 slices measured
#: PSNR_ob 31.81 dB on average, 8 slices 32.08 and 16 slices 31.79 (``mpib bench --suite
#: blender``; ``docs/blender.md``).
DEFAULT_MAX_SLICES = 5


def slabs_for(disparities, blur_parameter: float, slab_px: float = SLAB_PX) -> tuple:
    """Slab id per interval between neighbouring slices (far to near), and for the
    content on the nearest slice: consecutive ones form one slab while its disparity
    span stays within ``slab_px / A`` (a
    blur-radius span of ``slab_px`` pixels at any focus; as
    :func:`mpib_validate.runtime.layers.mpi.slab_of_groups`). ``slab_px = 0``: every interval
    alone."""
    d = np.asarray(disparities, np.float64)
    out, s, start = [], -1, 0.0
    for lo, hi in list(zip(d, d[1:])) + [(d[-1], d[-1])]:  # the last: the nearest slice
        if s < 0 or slab_px <= 0 or blur_parameter * (hi - start) > slab_px + 1e-9:
            s, start = s + 1, lo
        out.append(s)
    return tuple(out)


# --------------------------------------------------------------------------------------
# Slice placement


def slices_for_intervals(intervals, blur_parameter: float, tolerance_px: float = 0.5,
                         max_slices: int = 8) -> tuple[np.ndarray, float]:
    """Slice disparities (far to near) for content in disparity intervals.

    ``intervals``: ``[(lo, hi), ...]``, or a function of the plane step (disparity) that
    returns them (content split where a gap exceeds the step, so that gaps close as the
    tolerance grows). The planes are :func:`mpib_validate.runtime.layers.mpi.adaptive_planes` (only where
    content is, spaced for a blur-radius quantisation error of at most the tolerance);
    the tolerance is doubled, then refined by bisection to 0.1 %, until at most
    ``max_slices`` remain. If no tolerance gets there (more separate pieces of content
    than slices), the slices are spread evenly over the whole disparity range. Returns
    ``(disparities, tolerance_px_used)``.
    """
    from mpib_validate.runtime.layers.mpi import adaptive_planes, plane_spacing

    if max_slices < 1:
        raise ValueError(f"max_slices must be >= 1, got {max_slices}")
    if not blur_parameter > 0:
        raise ValueError(f"the blur parameter must be > 0, got {blur_parameter}")
    get = intervals if callable(intervals) else (lambda step, iv=list(intervals): iv)
    if not get(plane_spacing(blur_parameter, tolerance_px)):
        raise ValueError("no content to place slices on")

    def planes(tol):
        return adaptive_planes(get(plane_spacing(blur_parameter, tol)), blur_parameter, tol)

    if len(planes(tolerance_px)) <= max_slices:
        return planes(tolerance_px), float(tolerance_px)
    lo, hi = tolerance_px, 2.0 * tolerance_px
    for _ in range(40):
        if len(planes(hi)) <= max_slices:
            break
        lo, hi = hi, 2.0 * hi
    else:  # more separate pieces than slices, at any tolerance
        ends = np.array(get(plane_spacing(blur_parameter, tolerance_px)), np.float64)
        d0, d1 = float(ends.min()), float(ends.max())
        if max_slices == 1 or d1 <= d0:
            return np.array([0.5 * (d0 + d1)]), math.inf
        d = np.linspace(d0, d1, max_slices)
        return d, float(blur_parameter * (d[1] - d[0]) / 2.0)
    while hi - lo > 1e-3 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if len(planes(mid)) > max_slices else (lo, mid)
    return planes(hi), float(hi)


def place_slices(depth: np.ndarray, blur_parameter: float, tolerance_px: float = 0.5,
                 max_slices: int = 8, far_limit: float | None = None) -> tuple[np.ndarray, float]:
    """Slice disparities (far to near) for the depth present in a render: the content
    intervals of its disparity ``1/Z`` (gaps wider than one plane step split them; depth
    at or beyond ``far_limit`` is at infinity) through :func:`slices_for_intervals`."""
    from mpib_validate.runtime.layers.passes import DEFAULT_FAR_LIMIT, content_intervals, depth_to_disparity

    D = depth_to_disparity(depth, DEFAULT_FAR_LIMIT if far_limit is None else far_limit)
    values = np.unique(np.round(D, 12))
    return slices_for_intervals(lambda step: content_intervals(values, step), blur_parameter,
                                tolerance_px, max_slices)


# --------------------------------------------------------------------------------------
# The description


@dataclass(frozen=True)
class Ref:
    """Output ``out`` of the node named ``node``."""

    node: str
    out: int = 0


@dataclass(frozen=True)
class GroupIn:
    """The group input socket named ``name``."""

    name: str


@dataclass(frozen=True)
class Op:
    """One node of the graph: its abstract kind, arguments (:class:`Ref`,
    :class:`GroupIn` or a constant) and static options."""

    name: str
    kind: str
    args: tuple = ()
    params: tuple = ()  # (key, value) pairs

    def param(self, key, default=None):
        return dict(self.params).get(key, default)


#: Abstract kinds: arguments, and what the node computes (images are premultiplied RGBA).
KINDS = {
    "math": "(a, b): Math node, params op and clamp (float32, DIVIDE by 0 gives 0)",
    "separate": "(image,): R, G, B, A",
    "combine": "(r, g, b, a): an image",
    "over": "(background, foreground): fg + bg (1 - clamp(fg.a))",
    "bokeh_disk": "(): round Bokeh Image (512 x 512, Roundness 1)",
    "bokeh_blur": "(image, bokeh, radius_px): constant-size Bokeh Blur, radius truncated",
    "disk_kernel": "(radius_px,): K x K kernel clamp(r + 1/2 - |x|, 0, 1), param size K (5.x)",
    "bokeh_polygon": "(angle,): Bokeh Image of param flaps (Roundness 0, no catadioptric, "
                     "no colour shift), Angle linked (5.x); 4.x: a driver on the angle "
                     "property, base - rotation (+ pi where the slice at disparity param "
                     "turn_at >= 0 is in front of the focus)",
    "kernel_coords": "(): (dx, dy) = pixel index - size // 2 on a size x size image, y up, "
                     "param size (5.x); math on them builds a Convolve kernel",
    "convolve": "(image, kernel): Convolve, kernel normalised, zero-padded FFT (5.x)",
    "inpaint": "(image,): Inpaint, param distance (px)",
    "dilate": "(value,): Dilate/Erode in Step mode, param size n: max over (2n+1)^2",
}


@dataclass(frozen=True)
class GroupSpec:
    """What fixes the group's structure (a change regenerates it).

    Attributes:
        disparities: slice disparities, far to near (1/scene-unit).
        fill: ``"inpaint"`` (hidden background behind each slice) or ``"off"``.
        blur: ``"bokeh"`` (Bokeh Blur, both APIs) or ``"convolve"`` (5.x only).
        fill_px: Inpaint distance per slice (pixels; ignored without fill).
        kernel_radius_px: half size of the Convolve kernel image (its size is
            ``2 k + 3``); slice radii above ``k + 1/2`` are cut to that square.
        edge: how anti-aliased edge pixels are shared (see step 2 of the module
            docstring): ``"soft"`` (needs the fill) or ``"hard"``.
        edge_jump: disparity step to nearer content that makes a pixel an edge pixel
            (``"soft"``; :data:`EDGE_JUMP_PX` / A).
        slabs: slab id per interval ``[d_k, d_k+1)`` (``k = 0..N-2``) and, last, for
            the content at or nearer than the nearest slice (``k = N-1``); consecutive
            ids from 0; default each alone. A pixel is shared additively between the
            two slices of its interval (``1 - u`` and ``u``); the blurred layers of a
            slab are summed, slabs are composited with "over" (a slice bordering two
            slabs has a layer in each).
        bokeh_slices: with ``blur="convolve"``, the slices blurred by Bokeh Blur instead
            (small radii: its cost grows with the radius, the FFT's does not).
        density_px: with the fill, the radius of the window that estimates the share of
            the hidden background each slab covers (0: the Inpaint colour at full alpha;
            see step 3 of the module docstring).
        blades: the camera's aperture blades the group draws (0: a disk; 3 to 16): fixed
            when the group is made (a driver cannot add nodes); the rotation is the
            driven input "Aperture Rotation" (see step 4 of the module docstring).
        anamorphic: the group stretches its kernels by the driven input "Aperture
            Ratio" (Convolve only: Bokeh Blur draws a square Bokeh Image).
    """

    disparities: tuple
    fill: str = "inpaint"
    blur: str = "bokeh"
    fill_px: tuple = ()
    kernel_radius_px: int = 0
    edge: str = "soft"
    edge_jump: float = 0.0
    slabs: tuple = ()
    bokeh_slices: tuple = ()
    density_px: int = 0
    blades: int = 0
    anamorphic: bool = False

    @property
    def shaped(self) -> bool:
        """The aperture is not a disk of ratio 1 (the group has :data:`SHAPE_INPUTS`)."""
        return self.blades > 0 or self.anamorphic

    def __post_init__(self):
        d = tuple(float(x) for x in self.disparities)
        if not d:
            raise ValueError("a node group needs at least one slice")
        if any(b <= a for a, b in zip(d, d[1:])):
            raise ValueError(f"slice disparities must increase (far to near): {d}")
        if self.fill not in ("inpaint", "off"):
            raise ValueError(f"fill must be 'inpaint' or 'off', got {self.fill!r}")
        if self.blur not in ("bokeh", "convolve"):
            raise ValueError(f"blur must be 'bokeh' or 'convolve', got {self.blur!r}")
        if self.edge not in ("soft", "hard"):
            raise ValueError(f"edge must be 'soft' or 'hard', got {self.edge!r}")
        object.__setattr__(self, "edge_jump", float(self.edge_jump))
        object.__setattr__(self, "disparities", d)
        fill = tuple(int(v) for v in self.fill_px) or (0,) * len(d)
        if len(fill) != len(d):
            raise ValueError(f"{len(fill)} fill distances for {len(d)} slices")
        object.__setattr__(self, "fill_px", fill)
        slabs = tuple(int(v) for v in self.slabs) or tuple(range(len(d)))
        if len(slabs) != len(d) or slabs[0] != 0 or any(
                b - a not in (0, 1) for a, b in zip(slabs, slabs[1:])):
            raise ValueError(f"slabs must number consecutive runs of slices 0, 1, ...: {slabs}")
        object.__setattr__(self, "slabs", slabs)
        bs = tuple(sorted({int(i) for i in self.bokeh_slices}))
        if any(not 0 <= i < len(d) for i in bs):
            raise ValueError(f"bokeh_slices out of range: {bs}")
        object.__setattr__(self, "bokeh_slices", bs)
        if int(self.density_px) < 0:
            raise ValueError(f"density_px must be >= 0, got {self.density_px}")
        object.__setattr__(self, "density_px", int(self.density_px))
        b = int(self.blades)
        if not (b == 0 or 3 <= b <= MAX_BLADES):
            raise ValueError(f"blades must be 0 (a disk) or 3 to {MAX_BLADES}, got {b}")
        object.__setattr__(self, "blades", b)
        object.__setattr__(self, "anamorphic", bool(self.anamorphic))
        if self.anamorphic and (self.blur == "bokeh" or self.bokeh_slices):
            raise ValueError("Bokeh Blur cannot draw an anamorphic aperture ratio (its Bokeh "
                             "Image is square): blur 'convolve' without bokeh_slices")


def fill_distances(disparities, blur_parameter: float, cap: int = 256) -> tuple:
    """Inpaint distance per slice: ``ceil(A (d_max - d_i)) + 1`` px (the largest parallax
    between the slice and the nearest content), at most ``cap``."""
    d = np.asarray(disparities, np.float64)
    return tuple(int(min(cap, math.ceil(blur_parameter * (d[-1] - x)) + 1)) for x in d)


#: Most aperture blades (Blender's ``aperture_blades``; the Bokeh Image takes up to 24).
MAX_BLADES = 16

#: Largest Convolve kernel half size: the kernel image is cut from the 512 px Bokeh Image.
KERNEL_CAP = (BOKEH_IMAGE_SIZE - 3) // 2


def make_spec(disparities, blur_parameter: float, *, fill: str = "inpaint",
              blur: str = "bokeh", max_radius_px: float | None = None,
              slab_px: float = SLAB_PX, focus_disparity: float | None = None,
              bokeh_below_px: float = BOKEH_BELOW_PX,
              density_px: int = DENSITY_PX, aperture=None) -> GroupSpec:
    """The structure for given slices: fill distances by :func:`fill_distances` (each
    slab's fill weighted by its coverage estimated over ``density_px``), and
    (Convolve) a kernel for radii up to ``max_radius_px`` (default ``A d_max``, the
    largest radius of a focus at infinity or anywhere within the slices), at most
    :data:`KERNEL_CAP`. The kernel's size does not change the Convolve node's cost (its
    FFT pads the image by its own size). With Convolve and ``focus_disparity`` (one, or
    one per frame of an animation), the slices whose radius stays below
    ``bokeh_below_px`` at every such focus use Bokeh Blur (cheaper there); ``slab_px``:
    :func:`slabs_for`. ``aperture``: the camera's
    :class:`~mpib_validate.runtime.camera.Aperture` (or one per frame: the same blades;
    any ratio other than 1 makes the group anamorphic, its kernels sized for the largest
    extent ``max(1, 1/ratio)``, every slice on Convolve); default a disk."""
    d = np.asarray(disparities, np.float64)
    aps = [] if aperture is None else (
        list(aperture) if isinstance(aperture, (list, tuple)) else [aperture])
    blades = {a.blades for a in aps} or {0}
    if len(blades) > 1:
        raise ValueError(f"the aperture's blades change over the frames ({sorted(blades)}): "
                         f"the node group draws one blade count")
    anamorphic = any(a.ratio != 1.0 for a in aps)
    extent = max([a.extent for a in aps] + [1.0])
    if max_radius_px is None:
        max_radius_px = blur_parameter * float(max(d[-1], d[-1] - d[0]))
    k = (min(KERNEL_CAP, int(math.ceil(max_radius_px * extent)) + 1) if blur == "convolve"
         else 0)
    bokeh_slices = ()
    if blur == "convolve" and focus_disparity is not None and not anamorphic:  # one focus or several (frames)
        f = np.atleast_1d(np.asarray(focus_disparity, np.float64))
        r = blur_parameter * np.abs(d[:, None] - f[None, :]).max(axis=1)
        bokeh_slices = tuple(int(i) for i in np.flatnonzero(r < bokeh_below_px))
    return GroupSpec(tuple(d), fill, blur, fill_distances(d, blur_parameter), k,
                     edge="soft" if fill == "inpaint" else "hard",
                     edge_jump=EDGE_JUMP_PX / blur_parameter,
                     slabs=slabs_for(d, blur_parameter, slab_px), bokeh_slices=bokeh_slices,
                     density_px=density_px if fill == "inpaint" else 0,
                     blades=blades.pop(), anamorphic=anamorphic)


def spec_from_render(depth: np.ndarray, blur_parameter: float, *,
                     max_slices: int = DEFAULT_MAX_SLICES,
                     tolerance_px: float = 0.5, fill: str = "inpaint", blur: str = "bokeh",
                     max_radius_px: float | None = None, slab_px: float = SLAB_PX,
                     focus_disparity: float | None = None,
                     bokeh_below_px: float = BOKEH_BELOW_PX,
                     density_px: int = DENSITY_PX, aperture=None) -> GroupSpec:
    """The structure for a render's depth: slices by :func:`place_slices`, the rest by
    :func:`make_spec`."""
    d, _ = place_slices(depth, blur_parameter, tolerance_px, max_slices)
    return make_spec(d, blur_parameter, fill=fill, blur=blur, max_radius_px=max_radius_px,
                     slab_px=slab_px, focus_disparity=focus_disparity,
                     bokeh_below_px=bokeh_below_px, density_px=density_px,
                     aperture=aperture)


class _Builder:
    def __init__(self):
        self.ops: list[Op] = []
        self.names: set = set()

    def add(self, name, kind, *args, **params) -> Ref:
        if name in self.names:  # a second node of one name would shadow the first
            raise ValueError(f"node name {name!r} used twice")
        self.names.add(name)
        self.ops.append(Op(name, kind, tuple(args), tuple(sorted(params.items()))))
        return Ref(name)

    def math(self, name, op, a, b=0.0, clamp=False) -> Ref:
        return self.add(name, "math", a, b, op=op, clamp=bool(clamp))


@dataclass(frozen=True)
class Graph:
    spec: GroupSpec
    ops: tuple
    outputs: tuple  # (group output name, Ref)


def describe(spec: GroupSpec) -> Graph:
    """The node graph of :class:`GroupSpec` as data (see the module docstring)."""
    g = _Builder()
    d = spec.disparities
    n = len(d)
    slab = spec.slabs  # per interval [d_k, d_k+1)
    first = {}  # slab id -> its farthest interval
    last = {}  # slab id -> its nearest interval
    for i, s in enumerate(slab):
        first.setdefault(s, i)
        last[s] = i
    # 1. blur parameter and focus
    fl = GroupIn("Focal Length")
    t1 = g.math("lens_m", "MULTIPLY", fl, 1e-3)
    t2 = g.math("unit_x2", "MULTIPLY", GroupIn("Unit Scale"), 2.0)
    t3 = g.math("unit_x2N", "MULTIPLY", t2, GroupIn("F-Stop"))
    R = g.math("aperture_radius", "DIVIDE", t1, t3)
    t4 = g.math("lens_per_sensor", "DIVIDE", fl, GroupIn("Sensor Width"))
    fpx = g.math("focal_px", "MULTIPLY", t4, GroupIn("Resolution X"))
    A = g.math("blur_parameter", "MULTIPLY", R, fpx)
    df = g.math("focus_disparity", "DIVIDE", 1.0, GroupIn("Focus Distance"))
    radius = []
    for i, di in enumerate(d):
        e = g.math(f"s{i}.offset", "SUBTRACT", di, df)
        ab = g.math(f"s{i}.abs", "ABSOLUTE", e)
        radius.append(g.math(f"s{i}.radius", "MULTIPLY", A, ab))
    # 2. disparity, the split between slices
    g.add("image", "separate", GroupIn("Image"))
    ch = [Ref("image", k) for k in range(4)]
    alpha = ch[3]
    raw = g.math("disparity_raw", "DIVIDE", 1.0, GroupIn("Depth"))
    dil = g.add("disparity_dilated", "dilate", raw, size=EDGE_PX)
    soft = spec.edge == "soft" and spec.fill == "inpaint" and len(first) >= 2
    own_d = raw if soft else dil  # "hard": edge pixels go wholly to the nearer slice

    def split(tag, dv):
        lt_, ge_ = {}, {}
        for k in range(1, n):
            lt_[k] = g.math(f"{tag}lt{k}", "LESS_THAN", dv, d[k])  # d < d_k
            ge_[k] = g.math(f"{tag}ge{k}", "SUBTRACT", 1.0, lt_[k])  # d >= d_k
        own_ = {}  # d in [d_i, d_{i+1}): the slice whose far role the pixel is in
        for i in range(n):
            own_[i] = (1.0 if n == 1 else lt_[1] if i == 0 else ge_[n - 1] if i == n - 1
                       else g.math(f"{tag}own{i}", "MULTIPLY", ge_[i], lt_[i + 1]))
        return lt_, ge_, own_

    u = {}
    for k in range(n - 1):
        off = g.math(f"u{k}.offset", "SUBTRACT", own_d, d[k])
        u[k] = g.math(f"u{k}", "MULTIPLY", off, 1.0 / (d[k + 1] - d[k]), clamp=True)
    lt, ge, own = split("", own_d)

    def scaled(name, image_channels, factor):
        parts = [g.math(f"{name}.{c}", "MULTIPLY", image_channels[j], factor)
                 for j, c in enumerate("rgba")]
        return g.add(name, "combine", *parts)

    def in_range(tag, ge_, lt_, i0, i1):
        """d in [d_i0, d_i1) (i1 = n: no upper end)."""
        lo = ge_.get(i0, 1.0) if i0 > 0 else 1.0
        hi = lt_[i1] if i1 < n else 1.0
        if isinstance(lo, float):
            return hi
        if isinstance(hi, float):
            return lo
        return g.math(tag, "MULTIPLY", lo, hi)

    # HDR guard: pixels brighter than HDR_LIMIT (emitters, highlights) feed no fill and
    # are never split as edge pixels (an anti-aliased mix is not brighter than its parts)
    hdr_max = g.math("hdr.max", "MAXIMUM", g.math("hdr.max_rg", "MAXIMUM", ch[0], ch[1]), ch[2])
    ldr = g.math("hdr.ldr", "LESS_THAN", hdr_max, HDR_LIMIT)

    if soft:  # the edge ring: nearer content in a nearer slab within a pixel, by more
        _, dil_ge, own_near = split("dil.", dil)  # than the jump
        gap = g.math("edge.gap", "SUBTRACT", dil, raw)
        ring = g.math("edge.jump", "GREATER_THAN", gap, spec.edge_jump)
        cross = None
        for s in sorted(first)[1:]:
            b = first[s]
            c = g.math(f"edge.cross{s}", "SUBTRACT", dil_ge[b], ge[b])
            cross = c if cross is None else g.math(f"edge.crosses{s}", "MAXIMUM", cross, c)
        ring = g.math("edge.ring_slab", "MULTIPLY", ring, cross)
        ring = g.math("edge.ring", "MULTIPLY", ring, ldr)
    # 3. hidden background per slab: its own pixels (not the edge ring) extended, kept
    # where content of a nearer slab covers it, on the slab's nearest slice
    filled = {}  # slab id -> fill channels
    masks = {}  # slab id -> its pixels (by their own depth: edge pixels and highlights too)
    bokeh_ref = []

    def bokeh_image():  # one round Bokeh Image for every Bokeh Blur
        if not bokeh_ref:
            bokeh_ref.append(g.add("bokeh", "bokeh_disk"))
        return bokeh_ref[0]
    nslabs = len(first)

    def slab_range(tag, ge_, lt_, s):  # d within the intervals of slab s
        return in_range(tag, ge_, lt_, first[s], last[s] + 1 if s < nslabs - 1 else n)

    for s in sorted(first):
        i0, e = first[s], last[s]
        if not (spec.fill == "inpaint" and s < nslabs - 1 and spec.fill_px[i0] > 0):
            continue
        mask = slab_range(f"slab{s}.own", ge, lt, s)
        masks[s] = mask
        if soft:
            mask = g.math(f"slab{s}.own_core", "MULTIPLY", mask,
                          g.math(f"slab{s}.not_ring", "SUBTRACT", 1.0, ring))
        mask = g.math(f"slab{s}.src_mask", "MULTIPLY", mask, ldr)
        src = scaled(f"slab{s}.fill_src", ch, mask)
        g.add(f"slab{s}.filled", "separate",
              g.add(f"slab{s}.inpaint", "inpaint", src, distance=int(spec.fill_px[i0])))
        filled[s] = [Ref(f"slab{s}.filled", k) for k in range(4)]
    if filled and spec.density_px > 0:
        # the share of the hidden background a slab covers: among the visible pixels near
        # a hidden one that lie on the slab or behind it, the fraction on the slab (a wire
        # fence's fill stays sparse, a wall's is opaque); all masks blurred at once, four
        # to a Bokeh Blur
        order = sorted(filled)
        blurred = {}
        for j in range(0, len(order), 4):
            group = order[j:j + 4]
            chans = [masks[t] for t in group] + [0.0] * (4 - len(group))
            src = g.add(f"density{j // 4}.src", "combine", *chans)
            g.add(f"density{j // 4}", "separate",
                  g.add(f"density{j // 4}.blur", "bokeh_blur", src, bokeh_image(),
                        float(spec.density_px)))
            blurred.update({t: Ref(f"density{j // 4}", k) for k, t in enumerate(group)})
        behind = None
        for t in order:
            behind = blurred[t] if behind is None else g.math(
                f"slab{t}.behind", "ADD", behind, blurred[t])
            num = g.math(f"slab{t}.density_num", "ADD", blurred[t], DENSITY_EPS)
            den = g.math(f"slab{t}.density_den", "ADD", behind, DENSITY_EPS)
            share = g.math(f"slab{t}.density", "DIVIDE", num, den, clamp=True)
            filled[t] = [g.math(f"slab{t}.fill_share.{c}", "MULTIPLY", filled[t][k], share)
                         for k, c in enumerate("rgba")]
    colour = ch
    if soft:
        # the far side of an edge pixel: its own slab's fill (clean colour); the near side
        # the rest, max(I - (1 - b) F, 0) at alpha b, in the nearer (dilated) slice
        fc = None
        for s in filled:
            part = scaled(f"edge.fill{s}", filled[s], slab_range(f"edge.own{s}", ge, lt, s))
            fc = part if fc is None else g.add(f"edge.fills{s}", "over", fc, part)
        g.add("edge.fill", "separate", fc)
        fcc = [Ref("edge.fill", k) for k in range(4)]
        ring_f = g.math("edge.ring_filled", "MULTIPLY", ring, fcc[3])
        keep = g.math("edge.keep", "SUBTRACT", 1.0, ring_f)
        cols = []
        for k, c in enumerate("rgb"):
            mine = g.math(f"edge.own.{c}", "MULTIPLY", ch[k], keep)
            theirs = g.math(f"edge.far.{c}", "MULTIPLY", fcc[k], ring_f)
            cols.append(g.math(f"edge.colour.{c}", "ADD", mine, theirs))
        colour = cols + [alpha]
        near = []
        for k, c in enumerate("rgb"):
            far_part = g.math(f"edge.farpart.{c}", "MULTIPLY", fcc[k], 1.0 - EDGE_ALPHA)
            rest = g.math(f"edge.rest.{c}", "SUBTRACT", ch[k], far_part)
            pos = g.math(f"edge.rest+.{c}", "MAXIMUM", rest, 0.0)
            near.append(g.math(f"edge.near.{c}", "MULTIPLY", pos, ring_f))
        near.append(g.math("edge.near.a", "MULTIPLY", ring_f, EDGE_ALPHA))

    lens = _ApertureOps(g, spec, radius) if spec.shaped else None
    bokeh = (bokeh_image() if (spec.blur == "bokeh" or spec.bokeh_slices) and lens is None
             else None)
    acc = None

    def blur(i, name, layer):  # 4. the lens blur at slice i's radius
        if spec.blur == "bokeh" or i in spec.bokeh_slices:
            b = bokeh if lens is None else lens.bokeh(i)
            return g.add(f"{name}.blur", "bokeh_blur", layer, b, radius[i])
        if lens is not None:
            return g.add(f"{name}.blur", "convolve", layer, lens.kernel(i, name))
        kern = g.add(f"{name}.kernel", "disk_kernel", radius[i],
                     size=2 * int(spec.kernel_radius_px) + 3)
        return g.add(f"{name}.blur", "convolve", layer, kern)

    for s in sorted(first):  # additive shares of the slab's intervals, per slice
        k0, k1 = first[s], last[s]
        slab_sum = None
        for i in range(k0, min(k1 + 1, n - 1) + 1):
            name = f"s{i}.L{s}"
            parts = []
            if i - 1 >= k0:  # near share of interval i-1: u_{i-1} on [d_{i-1}, d_i)
                whole = i == n - 1 and k1 == n - 1  # the nearest slice's own content too
                parts.append(u[i - 1] if whole else
                             g.math(f"{name}.near", "MULTIPLY", u[i - 1], lt[i]))
            if i <= min(k1, n - 2):  # far share of interval i: 1 - u_i on [d_i, d_{i+1})
                one_u = g.math(f"{name}.1-u", "SUBTRACT", 1.0, u[i])
                parts.append(one_u if i == 0 else
                             g.math(f"{name}.far", "MULTIPLY", one_u, ge[i]))
            if i == n - 1 and k0 == n - 1:  # the nearest slice's content alone
                parts.append(1.0 if n == 1 else ge[n - 1])
            factor = (parts[0] if len(parts) == 1 else
                      g.math(f"{name}.factor", "ADD", parts[0], parts[1]))
            layer = scaled(f"s{i}.layer{s}", colour, factor)
            if i == k1 and s in filled:  # hidden background under nearer slabs
                fill = scaled(f"{name}.fill", filled[s], ge[k1 + 1])
                layer = g.add(f"{name}.with_fill", "over", fill, layer)
            if soft and i >= 1 and k0 <= i <= k1:  # the near side of edge pixels, in front
                edge = scaled(f"{name}.edge", near, own_near[i])
                layer = g.add(f"{name}.with_edge", "over", layer, edge)
            blurred = blur(i, name, layer)
            # 5. the layers of a slab summed; slabs composited far to near (Eq. 1)
            if slab_sum is None:
                slab_sum = blurred
            else:
                g.add(f"{name}.sum_a", "separate", slab_sum)
                g.add(f"{name}.sum_b", "separate", blurred)
                adds = [g.math(f"{name}.sum.{c}", "ADD", Ref(f"{name}.sum_a", k),
                               Ref(f"{name}.sum_b", k)) for k, c in enumerate("rgba")]
                slab_sum = g.add(f"{name}.sum", "combine", *adds)
        acc = slab_sum if acc is None else g.add(f"acc{s}", "over", acc, slab_sum)
    g.add("acc", "separate", acc)
    a_acc = Ref("acc", 3)
    # opaque film: normalised colour, alpha 1; transparent film (t = 1): the premultiplied
    # colour and coverage as they are, den = 1 + (1 - t) (max(acc_a, floor) - 1)
    t = GroupIn("Film Transparent")
    den = g.math("norm", "MAXIMUM", a_acc, NORM_FLOOR)
    keep = g.math("norm.opaque", "SUBTRACT", 1.0, t)
    den = g.math("norm.film", "ADD", g.math("norm.excess", "MULTIPLY", keep,
                                            g.math("norm-1", "SUBTRACT", den, 1.0)), 1.0)
    rgb = []
    for k, c in enumerate("rgb"):
        q = g.math(f"out.{c}/a", "DIVIDE", Ref("acc", k), den)
        rgb.append(g.math(f"out.{c}", "MAXIMUM", q, 0.0))
    cov = g.math("coverage", "MAXIMUM", a_acc, 0.0, clamp=True)
    alpha = g.math("out.a", "ADD", g.math("out.a-1", "MULTIPLY", t,
                                          g.math("coverage-1", "SUBTRACT", cov, 1.0)), 1.0)
    out = g.add("out", "combine", *rgb, alpha)
    return Graph(spec, tuple(g.ops), (("Image", out), ("Alpha", cov)))


class _ApertureOps:
    """The lens blur's ops for a shaped aperture (``spec.shaped``; step 4 of the module
    docstring, the conventions of docs/aperture.md), made once and shared by the slices.

    With ``n = spec.blades``, rotation ``theta`` ("Aperture Rotation") and ratio ``q``
    ("Aperture Ratio"): Cycles' aperture ``P`` (y up, as on screen) has its corners at
    ``theta + (2k + 1) pi / n`` on the unit circle, its edge normals at ``theta + 2 pi k /
    n`` (apothem ``cos(pi / n)``), and its x divided by ``q``. A point behind the focus
    (slice offset ``d_i - d_f < 0``) spreads into ``P`` scaled by the radius, one in front
    into ``-P``.

    - Bokeh Blur spreads a point into its Bokeh Image as drawn (y up), whose corners
      lie at ``pi/2 + 2 pi (k - 1) / n - angle`` (the Bokeh Image turns clockwise with
      Angle): ``angle = pi/2 - pi/n - theta`` gives ``P``, plus ``pi`` gives ``-P`` (the
      same polygon for even ``n``: one Bokeh Image for every slice; for odd ``n`` one per
      slice, its Angle switched by the slice's side of the focus). No ratio (square
      image).
    - Convolve correlates (``out(p) = sum_q K(q) I(p + q)``, ``q`` y up), so the kernel
      of a slice behind the focus is ``-P`` and in front ``P``: with ``(x, y)`` the kernel
      pixel's offset, ``x`` times ``q``, and ``m_k = x cos t_k + y sin t_k`` (``t_k =
      theta + 2 pi k / n``), ``K = clamp(r cos(pi/n) + 1/2 - M, 0, 1)``, ``M = max_k m_k``
      in front, ``max_k (-m_k)`` behind (odd ``n``; the same for even ``n``): the polygon
      of circumradius ``r`` with a one-pixel ramp across its edges (``1/q`` px wide
      across x-facing edges when stretched). A disk: ``clamp(r + 1/2 - |(q x, y)|, 0,
      1)`` (the disk kernel of ratio 1).
    """

    def __init__(self, g: _Builder, spec: GroupSpec, radius):
        self.g, self.spec, self.radius = g, spec, radius
        self.n = spec.blades
        self._bokeh = {}
        self._conv = None
        self._made = {}  # (what, slice) -> Ref: a slice with a layer in two slabs shares them

    def near(self, i):  # 1 for a slice in front of the focus (d_i > d_f), else 0
        key = ("near", i)
        if key not in self._made:
            self._made[key] = self.g.math(f"s{i}.near", "GREATER_THAN", Ref(f"s{i}.offset"), 0.0)
        return self._made[key]

    def bokeh(self, i):
        g, n = self.g, self.n
        if n == 0:
            raise ValueError("Bokeh Blur draws no anamorphic disk (the Bokeh Image is square)")
        if "angle" not in self._bokeh:
            self._bokeh["angle"] = g.math("aperture.bokeh_angle", "SUBTRACT",
                                          math.pi / 2 - math.pi / n,
                                          GroupIn("Aperture Rotation"))
        if n % 2 == 0:
            if "even" not in self._bokeh:
                self._bokeh["even"] = g.add("aperture.bokeh", "bokeh_polygon",
                                            self._bokeh["angle"], flaps=n,
                                            base=math.pi / 2 - math.pi / n, turn_at=-1.0)
            return self._bokeh["even"]
        if ("bokeh", i) not in self._made:
            turn = g.math(f"s{i}.bokeh_turn", "MULTIPLY", self.near(i), math.pi)
            angle = g.math(f"s{i}.bokeh_angle", "ADD", self._bokeh["angle"], turn)
            self._made[("bokeh", i)] = g.add(f"s{i}.bokeh", "bokeh_polygon", angle, flaps=n,
                                             base=math.pi / 2 - math.pi / n,
                                             turn_at=float(self.spec.disparities[i]))
        return self._made[("bokeh", i)]

    def _shared(self):
        if self._conv is not None:
            return self._conv
        g, n, spec = self.g, self.n, self.spec
        size = 2 * int(spec.kernel_radius_px) + 3
        g.add("kernel.pixel", "kernel_coords", size=size)
        c = float(size // 2)
        x = g.math("kernel.x", "SUBTRACT", Ref("kernel.pixel", 0), c)
        y = g.math("kernel.y", "SUBTRACT", Ref("kernel.pixel", 1), c)
        if spec.anamorphic:
            x = g.math("kernel.x_ratio", "MULTIPLY", x, GroupIn("Aperture Ratio"))
        if n == 0:
            r2 = g.math("kernel.r2", "ADD", g.math("kernel.x2", "MULTIPLY", x, x),
                        g.math("kernel.y2", "MULTIPLY", y, y))
            self._conv = {"distance": g.math("kernel.distance", "SQRT", r2)}
            return self._conv
        proj = []
        for k in range(n):
            t = g.math(f"kernel.t{k}", "ADD", GroupIn("Aperture Rotation"), 2 * math.pi * k / n)
            cx = g.math(f"kernel.x_cos{k}", "MULTIPLY", x, g.math(f"kernel.cos{k}", "COSINE", t))
            sy = g.math(f"kernel.y_sin{k}", "MULTIPLY", y, g.math(f"kernel.sin{k}", "SINE", t))
            proj.append(g.math(f"kernel.m{k}", "ADD", cx, sy))
        hi, lo = proj[0], proj[0]
        for k in range(1, n):
            hi = g.math(f"kernel.max{k}", "MAXIMUM", hi, proj[k])
            if n % 2:
                lo = g.math(f"kernel.min{k}", "MINIMUM", lo, proj[k])
        self._conv = {"front": hi}
        if n % 2:
            back = g.math("kernel.back", "MULTIPLY", lo, -1.0)
            self._conv.update(back=back, gap=g.math("kernel.gap", "SUBTRACT", hi, back))
        return self._conv

    def kernel(self, i, name=None):
        key = ("kernel", i)
        if key in self._made:
            return self._made[key]
        g, n = self.g, self.n
        sh = self._shared()
        r = self.radius[i]
        if n == 0:
            rp = g.math(f"s{i}.kernel.r+0.5", "ADD", r, 0.5)
            k = g.math(f"s{i}.kernel", "SUBTRACT", rp, sh["distance"], clamp=True)
        else:
            if n % 2:  # behind the focus -P, in front P
                pick = g.math(f"s{i}.kernel.pick", "MULTIPLY", sh["gap"], self.near(i))
                m = g.math(f"s{i}.kernel.m", "ADD", sh["back"], pick)
            else:
                m = sh["front"]
            a = g.math(f"s{i}.kernel.apothem", "MULTIPLY", r, math.cos(math.pi / n))
            edge = g.math(f"s{i}.kernel.edge", "ADD", a, 0.5)
            k = g.math(f"s{i}.kernel", "SUBTRACT", edge, m, clamp=True)
        self._made[key] = k
        return k


# --------------------------------------------------------------------------------------
# The numpy model of the same nodes

_F = np.float32


def _math(op: str, a, b, clamp: bool):
    a = np.asarray(a, _F)
    b = np.asarray(b, _F)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if op == "ADD":
            r = a + b
        elif op == "SUBTRACT":
            r = a - b
        elif op == "MULTIPLY":
            r = a * b
        elif op == "DIVIDE":
            r = np.where(b == 0, _F(0), a / np.where(b == 0, _F(1), b))
        elif op == "ABSOLUTE":
            r = np.abs(a)
        elif op == "LESS_THAN":
            r = (a < b).astype(_F)
        elif op == "GREATER_THAN":
            r = (a > b).astype(_F)
        elif op == "MAXIMUM":
            r = np.maximum(a, b)
        elif op == "MINIMUM":
            r = np.minimum(a, b)
        elif op == "SQRT":
            r = np.where(a > 0, np.sqrt(np.maximum(a, 0)), _F(0))
        elif op == "FLOOR":
            r = np.floor(a)
        elif op == "SINE":
            r = np.sin(a)
        elif op == "COSINE":
            r = np.cos(a)
        else:
            raise ValueError(f"math op {op!r} is not modelled")
    r = np.asarray(r, _F)
    return np.clip(r, _F(0), _F(1)) if clamp else r


def bokeh_disk_image(size: int = BOKEH_IMAGE_SIZE) -> np.ndarray:
    """The round Bokeh Image (Roundness 1, no catadioptric, no shift), one channel
    ``(size, size)`` with row 0 at the bottom: 1 inside the circle of radius ``size/2``
    about the centre (texel centres at ``texel + 1/2``), ``R - dist`` within a pixel of
    its edge, 0 outside."""
    R = _F(size / 2.0)
    t = np.arange(size, dtype=_F) + _F(0.5) - R
    dist = np.sqrt(t[None, :] ** 2 + t[:, None] ** 2).astype(_F)
    v = np.where(dist > R, _F(0), np.where(R - dist < 1, R - dist, _F(1)))
    return v.astype(_F)


def bokeh_polygon_image(flaps: int, angle: float, size: int = BOKEH_IMAGE_SIZE,
                        legacy: bool = False) -> np.ndarray:
    """The Bokeh Image of ``flaps`` sides at ``angle`` (radians; Roundness 0, no
    catadioptric, no colour shift), one channel ``(size, size)``, row 0 at the bottom, as
    Blender 5.0 computes it on the CPU (``compositor/cached_resources/intern/
    bokeh_kernel.cc``, float32): corners on the circle of radius ``size/2`` about the
    centre at ``pi/2 + e (k - 1) - angle`` (``e = 2 pi / flaps``: clockwise as Angle
    grows, a corner straight up at 0); a texel at ``p`` (centre ``texel + 1/2``) is 0
    outside, ``|F| - |p|`` within a pixel of the edge (``F`` the foot of ``p`` on its
    edge's line), else 1. ``legacy``: Blender 4.2-4.5's (``COM_BokehImageOperation.cc``):
    the same polygon, texels sampled at their corners (``texel - size/2``), corners found
    by their bearing from +y (``atan2(x, y)``), the edge itself inside."""
    if legacy:
        return _bokeh_polygon_image_legacy(int(flaps), angle, size)
    n = int(flaps)
    ext = _F(2.0 * math.pi / n)
    rot = _F(_F(angle) - _F(math.pi / 2.0 - float(ext)))
    R = _F(size / 2.0)
    t = np.arange(size, dtype=_F) + _F(0.5) - R
    px, py = np.broadcast_to(t[None, :], (size, size)), np.broadcast_to(t[:, None], (size, size))
    two_pi = _F(2.0 * math.pi)
    a = (np.arctan2(py, px) + rot).astype(_F)
    a = (a - two_pi * np.floor(a / two_pi)).astype(_F)
    k = (a / ext).astype(np.int64).astype(_F)

    def vertex(j):
        ang = (ext * j - rot).astype(_F)
        return np.cos(ang).astype(_F) * R, np.sin(ang).astype(_F) * R

    x1, y1 = vertex(k)
    x2, y2 = vertex(k + _F(1))
    lx, ly = x2 - x1, y2 - y1
    par = ((px - x1) * lx + (py - y1) * ly) / (lx * lx + ly * ly)
    fx, fy = x1 + lx * par, y1 + ly * par
    edge = np.sqrt(fx * fx + fy * fy).astype(_F)
    dist = np.sqrt(px * px + py * py).astype(_F)
    v = np.where(dist > edge, _F(0), np.where(edge - dist < 1, edge - dist, _F(1)))
    return v.astype(_F)


def _bokeh_polygon_image_legacy(n: int, angle: float, size: int) -> np.ndarray:
    two_pi = _F(math.pi * 2.0)
    flap = _F(two_pi / _F(n))
    add = _F(angle)
    while add < 0:
        add = _F(add + two_pi)
    while add > _F(math.pi):
        add = _F(add - two_pi)
    c = _F(size // 2)
    R = _F(size // 2)
    t = np.arange(size, dtype=_F)
    x, y = np.broadcast_to(t[None, :], (size, size)), np.broadcast_to(t[:, None], (size, size))
    dx, dy = x - c, y - c
    dist = np.sqrt(dx * dx + dy * dy).astype(_F)
    bearing = (np.arctan2(dx, dy) + two_pi).astype(_F)
    k = ((bearing - add) / flap).astype(np.int64).astype(_F)

    def start(j):
        b = (flap * j + add).astype(_F)
        return np.sin(b).astype(_F) * R + c, np.cos(b).astype(_F) * R + c

    x1, y1 = start(k)
    x2, y2 = start(k + _F(1))
    hx, hy = x2 - x1, y2 - y1
    u = ((x - x1) * hx + (y - y1) * hy) / (hx * hx + hy * hy)
    fx, fy = x1 + hx * u - c, y1 + hy * u - c
    edge = np.sqrt(fx * fx + fy * fy).astype(_F)
    v = np.where(edge >= dist, np.where(edge - dist < 1, edge - dist, _F(1)), _F(0))
    return v.astype(_F)


def _sample_bilinear_extended(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Blender's ``sample_bilinear_extended``: normalised coordinates ``(u, v)`` (grids),
    texel coordinates ``u W - 1/2``, bilinear, edges clamped. ``img`` rows bottom-up."""
    h, w = img.shape
    x = u * w - _F(0.5)
    y = v * h - _F(0.5)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0).astype(_F)
    fy = (y - y0).astype(_F)

    def at(yy, xx):
        return img[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)]

    top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
    bot = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
    return (top * (1 - fy) + bot * fy).astype(_F)


def bokeh_blur_kernel(radius: int, bokeh: np.ndarray | None = None) -> np.ndarray:
    """The weights Bokeh Blur uses at integer ``radius`` with the round Bokeh Image, as a
    correlation kernel ``(2 s + 1)^2`` over offsets (rows top-down): tap ``t`` samples
    the Bokeh Image bilinearly at ``1 - (t + 1/2) / (2 s + 1)`` (a disk of radius about
    ``s + 1/2``). Blender 5.0 and 4.2 (measured with impulses) weigh alike. ``bokeh``:
    another Bokeh Image (rows bottom-up; default the round one): a point spreads into it
    as drawn (the weight of offset ``o``, y up, is the image at ``-o``)."""
    s = int(radius)
    if s <= 0:
        return np.ones((1, 1), _F)
    n = 2 * s + 1
    t = np.arange(n, dtype=_F)
    c = _F(1) - (t + _F(0.5)) / _F(n)
    # kernel texel (tx, ty) weighs offset (tx - s, ty - s) in Blender's axes (y up)
    img = bokeh_disk_image() if bokeh is None else np.asarray(bokeh, _F)
    k_up = _sample_bilinear_extended(img, c[None, :], c[:, None])
    return np.ascontiguousarray(k_up[::-1])


def legacy_pixel_size(radius, largest_side) -> int:
    """The radius 4.x's Bokeh Blur uses for the Size the 4.x emission passes:
    ``(floor(r) + 1/2) 100 / M`` percent, clamped to [0, 10], times ``M / 100``,
    truncated (float32 as Blender)."""
    M = _F(largest_side)
    pct = (np.floor(_F(radius)) + _F(0.5)) * _F(100) / M
    pct = min(max(pct, _F(0)), _F(10))
    return int(_F(pct) * M / _F(100))


def _bokeh_blur(image: np.ndarray, radius, legacy: bool, largest_side=None,
                bokeh: np.ndarray | None = None) -> np.ndarray:
    """Constant-size Bokeh Blur: ``sum_k w_k I(p + k) / sum_k w_k`` over
    :func:`bokeh_blur_kernel`, borders extended (both APIs; 4.x converts the radius to
    and from a percentage of the larger side, :func:`legacy_pixel_size`)."""
    from scipy import ndimage

    if legacy:
        s = legacy_pixel_size(radius, largest_side)
    else:
        s = int(np.floor(np.asarray(radius, _F)))  # the node truncates (radius >= 0)
    if s <= 0:
        return image.astype(_F)
    kern = bokeh_blur_kernel(s, bokeh).astype(np.float64)
    img = image.astype(np.float64)
    num = np.stack([ndimage.correlate(img[..., c], kern, mode="nearest")
                    for c in range(img.shape[2])], axis=-1)
    return (num / float(kern.sum())).astype(_F)


def disk_kernel(radius, size: int) -> np.ndarray:
    """The Convolve kernel built from nodes: ``clamp(r + 1/2 - |x - c|, 0, 1)`` on a
    ``size x size`` image, ``c = size // 2`` (float32, as the nodes compute it)."""
    r = np.asarray(radius, _F)
    t = np.arange(size, dtype=_F) - _F(size // 2)
    dist = np.sqrt((t[None, :] * t[None, :] + t[:, None] * t[:, None]).astype(_F)).astype(_F)
    return np.clip((r + _F(0.5)) - dist, _F(0), _F(1)).astype(_F)


def kernel_pixels(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Image Coordinates' pixel indices ``(x, y)`` of a ``size x size`` image, as arrays
    indexed ``[y, x]`` with row 0 at the bottom (y up)."""
    t = np.arange(size, dtype=_F)
    return (np.broadcast_to(t[None, :], (size, size)).copy(),
            np.broadcast_to(t[:, None], (size, size)).copy())


def _convolve(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolve (5.x): zero-padded, the kernel divided by its sum, as a correlation
    ``out(p) = sum_q K(q) I(p + q)`` with ``q`` y up (measured with an asymmetric kernel):
    ``kernel`` indexed ``[y, x]`` with row 0 at the bottom (as :func:`kernel_pixels`), so
    that, for the convolution of the top-down image, its columns are reversed."""
    from scipy.signal import fftconvolve

    k = np.ascontiguousarray(kernel[:, ::-1]).astype(np.float64)
    s = k.sum()
    k = k / (s if s != 0 else 1.0)
    out = np.stack([fftconvolve(image[..., c].astype(np.float64), k, mode="same")
                    for c in range(image.shape[2])], axis=-1)
    return out.astype(_F)


def _dilate(value: np.ndarray, size: int) -> np.ndarray:
    """Dilate/Erode in Step mode: the largest value over the ``(2 n + 1)^2`` square
    (borders extended)."""
    from scipy import ndimage

    n = int(size)
    return ndimage.maximum_filter(np.asarray(value, _F), size=2 * n + 1, mode="nearest")


def _gauss_weights(max_distance: int) -> np.ndarray:
    """Inpaint's smoothing weights: Blender's Gaussian filter at ``i / D``, i = 0..D,
    normalised over the symmetric filter."""
    gf = _F(1.6)
    two = _F(2) * gf * gf
    x = np.arange(max_distance + 1, dtype=_F) * _F(1.0 / max_distance if max_distance else 0)
    x = x * (_F(3) * gf)
    w = (_F(1) / np.sqrt(_F(np.pi) * two) * np.exp(-x * x / two)).astype(_F)
    s = w[0] + 2 * w[1:].sum(dtype=_F)
    return (w / s).astype(_F)


def _jump_flood(seed: np.ndarray) -> np.ndarray:
    """Jump flooding (1+JFA) as Blender runs it: for each pixel the (x, y) of a nearby
    seed, (-1, -1) where none. ``seed`` is boolean, rows bottom-up."""
    H, W = seed.shape
    yy, xx = np.mgrid[:H, :W]
    cur = np.where(seed[..., None], np.stack([xx, yy], -1), -1).astype(np.int64)
    steps = [1]
    s = 1 << max(0, (max(H, W) - 1).bit_length())  # power of 2 >= max side
    s //= 2
    while s:
        steps.append(s)
        s //= 2
    for step in steps:
        best = np.full((H, W), np.inf, np.float32)
        out = np.zeros((H, W, 2), np.int64)
        for j in (-1, 0, 1):
            for i in (-1, 0, 1):
                ny, nx = yy + j * step, xx + i * step
                inside = (ny >= 0) & (ny < H) & (nx >= 0) & (nx < W)
                val = cur[np.clip(ny, 0, H - 1), np.clip(nx, 0, W - 1)]
                ok = inside & (val[..., 0] != -1)
                dx = (val[..., 0] - xx).astype(np.float32)
                dy = (val[..., 1] - yy).astype(np.float32)
                d2 = dx * dx + dy * dy
                better = ok & (d2 < best)
                best = np.where(better, d2, best)
                out = np.where(better[..., None], val, out)
        cur = np.where(np.isfinite(best)[..., None], out, -1)
    return cur


def _inpaint(image: np.ndarray, distance: int) -> np.ndarray:
    """Inpaint (5.x CPU): fill non-opaque pixels within ``distance`` px of the opaque
    region from the nearest boundary pixel (jump flooding), smoothed by a separable
    Gaussian of radius ``min(D, dist) / sqrt 2``; output alpha 1 there."""
    D = int(distance)
    if D <= 0:
        return image.astype(_F)
    img = image.astype(_F)[::-1]  # rows bottom-up, as Blender's texel y
    H, W = img.shape[:2]
    a = img[..., 3]
    opaque = a == 1.0
    pad = np.pad(a, 1, mode="edge")
    trans_nb = np.zeros((H, W), bool)
    for j in (-1, 0, 1):
        for i in (-1, 0, 1):
            if i or j:
                trans_nb |= pad[1 + j:1 + j + H, 1 + i:1 + i + W] < 1.0
    flood = _jump_flood(opaque & trans_nb)
    yy, xx = np.mgrid[:H, :W]
    dx = (xx - flood[..., 0]).astype(_F)
    dy = (yy - flood[..., 1]).astype(_F)
    dist = np.sqrt(dx * dx + dy * dy).astype(_F)
    bcol = img[np.clip(flood[..., 1], 0, H - 1), np.clip(flood[..., 0], 0, W - 1)]
    filled = bcol * (1 - a[..., None]) + img * a[..., None]
    filled = np.where(opaque[..., None], img, filled).astype(_F)
    # Blender divides the float by the double constant sqrt(2): the quotient is rounded
    # once, from double (this decides int(radius) where it is near an integer)
    radius = (np.minimum(_F(D), dist).astype(np.float64) / math.sqrt(2.0)).astype(_F)
    radius = np.where(opaque | (dist > _F(D * 2.0)), _F(0), radius).astype(_F)
    dist = np.where(opaque, _F(0), dist)
    w = _gauss_weights(D)
    smoothed = _variable_blur(_variable_blur(filled, radius, w, axis=1), radius, w, axis=0)
    keep = opaque | (dist > _F(D))
    mixed = smoothed[..., :3] * (1 - a[..., None]) + img[..., :3] * a[..., None]
    out = np.concatenate([mixed, np.ones((H, W, 1), _F)], -1)
    out = np.where(keep[..., None], img, out).astype(_F)
    return out[::-1]


def _variable_blur(img: np.ndarray, radius: np.ndarray, weights: np.ndarray, axis: int):
    """One pass of Blender's symmetric separable variable-size blur along ``axis``: each
    pixel gathers ``int(radius)`` taps each side with weights sampled bilinearly from
    ``weights`` at ``(i + 1/2) / (r + 1)``, divided by their sum; edges extended."""
    r = radius.astype(_F).astype(np.int64)
    n = len(weights)
    acc = img * weights[0]
    wsum = np.full(r.shape, weights[0], _F)
    L = img.shape[axis]
    idx = np.arange(L)
    for i in range(1, int(r.max(initial=0)) + 1):
        active = r >= i
        if not active.any():
            continue
        # weight for tap i at radius r (per pixel)
        x = (_F(i) + _F(0.5)) / (r.astype(_F) + 1) * _F(n) - _F(0.5)
        x0 = np.floor(x).astype(np.int64)
        f = (x - x0).astype(_F)
        wv = (weights[np.clip(x0, 0, n - 1)] * (1 - f) + weights[np.clip(x0 + 1, 0, n - 1)] * f)
        wv = np.where(active, wv, _F(0)).astype(_F)
        plus = np.take(img, np.minimum(idx + i, L - 1), axis=axis)
        minus = np.take(img, np.maximum(idx - i, 0), axis=axis)
        acc = acc + (plus + minus) * wv[..., None]
        wsum = wsum + wv * 2
    return (acc / wsum[..., None]).astype(_F)


def evaluate(graph: Graph, image: np.ndarray, depth: np.ndarray, values: dict,
             legacy: bool = False, keep: bool = False) -> dict:
    """Run the numpy model of ``graph``.

    Args:
        image: ``(H, W, 4)`` premultiplied linear RGBA (rows top-down), the Image input.
        depth: ``(H, W)`` Depth pass (scene units).
        values: the scalar group inputs by name (defaults from :data:`INPUTS`).
        legacy: model the 4.2-4.5 nodes (Bokeh Blur); the 4.x Inpaint is not modelled.
        keep: also return every node's value under ``"nodes"``.

    Returns:
        ``{"Image": (H, W, 4), "Alpha": (H, W)}`` float32 (plus ``"nodes"``).
    """
    inputs = {name: default for name, _, default, _ in interface_inputs(graph.spec)}
    inputs.update(values)
    inputs["Image"] = np.asarray(image, _F)
    inputs["Depth"] = np.asarray(depth, _F)
    H, W = inputs["Depth"].shape
    vals: dict = {}

    def get(arg):
        if isinstance(arg, Ref):
            v = vals[arg.node]
            return v[arg.out] if isinstance(v, tuple) else v
        if isinstance(arg, GroupIn):
            return np.asarray(inputs[arg.name], _F)
        return np.asarray(arg, _F)

    for op in graph.ops:
        a = [get(x) for x in op.args]
        k = op.kind
        if k == "math":
            v = _math(op.param("op"), a[0], a[1], op.param("clamp", False))
        elif k == "separate":
            v = tuple(a[0][..., c] for c in range(4))
        elif k == "combine":
            v = np.stack([np.broadcast_to(x, (H, W)) for x in a], -1).astype(_F)
        elif k == "over":
            bg, fg = (np.broadcast_to(x, (H, W, 4)) for x in a)
            v = (fg + bg * (1 - np.clip(fg[..., 3:4], 0, 1))).astype(_F)
        elif k == "bokeh_disk":
            v = None
        elif k == "bokeh_polygon":
            v = bokeh_polygon_image(op.param("flaps"), float(a[0]), legacy=legacy)
        elif k == "kernel_coords":
            if legacy:
                raise ValueError("the Convolve path exists in Blender 5.x only")
            v = kernel_pixels(op.param("size"))
        elif k == "bokeh_blur":
            v = _bokeh_blur(a[0], a[2], legacy, max(float(inputs["Resolution X"]),
                                                    float(inputs["Resolution Y"])), a[1])
        elif k == "disk_kernel":
            if legacy:
                raise ValueError("the Convolve path exists in Blender 5.x only")
            v = disk_kernel(a[0], op.param("size"))
        elif k == "convolve":
            v = _convolve(a[0], a[1])
        elif k == "dilate":
            v = _dilate(a[0], op.param("size"))
        elif k == "inpaint":
            if legacy:
                raise NotImplementedError("the 4.x Inpaint node's algorithm is not modelled")
            v = _inpaint(a[0], op.param("distance"))
        else:
            raise ValueError(f"unknown node kind {k!r}")
        vals[op.name] = v
    out = {name: np.asarray(get(ref), _F) for name, ref in graph.outputs}
    if keep:
        out["nodes"] = vals
    return out


# --------------------------------------------------------------------------------------
# Emission into Blender (5.x or 4.2-4.5 API)


class _Emitter:
    """Turns the ops of a :class:`Graph` into nodes of ``tree`` for one API."""

    def __init__(self, tree, legacy: bool):
        self.tree = tree
        self.legacy = legacy
        self.nodes = {}  # op name -> node
        self.shared = {}
        self.bokeh_angles = []  # 4.x: [node name, base, turn_at] (a driver sets the angle)
        self.gin = tree.nodes.new("NodeGroupInput")
        self.gin.location = (-400, 0)
        self.column = {}

    def new(self, kind, label, slot=None):
        n = self.tree.nodes.new(node_id(kind, self.legacy))
        n.name = n.label = label
        row = slot if slot is not None else 0
        col = self.column.get(row, 0)
        self.column[row] = col + 1
        n.location = (col * 180.0, -row * 900.0)
        n.hide = kind == "math"
        return n

    def socket(self, arg):
        """The output socket an argument comes from, or None for a constant."""
        if isinstance(arg, Ref):
            return self.nodes[arg.node].outputs[arg.out]
        if isinstance(arg, GroupIn):
            return self.gin.outputs[arg.name]
        return None

    def feed(self, dst, arg):
        src = self.socket(arg)
        if src is None:
            dst.default_value = float(arg) if dst.type == "VALUE" else arg
        else:
            self.tree.links.new(src, dst)

    def math(self, label, op, a, b=0.0, clamp=False, slot=None):
        n = self.new("math", label, slot)
        n.operation = op
        n.use_clamp = bool(clamp)
        for sock, arg in zip(n.inputs, (a, b)):
            if isinstance(arg, (Ref, GroupIn)):
                self.tree.links.new(self.socket(arg), sock)
            elif hasattr(arg, "bl_idname"):  # a node socket already
                self.tree.links.new(arg, sock)
            else:
                sock.default_value = float(arg)
        return n

    def emit(self, op: Op):
        m = re.match(r"s(\d+)\.", op.name)
        slot = int(m.group(1)) + 1 if m else 0  # one row of nodes per slice
        k, L = op.kind, self.legacy
        if k == "math":
            n = self.math(op.name, op.param("op"), *op.args, clamp=op.param("clamp", False),
                          slot=slot)
        elif k == "separate":
            n = self.new("separate", op.name, slot)
            self.feed(n.inputs[0], op.args[0])
        elif k == "combine":
            n = self.new("combine", op.name, slot)
            for sock, arg in zip(n.inputs, op.args):
                self.feed(sock, arg)
        elif k == "over":
            n = self.new("over", op.name, slot)
            if L:
                n.use_premultiply = False
                n.premul = 0.0
                n.inputs[0].default_value = 1.0
                self.feed(n.inputs[1], op.args[0])
                self.feed(n.inputs[2], op.args[1])
            else:
                self.feed(n.inputs["Background"], op.args[0])
                self.feed(n.inputs["Foreground"], op.args[1])
        elif k == "bokeh_disk":
            n = self.new("bokeh_image", op.name, slot)
            set_option(n, "Roundness", 1.0, "rounding")
            set_option(n, "Catadioptric Size", 0.0, "catadioptric")
            set_option(n, "Color Shift", 0.0, "shift")
            set_option(n, "Angle", 0.0)
        elif k == "bokeh_blur":
            n = self.new("bokeh_blur", op.name, slot)
            self.feed(n.inputs["Image"], op.args[0])
            self.feed(n.inputs["Bokeh"], op.args[1])
            if L:
                # 4.x: Size in percent of the larger side, converted back with truncation:
                # pass (floor(r) + 1/2) so that the conversion lands inside the same pixel
                n.use_variable_size = False
                n.use_extended_bounds = False
                f = self.math(op.name + ".floor", "FLOOR", op.args[2], slot=slot)
                h = self.math(op.name + ".half", "ADD", f.outputs[0], 0.5, slot=slot)
                side = self.shared.get("side")
                if side is None:
                    side = self.shared["side"] = self.math(
                        "largest_side", "MAXIMUM", GroupIn("Resolution X"),
                        GroupIn("Resolution Y"))
                p = self.math(op.name + ".x100", "MULTIPLY", h.outputs[0], 100.0, slot=slot)
                pct = self.math(op.name + ".percent", "DIVIDE", p.outputs[0], side.outputs[0],
                                slot=slot)
                self.tree.links.new(pct.outputs[0], n.inputs["Size"])
            else:
                self.feed(n.inputs["Size"], op.args[2])
        elif k == "bokeh_polygon":
            n = self.new("bokeh_image", op.name, slot)
            set_option(n, "Flaps", int(op.param("flaps")))
            set_option(n, "Roundness", 0.0, "rounding")
            set_option(n, "Catadioptric Size", 0.0, "catadioptric")
            set_option(n, "Color Shift", 0.0, "shift")
            if L:  # a property: driven from the camera (add_camera_drivers), see bokeh_angles
                self.bokeh_angles.append([op.name, float(op.param("base")),
                                          float(op.param("turn_at"))])
            else:
                self.feed(n.inputs["Angle"], op.args[0])
        elif k == "kernel_coords":
            n = self._kernel_pixels(op.param("size"))
        elif k == "disk_kernel":
            dist = self._kernel_distance(op.param("size"))
            rp = self.math(op.name + ".r+0.5", "ADD", op.args[0], 0.5, slot=slot)
            n = self.math(op.name, "SUBTRACT", rp.outputs[0], dist.outputs[0], clamp=True,
                          slot=slot)
        elif k == "convolve":
            n = self.new("convolve", op.name, slot)
            self.feed(n.inputs["Image"], op.args[0])
            n.inputs["Kernel Data Type"].default_value = "Float"
            self.tree.links.new(self.socket(op.args[1]), n.inputs["Float Kernel"])
            n.inputs["Normalize Kernel"].default_value = True
        elif k == "dilate":
            n = self.new("dilate", op.name, slot)
            self.feed(n.inputs[0], op.args[0])
            if L:
                n.mode = "STEP"
            else:
                n.inputs["Type"].default_value = "Steps"
            set_option(n, "Size", int(op.param("size")), "distance")
        elif k == "inpaint":
            n = self.new("inpaint", op.name, slot)
            self.feed(n.inputs["Image"], op.args[0])
            set_option(n, "Size", int(op.param("distance")), "distance")
        else:
            raise ValueError(f"unknown node kind {k!r}")
        self.nodes[op.name] = n

    def _kernel_pixels(self, size: int):
        """Separate XYZ of the pixel indices (x, y) of a size x size image (5.x): the Bokeh
        Image cropped to ``size`` gives the domain, Image Coordinates the pixel indices."""
        key = ("pixels", size)
        if key in self.shared:
            return self.shared[key]
        if not 1 <= size <= BOKEH_IMAGE_SIZE:
            raise ValueError(f"the Convolve kernel must be 1..{BOKEH_IMAGE_SIZE} px, got {size}")
        src = self.new("bokeh_image", "kernel_domain")
        crop = self.new("crop", "kernel_crop")
        self.tree.links.new(src.outputs[0], crop.inputs["Image"])
        for name, v in (("X", 0), ("Y", 0), ("Width", size), ("Height", size)):
            crop.inputs[name].default_value = v
        crop.inputs["Alpha Crop"].default_value = False
        coords = self.new("image_coordinates", "kernel_coordinates")
        self.tree.links.new(crop.outputs[0], coords.inputs["Image"])
        xyz = self.new("separate_xyz", "kernel_xy")
        self.tree.links.new(coords.outputs["Pixel"], xyz.inputs[0])
        self.shared[key] = xyz
        return xyz

    def _kernel_distance(self, size: int):
        """|x - c| on a size x size image, shared by every slice's disk kernel (5.x)."""
        key = ("distance", size)
        if key in self.shared:
            return self.shared[key]
        xyz = self._kernel_pixels(size)
        c = float(size // 2)
        dx = self.math("kernel_dx", "SUBTRACT", xyz.outputs[0], c)
        dy = self.math("kernel_dy", "SUBTRACT", xyz.outputs[1], c)
        dx2 = self.math("kernel_dx2", "MULTIPLY", dx.outputs[0], dx.outputs[0])
        dy2 = self.math("kernel_dy2", "MULTIPLY", dy.outputs[0], dy.outputs[0])
        s = self.math("kernel_r2", "ADD", dx2.outputs[0], dy2.outputs[0])
        dist = self.math("kernel_distance", "SQRT", s.outputs[0])
        self.shared[key] = dist
        return dist


def _new_input(group, name, stype, default, desc):
    s = group.interface.new_socket(name, in_out="INPUT", socket_type=stype, description=desc)
    s.default_value = default
    if stype == "NodeSocketFloat" and name not in ("Depth", "Aperture Rotation"):
        s.min_value = 0.0
    return s


def _ensure_interface(group, spec=None) -> None:
    """Give ``group`` exactly the sockets of :func:`interface_inputs` and :data:`OUTPUTS`;
    kept as they are when they already match (so links, values and drivers on group
    nodes stay). A group that differs only by the aperture inputs (:data:`SHAPE_INPUTS`:
    the camera's blades or ratio changed) gets them added or removed, the other sockets
    (and the links to them) kept."""
    inputs = interface_inputs(spec)
    want = [(n, "INPUT", t) for n, t, _, _ in inputs] + [(n, "OUTPUT", t) for n, t, _ in OUTPUTS]
    have = [(s.name, s.in_out, s.socket_type) for s in _interface_sockets(group)]
    if sorted(have) == sorted(want):
        return
    shape = {(n, "INPUT", t) for n, t, _, _ in SHAPE_INPUTS}
    if sorted(set(have) - shape) == sorted(set(want) - shape) and len(set(have)) == len(have):
        for item in _interface_sockets(group):
            if (item.name, item.in_out, item.socket_type) in shape - set(want):
                group.interface.remove(item)
        for name, stype, default, desc in inputs:
            if (name, "INPUT", stype) in shape - set(have):
                _new_input(group, name, stype, default, desc)
        return
    group.interface.clear()
    for name, stype, default, desc in inputs:
        _new_input(group, name, stype, default, desc)
    for name, stype, desc in OUTPUTS:
        group.interface.new_socket(name, in_out="OUTPUT", socket_type=stype, description=desc)


def build_group(graph: Graph, group=None, name: str = GROUP_NAME):
    """Emit ``graph`` as a compositor node group for the running Blender's API.

    ``group``: an existing group to regenerate in place (its nodes are replaced, its
    interface kept if it matches, so group nodes using it keep their links, values and
    drivers); default a new group named ``name``. Returns the group. Its structure is
    stored in the group's custom property ``mpib_spec`` (for :func:`spec_of`)."""
    import json

    import bpy

    legacy = is_legacy_api(bpy)
    if graph.spec.blur == "convolve" and legacy:
        raise ValueError("blur 'convolve' needs Blender 5.0 or later (no Convolve node before)")
    if graph.spec.anamorphic and legacy:  # no Convolve to stretch the kernels
        raise ValueError("the node group draws an anamorphic ratio on Blender 5.0 or later "
                         "only")
    if group is None:
        group = bpy.data.node_groups.new(name, "CompositorNodeTree")
    group.nodes.clear()
    _ensure_interface(group, graph.spec)
    em = _Emitter(group, legacy)
    for op in graph.ops:
        em.emit(op)
    if em.bokeh_angles:  # 4.x: the Bokeh Images' angles, for add_camera_drivers
        group["mpib_bokeh_angles"] = json.dumps(em.bokeh_angles)
    elif "mpib_bokeh_angles" in group:
        del group["mpib_bokeh_angles"]
    gout = group.nodes.new("NodeGroupOutput")
    gout.location = (em.column.get(0, 0) * 180.0 + 200, 0)
    for out_name, ref in graph.outputs:
        group.links.new(em.socket(ref), gout.inputs[out_name])
    s = graph.spec
    group["mpib_spec"] = json.dumps({"disparities": list(s.disparities), "fill": s.fill,
                                     "blur": s.blur, "fill_px": list(s.fill_px),
                                     "kernel_radius_px": s.kernel_radius_px,
                                     "edge": s.edge, "edge_jump": s.edge_jump,
                                     "slabs": list(s.slabs),
                                     "bokeh_slices": list(s.bokeh_slices),
                                     "density_px": s.density_px,
                                     **({"blades": s.blades, "anamorphic": s.anamorphic}
                                        if s.shaped else {})})
    return group


def spec_of(group) -> GroupSpec | None:
    """The :class:`GroupSpec` a group was built from (None if it is not one of ours)."""
    import json

    raw = group.get("mpib_spec") if group is not None else None
    if not raw:
        return None
    d = json.loads(raw)
    return GroupSpec(tuple(d["disparities"]), d["fill"], d["blur"], tuple(d["fill_px"]),
                     int(d["kernel_radius_px"]), d.get("edge", "hard"), d.get("edge_jump", 0.0),
                     tuple(d.get("slabs", ())), tuple(d.get("bokeh_slices", ())),
                     int(d.get("density_px", 0)), int(d.get("blades", 0)),
                     bool(d.get("anamorphic", False)))


def install(scene, group, node_name: str = GROUP_NAME, changes: list | None = None):
    """Put the group where the render enters the compositor tree of ``scene`` (created as
    needed), enabling the Depth pass. Reuses a group node named ``node_name`` if there is
    one. Returns the group node; appends to ``changes`` one phrase per change made to
    the artist's links.

    The node takes Render Layers' Image and Depth. Every socket that took Render Layers'
    Image (e.g. the artist's Glare) takes the node's Image instead, and every one that
    took its Alpha takes the node's Alpha (the refocused coverage), so the artist's
    chain is kept whole after the node. Where nothing took the render's Image, the node
    feeds the compositor output, unless something else already does: then that link is
    kept and the node is left for the artist to connect (said in ``changes``)."""
    import bpy

    legacy = is_legacy_api(bpy)
    tree = compositor_tree(scene, create=True)
    changes = [] if changes is None else changes
    for vl in scene.view_layers:
        vl.use_pass_z = True
    rl = next((n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers"), None)
    if rl is None:
        rl = tree.nodes.new("CompositorNodeRLayers")
        rl.location = (-400, 0)
    out = tree_output(tree)
    node = tree.nodes.get(node_name)
    if node is None or node.bl_idname != "CompositorNodeGroup":
        node = tree.nodes.new(node_id("group", legacy))
        node.name = node_name
        node.location = (rl.location[0] + 300, rl.location[1])
    node.node_tree = group
    node.label = group.name
    node.width = 220

    def takers(socket_name):
        src = rl.outputs.get(socket_name)
        return [] if src is None else [link.to_socket for link in tree.links
                                       if link.from_socket == src and link.to_node != node]

    def named(sockets):
        return ", ".join(f"'{s.node.name}' ({s.name})" for s in sockets)

    image_takers, alpha_takers = takers("Image"), takers("Alpha")
    tree.links.new(rl.outputs["Image"], node.inputs["Image"])
    tree.links.new(rl.outputs["Depth"], node.inputs["Depth"])
    for s in image_takers:
        tree.links.new(node.outputs["Image"], s)
    for s in alpha_takers:
        tree.links.new(node.outputs["Alpha"], s)
    if image_takers:
        changes.append(f"inserted between Render Layers and {named(image_takers)}")
    if alpha_takers:
        changes.append(f"{named(alpha_takers)} now take(s) the node's Alpha instead of "
                       f"Render Layers' Alpha")
    if not image_takers and not node.outputs["Image"].is_linked:
        target = out.inputs[0]
        if target.is_linked:
            changes.append(f"the compositor output keeps its input from "
                           f"'{target.links[0].from_node.name}'; connect the node's Image "
                           f"where the render should enter your tree")
        else:
            tree.links.new(node.outputs["Image"], target)
            out.location = (node.location[0] + 300, node.location[1])
            changes.append("connected to the compositor output")
    return node


# --------------------------------------------------------------------------------------
# Drivers from the scene camera, and the scene's depth range without a render


def _driver(owner, expression: str, variables, prop: str = "default_value") -> None:
    """Replace the driver of ``owner.<prop>`` (a socket's value, a node's property): a
    simple expression (evaluated without Python) over SINGLE_PROP variables ``(name,
    id_type, id, data_path)``."""
    owner.driver_remove(prop)
    fc = owner.driver_add(prop)
    drv = fc.driver
    drv.type = "SCRIPTED"
    for name, id_type, ident, path in variables:
        var = drv.variables.new()
        var.name = name
        var.type = "SINGLE_PROP"
        var.targets[0].id_type = id_type
        var.targets[0].id = ident
        var.targets[0].data_path = path
    drv.expression = expression


#: Inputs the camera drivers set.
DRIVEN_INPUTS = ("Focus Distance", "F-Stop", "Focal Length", "Sensor Width", "Resolution X",
                 "Resolution Y", "Film Transparent")


def add_camera_drivers(node, scene, cam_obj=None) -> list[str]:
    """Drive the group node's lens inputs from ``cam_obj`` (default the scene camera) and
    the scene's render settings, with simple expressions that Blender evaluates without
    Python, follow keyframes and survive saving:

    - Focus Distance: the focus object's planar depth ``|z . (cam - obj)| / |z|`` (z the
      camera's view axis, as Blender computes it), else ``dof.focus_distance``;
    - F-Stop, Focal Length: ``dof.aperture_fstop``, ``lens``;
    - Sensor Width: the sensor size across the image width for the fit (HORIZONTAL:
      the width; VERTICAL: ``height * W / H``; AUTO: ``width * W / max(W, H)``);
    - Resolution X/Y: ``floor(resolution * percentage / 100)``;
    - Film Transparent: ``render.film_transparent``.

    Unit Scale is set to 1 and not driven: Cycles takes the lens in mm as 1e-3 Blender
    units whatever the scene's Unit Scale (its depth of field does not change with it).
    Returns the names of the driven inputs. Deleting a driver leaves its input free."""
    cam_obj = cam_obj or scene.camera
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise ValueError("the scene has no camera to drive the node from")
    cam = cam_obj.data
    focus_expr, focus_vars = _focus_driver(cam_obj)
    _driver(node.inputs["Focus Distance"], focus_expr, focus_vars)
    _driver(node.inputs["F-Stop"], "n", [("n", "CAMERA", cam, "dof.aperture_fstop")])
    _driver(node.inputs["Focal Length"], "f", [("f", "CAMERA", cam, "lens")])
    res = [("rx", "SCENE", scene, "render.resolution_x"),
           ("ry", "SCENE", scene, "render.resolution_y")]
    pct = [("pct", "SCENE", scene, "render.resolution_percentage")]
    # sensor_fit is an enum: AUTO 0, HORIZONTAL 1, VERTICAL 2
    _driver(node.inputs["Sensor Width"],
            "sw if fit == 1 else (sh * rx / ry if fit == 2 else sw * rx / max(rx, ry))",
            [("sw", "CAMERA", cam, "sensor_width"), ("sh", "CAMERA", cam, "sensor_height"),
             ("fit", "CAMERA", cam, "sensor_fit")] + res)
    _driver(node.inputs["Resolution X"], "floor(rx * pct / 100)", res[:1] + pct)
    _driver(node.inputs["Resolution Y"], "floor(ry * pct / 100)", res[1:] + pct)
    node.inputs["Unit Scale"].driver_remove("default_value")
    node.inputs["Unit Scale"].default_value = 1.0
    _driver(node.inputs["Film Transparent"], "t", [("t", "SCENE", scene, "render.film_transparent")])
    driven = list(DRIVEN_INPUTS)
    if "Aperture Rotation" in node.inputs:  # a group made for a shaped aperture
        _driver(node.inputs["Aperture Rotation"], "r",
                [("r", "CAMERA", cam, "dof.aperture_rotation")])
        _driver(node.inputs["Aperture Ratio"], "q", [("q", "CAMERA", cam, "dof.aperture_ratio")])
        driven += [name for name, *_ in SHAPE_INPUTS]
    _drive_bokeh_angles(node.node_tree, cam, focus_expr, focus_vars)
    return driven


def _focus_driver(cam_obj) -> tuple[str, list]:
    """The focus distance as a simple driver expression and its variables: the focus
    object's planar depth ``|z . (cam - obj)| / |z|`` (z the camera's view axis, as
    Blender computes it), else ``dof.focus_distance``."""
    cam = cam_obj.data
    focus_obj = cam.dof.focus_object
    if focus_obj is None:
        return "z", [("z", "CAMERA", cam, "dof.focus_distance")]
    vars_ = []
    for i, ax in enumerate("xyz"):  # RNA paths index matrix_world column first
        vars_ += [(f"z{ax}", "OBJECT", cam_obj, f"matrix_world[2][{i}]"),
                  (f"c{ax}", "OBJECT", cam_obj, f"matrix_world[3][{i}]"),
                  (f"o{ax}", "OBJECT", focus_obj, f"matrix_world[3][{i}]")]
    return ("abs(zx * (cx - ox) + zy * (cy - oy) + zz * (cz - oz)) / "
            "sqrt(zx * zx + zy * zy + zz * zz)", vars_)


def _drive_bokeh_angles(group, cam, focus_expr: str, focus_vars) -> None:
    """Blender 4.2-4.5: the Bokeh Image's Angle is a node property, not an input the group
    can feed, so each of the group's polygon Bokeh Images (``mpib_bokeh_angles``, from
    :func:`build_group`) gets a driver on it, the same angle the 5.x graph computes:
    ``base - rotation``, plus ``pi`` for a slice (disparity ``d``) in front of the focus
    (``d z > 1``, z the focus distance), for odd blades."""
    import json

    raw = group.get("mpib_bokeh_angles") if group is not None else None
    for name, base, turn_at in json.loads(raw) if raw else ():
        expr = f"{base!r} - r"
        if turn_at >= 0:
            expr += f" + ({math.pi!r} if {turn_at!r} * ({focus_expr}) > 1 else 0)"
        _driver(group.nodes[name], expr, [("r", "CAMERA", cam, "dof.aperture_rotation")]
                + (focus_vars if turn_at >= 0 else []), prop="angle")


def scene_disparity_intervals(scene, cam_obj=None) -> list[tuple[float, float]]:
    """Disparity intervals ``1/Z`` of the visible mesh objects' bounding boxes in front
    of the camera (Z planar depth, clipped to the camera's clip range), plus the
    background at 0 when the world is visible: a stand-in for the depth of a render
    when there is none yet."""
    from mathutils import Vector

    cam_obj = cam_obj or scene.camera
    inv = cam_obj.matrix_world.inverted()
    cam = cam_obj.data
    out = [(0.0, 0.0)]
    for ob in scene.objects:
        if ob.type not in ("MESH", "CURVE", "SURFACE", "META", "FONT") or not ob.visible_get():
            continue
        zs = [-(inv @ (ob.matrix_world @ Vector(c))).z for c in ob.bound_box]
        z0, z1 = max(min(zs), cam.clip_start), min(max(zs), cam.clip_end)
        if z1 > cam.clip_start and z0 <= z1:
            out.append((1.0 / z1, 1.0 / z0))
    return out
