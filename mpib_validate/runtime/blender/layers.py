"""Depth groups as Blender view layers: one view layer per group, the others Indirect Only.

For the layered input of :mod:`mpib_validate.runtime.layers.layered`, Cycles renders each depth group
in a view layer ``mpib_group_<k>`` (``k = 0`` farthest) in the same F12 render:

- the group's objects are linked into a new collection ``mpib_group_<k>`` (they stay in
  their own collections too); in view layer ``j`` every other group's collection is
  *Indirect Only* (``LayerCollection.indirect_only``, Cycles): its objects still cast
  shadows and appear in reflections but are not seen by camera rays. Blender ORs this
  flag over the collections that hold an object, so an object of another group is
  indirect only in layer ``j`` even though its own collection is not.
- film transparent (a scene setting: the artist's view layers render with it too while
  the layers are set up), so that a layer's alpha is Cycles' own coverage; Combined and
  Z passes.

- the world: with the film transparent no layer shows it, so where the artist's film
  was opaque the farthest layer also gets the Environment pass (the world as camera
  rays see it, weighted by the samples that miss every object): ``Combined +
  Environment`` is that layer with the world behind it, opaque
  (:func:`mpib_validate.runtime.refocus.load_layered_passes` adds them).

What the trick gets wrong: light that reaches the camera *through* a nearer group
(refraction, or a transparent BSDF seen in the farther layer) is rendered in the nearer
layer only, and is blurred at that group's depth; a farther layer sees no reflections
of itself in a nearer mirror. Measured on a glass ball before a wall
(``tests/test_layered.py``): the layers composited with "over" give back the single
pass to rms 1.5e-3 with the same seed (another seed: 7.5e-3), and the refocus inside
the ball is 1.8 dB further from Cycles' depth of field than for the same ball diffuse
(noise-corrected). A
spanning object put in the farthest group (a ground plane) that hides part of a nearer
group's object (a hill in front of a house) does not hide it in the layers: Indirect
Only makes it invisible to that group's camera rays, and "over" puts the nearer group
on top.

:func:`remove_layers` removes the view layers and collections again (found by their
``mpib_group_`` names) and restores the film setting; the artist's own view layers are
not touched.

Automatic grouping (:func:`split_groups`, pure numpy): each object's disparity interval
``[1/z_max, 1/z_min]`` from its bounding box in camera space (``z`` the distance along
the view axis, scene units). Disparity, because blur radius is linear in it
(``r = A |d - d_f|``): a gap in disparity is a gap in blur. An object whose interval
spans more than :data:`SPANNING_FRACTION` of the scene's disparity range (a ground
plane, a long wall seen at an angle) goes to the farthest group and does not take part
in the split; the others are merged where their intervals overlap and split at the
largest gaps, at most ``max_groups - 1`` of them, each at least ``min_gap`` of the
range.

Where the depth jumps in the last render (:func:`refine_intervals`): a bounding box is
conservative (a ball's box reaches behind its visible front, a tilted board's box
covers depths its visible face does not), so when the Z pass of the last render is
given, each object's interval shrinks to the disparities that render shows inside the
object's screen rectangle and inside its box interval. A gap between the refined
intervals is then a disparity range that no visible pixel of those objects has: a
jump in the rendered depth. An object the render does not show there (hidden, or the
scene changed) keeps its box interval. A scene where nothing can be split gives one group: the caller renders the
single pass (:func:`auto_groups` says why). Or the artist picks collections
(:func:`groups_from_collections`).
"""

from __future__ import annotations

import numpy as np

#: View layers and collections made here are named ``GROUP_PREFIX + str(k)``.
GROUP_PREFIX = "mpib_group_"
#: An object spanning more than this fraction of the scene's disparity range is farthest.
SPANNING_FRACTION = 0.5
#: Smallest gap (fraction of the disparity range) the automatic grouping splits at.
MIN_GAP_FRACTION = 0.05
#: Object types that the camera can see.
RENDERABLE = {"MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD", "VOLUME"}
_SAVED_FILM = "mpib_film_transparent"


def split_groups(intervals, max_groups: int = 3, min_gap_fraction: float = MIN_GAP_FRACTION,
                 spanning_fraction: float = SPANNING_FRACTION) -> list[list[int]]:
    """Indices of ``intervals`` (``(d_lo, d_hi)`` disparity per object) in groups, far
    to near (see the module docstring). One group when there is nothing to split."""
    iv = np.asarray(intervals, np.float64).reshape(-1, 2)
    n = len(iv)
    if n == 0:
        return []
    lo, hi = iv.min(axis=1), iv.max(axis=1)
    total = float(hi.max() - lo.min())
    if n == 1 or total <= 0 or max_groups < 2:
        return [list(range(n))]
    spanning = (hi - lo) > spanning_fraction * total
    rest = np.flatnonzero(~spanning)
    order = rest[np.argsort(lo[rest], kind="stable")]
    clusters: list[list[int]] = []
    top = -np.inf
    for i in order:  # merge overlapping intervals, far to near
        if clusters and lo[i] <= top:
            clusters[-1].append(int(i))
            top = max(top, hi[i])
        else:
            clusters.append([int(i)])
            top = hi[i]
    gaps = [lo[c[0]] - max(hi[j] for j in p) for p, c in zip(clusters, clusters[1:])]
    cut = sorted(np.argsort(gaps)[::-1][:max_groups - 1])
    cut = [k for k in cut if gaps[k] >= min_gap_fraction * total]
    groups, start = [], 0
    for k in cut:
        groups.append([i for c in clusters[start:k + 1] for i in c])
        start = k + 1
    groups.append([i for c in clusters[start:] for i in c])
    groups = [g for g in groups if g]
    far = [int(i) for i in np.flatnonzero(spanning)]
    if far:
        if groups:
            groups[0] = sorted(far + groups[0])
        else:
            groups = [far]
    return groups


# --------------------------------------------------------------------------------------
# bpy adapters


def refine_intervals(intervals, rects, disparity, rel_tol: float = 1e-3) -> list[tuple[float, float]]:
    """Each ``(d_lo, d_hi)`` of ``intervals`` (1/scene-unit) shrunk to the ``[min, max]``
    of the values of ``disparity`` (``(H, W)``, 1/Z of the last render) inside its pixel
    rectangle ``(x0, y0, x1, y1)`` (half-open, clipped to the image) that lie in the
    interval widened by ``rel_tol`` (Z is float32; a silhouette's pixel centre is on the
    object); unchanged where there is none (see the module docstring)."""
    D = np.asarray(disparity, np.float64)
    H, W = D.shape
    out = []
    for (lo, hi), (x0, y0, x1, y1) in zip(intervals, rects):
        lo, hi = min(lo, hi), max(lo, hi)
        x0, x1 = max(0, int(x0)), min(W, int(x1))
        y0, y1 = max(0, int(y0)), min(H, int(y1))
        v = D[y0:y1, x0:x1].ravel() if (x1 > x0 and y1 > y0) else np.empty(0)
        v = v[(v >= lo * (1 - rel_tol)) & (v <= hi * (1 + rel_tol))]
        out.append((float(v.min()), float(v.max())) if v.size else (float(lo), float(hi)))
    return out


def object_screen_rect(scene, obj, width: int, height: int) -> tuple[int, int, int, int]:
    """Pixel rectangle ``(x0, y0, x1, y1)`` (rows from the top, half-open) that ``obj``'s
    bounding box covers in the camera's view; the whole image if a corner is behind
    the camera."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    pts = [world_to_camera_view(scene, scene.camera, obj.matrix_world @ Vector(c))
           for c in obj.bound_box]
    if any(p.z <= 0 for p in pts):
        return 0, 0, int(width), int(height)
    xs = [p.x * width for p in pts]
    ys = [(1.0 - p.y) * height for p in pts]
    return (int(np.floor(min(xs))), int(np.floor(min(ys))), int(np.ceil(max(xs))) + 1,
            int(np.ceil(max(ys))) + 1)


def object_disparity_interval(obj, camera, near: float = 1e-3) -> tuple[float, float]:
    """``(1/z_max, 1/z_min)`` of ``obj``'s bounding box corners in ``camera``'s space
    (``z`` along the view axis, scene units; corners nearer than ``near`` are clamped)."""
    from mathutils import Vector

    to_cam = camera.matrix_world.inverted() @ obj.matrix_world
    z = np.array([-(to_cam @ Vector(c)).z for c in obj.bound_box])  # cameras look down -Z
    z = np.maximum(z, near)
    return float(1.0 / z.max()), float(1.0 / z.min())


def artist_layer(scene):
    """The view layer the groups are taken from: the first that is not ours."""
    for vl in scene.view_layers:
        if not vl.name.startswith(GROUP_PREFIX):
            return vl
    raise ValueError(f"scene '{scene.name}' has no view layer of its own")


def auto_groups(scene, max_groups: int = 3, depth=None) -> tuple[list[list], str]:
    """The renderable objects that the camera sees in the artist's view layer
    (:func:`artist_layer`; not in an excluded collection, not hidden from renders or
    camera rays) in depth groups, far to near, and a one-line report. ``depth``: the
    Z pass ``(H, W)`` (scene units) of the last render, whose jumps refine the objects'
    intervals (:func:`refine_intervals`); ignored unless it has the render's size. One
    group (or none) means: render the single pass."""
    cam = scene.camera
    if cam is None:
        return [], "the scene has no camera: single pass"
    source = artist_layer(scene)
    source.update()  # collection flags and object matrices are stale after Python edits
    objs = [o for o in source.objects if o.type in RENDERABLE and not o.hide_render
            and o.visible_camera]
    if len(objs) < 2:
        return [objs] if objs else [], (f"{len(objs)} visible object(s): nothing to split "
                                        f"into depth groups, single pass")
    intervals = [object_disparity_interval(o, cam) for o in objs]
    r = scene.render
    W, H = r.resolution_x * r.resolution_percentage // 100, r.resolution_y * r.resolution_percentage // 100
    refined = depth is not None and np.shape(depth) == (H, W)
    if refined:
        from mpib_validate.runtime.layers.passes import PassError, depth_to_disparity

        try:
            D = depth_to_disparity(np.asarray(depth, np.float64), source="the last render's Z")
        except PassError:  # NaN, or nothing but the world: the boxes alone
            refined, D = False, None
    if refined:
        intervals = refine_intervals(intervals, [object_screen_rect(scene, o, W, H)
                                                 for o in objs], D)
    idx = split_groups(intervals, max_groups)
    groups = [[objs[i] for i in g] for g in idx]
    how = " (refined by the last render's depth)" if refined else ""
    if len(groups) < 2:
        return groups, (f"{len(objs)} objects overlap in depth{how}: one depth group, single "
                        f"pass")
    names = "; ".join(", ".join(o.name for o in g) for g in groups)
    return groups, f"{len(groups)} depth groups{how}, far to near: {names}"


def groups_from_collections(scene, collections) -> list[list]:
    """Depth groups that the artist picks: the renderable objects the camera sees (as
    in :func:`auto_groups`) of each collection, children included, ordered far to near
    by the median disparity of their bounding boxes; an object in several of the
    collections goes to the first that holds it; empty groups are dropped. The visible
    objects that no picked collection holds are one more group, ordered like the others
    (an object left out of every group would be seen directly in every group layer):
    picking only a foreground collection splits it from the rest."""
    source = artist_layer(scene)
    source.update()
    seen = {o.name for o in source.objects if o.type in RENDERABLE and not o.hide_render
            and o.visible_camera}
    groups, taken = [], set()
    for coll in collections:
        objs = [o for o in coll.all_objects if o.name in seen and o.name not in taken]
        taken.update(o.name for o in objs)
        if objs:
            d = [np.mean(object_disparity_interval(o, scene.camera)) for o in objs]
            groups.append((float(np.median(d)), objs))
    rest = [o for o in source.objects if o.name in seen and o.name not in taken]
    if rest:
        d = [np.mean(object_disparity_interval(o, scene.camera)) for o in rest]
        groups.append((float(np.median(d)), rest))
    return [objs for _, objs in sorted(groups, key=lambda g: g[0])]


def _layer_collection(layer_collection, name):
    if layer_collection.name == name:
        return layer_collection
    for child in layer_collection.children:
        found = _layer_collection(child, name)
        if found is not None:
            return found
    return None


def setup_layers(scene, groups) -> list[str]:
    """One view layer per group of objects (far to near), see the module docstring;
    earlier ``mpib_group_`` layers are removed first. Returns the layer names."""
    import bpy

    remove_layers(scene)
    if _SAVED_FILM not in scene:
        scene[_SAVED_FILM] = bool(scene.render.film_transparent)
    world_behind = not scene[_SAVED_FILM]  # the artist's film shows the world
    scene.render.film_transparent = True
    names = [f"{GROUP_PREFIX}{k}" for k in range(len(groups))]
    for name, objs in zip(names, groups):
        coll = bpy.data.collections.new(name)
        scene.collection.children.link(coll)
        for o in objs:
            coll.objects.link(o)
    source = artist_layer(scene)
    for vl in scene.view_layers:  # the artist's layers render as before
        if not vl.name.startswith(GROUP_PREFIX):
            for name in names:
                _layer_collection(vl.layer_collection, name).exclude = True
    for j, name in enumerate(names):
        vl = scene.view_layers.new(name)
        vl.use = True
        vl.use_pass_combined = True
        vl.use_pass_z = True
        vl.use_pass_environment = world_behind and j == 0
        _copy_collection_flags(source.layer_collection, vl.layer_collection)
        for k, other in enumerate(names):
            lc = _layer_collection(vl.layer_collection, other)
            lc.exclude = False
            lc.indirect_only = k != j
    return names


def _copy_collection_flags(src, dst):
    """The artist's Exclude, Holdout and Indirect Only per collection (a new view layer
    includes every collection)."""
    for child in src.children:
        if child.name.startswith(GROUP_PREFIX):
            continue
        target = _layer_collection(dst, child.name)
        if target is None:
            continue
        target.exclude = child.exclude
        if not child.exclude:
            target.holdout = child.holdout
            target.indirect_only = child.indirect_only
            _copy_collection_flags(child, target)


def remove_layers(scene) -> int:
    """Remove the ``mpib_group_`` view layers and collections and restore the film
    setting; returns how many view layers were removed. The artist's own are kept."""
    import bpy

    ours = [vl for vl in scene.view_layers if vl.name.startswith(GROUP_PREFIX)]
    for vl in ours:
        scene.view_layers.remove(vl)
    for coll in [c for c in bpy.data.collections if c.name.startswith(GROUP_PREFIX)]:
        bpy.data.collections.remove(coll)
    if _SAVED_FILM in scene:
        scene.render.film_transparent = bool(scene[_SAVED_FILM])
        del scene[_SAVED_FILM]
    return len(ours)


def prepare(scene, max_groups: int = 3, depth=None) -> tuple[list[str], str]:
    """Automatic grouping (``depth``: the last render's Z pass, see :func:`auto_groups`)
    and its view layers: ``(layer names, report)``. Where there is nothing to split
    (one object, or all overlapping in depth), no layer is made (``[]``, and earlier
    ``mpib_group_`` layers are removed): the single pass."""
    groups, report = auto_groups(scene, max_groups, depth)
    if len(groups) < 2:
        remove_layers(scene)
        return [], report
    return setup_layers(scene, groups), report
