"""From rendered passes (colour + depth) to an MPI, with the hidden background filled.

The input is what a renderer gives: an all-in-focus colour image and one depth per
pixel (Blender's Combined and Depth passes), nothing behind the foreground. The steps:

1. :func:`depth_to_disparity`: ``d = 1/Z``; depth at or beyond ``far_limit`` (Cycles
   writes 1e10 for the background) is infinitely far, ``d = 0``.
2. Occlusion regions and the hidden-background fill (:mod:`mpib_validate.runtime.layers.fill`).
3. Edge pixels: an anti-aliased pixel on a depth edge mixes foreground and background
   colour, but its depth is one or the other. Such a pixel is unmixed: with the
   foreground colour ``c_n`` (filled from nearby pure foreground) and the background
   colour ``c_f`` (the hidden-background fill), its coverage is the projection
   ``a = <c - c_f, c_n - c_f> / |c_n - c_f|^2``, kept in [1/4, 1] where the depth says
   near and in [0, 3/4] where it says far. The foreground plane gets alpha ``a`` and the
   background an opaque layer behind it; the side the depth names takes the rest of the
   colour, ``(c - (1 - a) c_f) / a`` or ``(c - a c_n) / (1 - a)``, so that the pinhole
   composite is the pixel exactly. No fringe of the wrong colour is then blurred with
   the other layer. A structure one or two pixels wide (a wire, a blade of grass) has no
   pure pixel; the far-side pixels around it, including those that touch it only at a
   corner, take its most contrasting own (most covered) pixel within 1.5 px as ``c_n``
   and may give it up to their whole colour, so that its colour leaves them with it
   instead of staying sharp or blurring with the background's radius.
4. The sheets (hidden background, unmixed background parts, visible pixels, unmixed
   foreground parts, far to near) are cut into planes with
   :func:`mpib_validate.runtime.layers.mpi.layers_from_sheets`: each pixel is shared between its two
   neighbouring planes so that Eq. 16 gives back its disparity.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from mpib_validate.runtime.layers import fill as _fill
from mpib_validate.runtime.layers.mpi import (SNAP_PX, MPI, LayerPlan, Pixels, Sheet, adaptive_planes,
                                             layers_from_sheets, plan_layers, plane_spacing,
                                             uniform_planes)


class PassError(ValueError):
    """Unusable colour or depth input; the message names the file."""


DEFAULT_FAR_LIMIT = 1e9


def depth_to_disparity(depth: np.ndarray, far_limit: float = DEFAULT_FAR_LIMIT,
                       source: str = "depth") -> np.ndarray:
    """Disparity ``1/Z`` (1/scene-unit) from planar depth ``Z`` (scene units).

    Depth ``>= far_limit`` (or +inf) is infinitely far: disparity 0. Raises
    :class:`PassError` naming ``source`` for NaN, for depth ``<= 0``, and for depth that
    is everywhere at infinity (nothing to refocus on).
    """
    Z = np.asarray(depth, np.float64)
    nan = np.isnan(Z)
    if nan.any():
        y, x = np.argwhere(nan)[0]
        raise PassError(f"{source}: depth is NaN at {int(nan.sum())} pixel(s), first at "
                        f"(row {y}, column {x})")
    bad = Z <= 0
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise PassError(f"{source}: depth must be > 0; {int(bad.sum())} pixel(s) are <= 0 "
                        f"(min {Z.min():.4g} at row {y}, column {x})")
    far = Z >= far_limit
    if far.all():
        raise PassError(f"{source}: depth is at infinity (>= {far_limit:g}) everywhere; "
                        f"was the Depth pass rendered with geometry in view?")
    return np.where(far, 0.0, 1.0 / np.where(far, 1.0, Z))


def passes_disparity(passes, far_limit: float = DEFAULT_FAR_LIMIT) -> np.ndarray:
    """The disparity of passes (:class:`mpib_validate.runtime.refocus.Passes`): the one
    given (``passes.disparity``, a photograph's), else :func:`depth_to_disparity` of
    their depth."""
    if passes.disparity is not None:
        return np.asarray(passes.disparity, np.float64)
    return depth_to_disparity(passes.depth, far_limit, source=passes.depth_source)


@dataclass
class PassesSettings:
    """How to build the MPI.

    Attributes:
        tolerance_px: largest blur-radius quantisation error of the plane placement.
        planes: ``adaptive`` (only where content is) or ``uniform`` (``n_uniform`` planes).
        jump_px: a neighbour pair is a depth edge when its blur-radius difference
            ``A |d_1 - d_2|`` exceeds this (pixels).
        fill: fill the hidden background (off: visible-only layers).
        unmix_edges: unmix anti-aliased edge pixels (off: each pixel goes whole to its
            own depth, as in the official pipeline). Needs ``fill``: the background
            part of a near-side edge pixel is the fill.
        split: how a pixel between two planes is shared (:func:`mpi.split_between_planes`):
            ``linear`` (over, with an opaque backing) or ``additive`` (the shares of an
            interval summed by the compositor, see :attr:`mpi.Layer.group`).
        slab_px: with ``split="additive"``: consecutive groups whose blur radii span at
            most this many pixels form one slab, summed before "over" (0: each group
            alone). Fewer seams where one surface crosses groups, and one layer per plane
            of a slab; two surfaces closer than this are then side by side rather than
            one in front (an error within a band of that many pixels).
        refine: ``"off"`` (the disparity is trusted: exact depth from a renderer) or
            ``"guided"`` (an unreliable, e.g. predicted, disparity: its edges are moved
            onto the colour edges first, :func:`mpib_validate.runtime.layers.refine.refine_disparity`),
            or ``"guided-thin"`` (the same, and structures thinner than the prediction's
            blur recovered from the local mean: ``thin=True``, no ``flip_px`` limit).
    """

    tolerance_px: float = 0.5
    planes: str = "adaptive"
    n_uniform: int = 32
    jump_px: float = 1.0
    fill: bool = True
    unmix_edges: bool = True
    split: str = "linear"
    slab_px: float = 0.0
    refine: str = "off"


@dataclass
class PassesInfo:
    planes: int = 0
    fill_fraction: float = 0.0
    edge_fraction: float = 0.0
    seconds: float = 0.0
    disparity_range: tuple = (0.0, 0.0)
    extra: dict = field(default_factory=dict)


#: Up to this many values :func:`content_intervals` with ``exact=False`` finds the
#: intervals exactly; beyond, on bins one plane step wide.
EXACT_INTERVALS_PX = 1 << 22


def content_intervals(values: np.ndarray, step: float,
                      exact: bool = True) -> list[tuple[float, float]]:
    """Disparity intervals that hold content: sorted values split where a gap exceeds
    one plane step (values rounded to 1e-12).

    ``exact=False`` (the memory estimate's: cheap on any input): beyond
    :data:`EXACT_INTERVALS_PX` values, the occupied bins one step wide (an O(n) count
    that can merge two intervals less than two steps apart: never fewer planes)."""
    v = np.asarray(values, np.float64).ravel()
    if not exact and v.size > EXACT_INTERVALS_PX:
        lo, hi = float(v.min()), float(v.max())
        b = ((v - lo) / step).astype(np.int64)
        n = int(b.max()) + 1
        ids = np.flatnonzero(np.bincount(b, minlength=n)) if n <= 1 << 24 else np.unique(b)
        breaks = np.flatnonzero(np.diff(ids) > 1)
        starts = ids[np.concatenate([[0], breaks + 1])]
        ends = ids[np.concatenate([breaks, [ids.size - 1]])]
        return [(lo + s * step, min(lo + (e + 1) * step, hi)) for s, e in zip(starts, ends)]
    v = np.round(v, 12)
    if v.size == 0:
        return []
    binned = _binned_intervals(v, step)
    if binned is not None:
        return binned
    v = np.unique(v)
    breaks = np.flatnonzero(np.diff(v) > step)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [v.size - 1]])
    return [(float(v[a]), float(v[b])) for a, b in zip(starts, ends)]


def _binned_intervals(v: np.ndarray, step: float):
    """:func:`content_intervals` without a full sort: the values grouped into bins one
    step wide (a radix sort of 16-bit bin numbers). A gap wider than a step can then only
    lie between the largest value of one occupied bin and the smallest of the next (the
    bins are monotone in the value), provided no bin spans more than a step itself
    (rounding at its edges); None where that fails or does not pay (then sort)."""
    if v.size < (1 << 16):
        return None
    lo, hi = float(v.min()), float(v.max())
    if not (np.isfinite(lo) and np.isfinite(hi) and step > 0):
        return None
    top = (hi - lo) / step
    if not top < 32000:
        return None
    b = ((v - lo) / step).astype(np.int16)
    order = np.argsort(b, kind="stable")
    counts = np.bincount(b, minlength=int(top) + 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[counts > 0]
    sv = v[order]
    bmin = np.minimum.reduceat(sv, starts)
    bmax = np.maximum.reduceat(sv, starts)
    if (bmax - bmin > step).any():
        return None
    breaks = np.flatnonzero(bmin[1:] - bmax[:-1] > step)
    first = np.concatenate([[0], breaks + 1])
    last = np.concatenate([breaks, [bmin.size - 1]])
    return [(float(bmin[a]), float(bmax[z])) for a, z in zip(first, last)]


#: An edge pixel is unmixed only if ``a c_n + (1 - a) c_f`` explains its colour to within
#: this fraction of the contrast ``|c_n - c_f|``; otherwise it stays whole.
UNMIX_RESIDUAL = 0.2


def _unmix(colour, near_colour, far_colour):
    """Coverage ``a`` of the near colour in ``c = a c_n + (1 - a) c_f`` (least squares),
    clamped to [0, 1], and whether that explains ``c`` (see ``UNMIX_RESIDUAL``)."""
    dn = near_colour - far_colour
    num = ((colour - far_colour) * dn).sum(axis=-1)
    den = (dn * dn).sum(axis=-1)
    a = np.clip(np.divide(num, den, out=np.ones_like(num), where=den > 1e-12), 0.0, 1.0)
    resid = np.linalg.norm(colour - far_colour - a[..., None] * dn, axis=-1)
    explained = (den > 1e-12) & (resid <= UNMIX_RESIDUAL * np.sqrt(den))
    return a, explained


#: Pure pixels further than this (px) from an edge pixel do not inform its unmixing.
UNMIX_REACH = 3.0


def _nearest_within(values: np.ndarray, source: np.ndarray, at: np.ndarray, reach: float):
    """For the flat pixel indices ``at``: the value of the nearest ``source`` pixel
    (Euclidean, ties in raster order of the offsets) no further than ``reach`` px, and
    whether there is one. Costs one gather per offset in the disk, on ``at`` only."""
    H, W = source.shape
    R = int(math.floor(reach))
    offsets = sorted(((dy * dy + dx * dx, dy, dx) for dy in range(-R, R + 1)
                      for dx in range(-R, R + 1) if dy * dy + dx * dx <= reach * reach))
    y, x = np.divmod(at, W)
    found = np.full(at.shape, -1, np.int64)
    for _, dy, dx in offsets:
        todo = np.flatnonzero(found < 0)
        if todo.size == 0:
            break
        yy, xx = y[todo] + dy, x[todo] + dx
        inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
        todo, yy, xx = todo[inside], yy[inside], xx[inside]
        hit = source[yy, xx]
        found[todo[hit]] = yy[hit] * W + xx[hit]
    ok = found >= 0
    out = np.zeros((at.size,) + values.shape[2:], values.dtype)
    out[ok] = values.reshape((H * W,) + values.shape[2:])[found[ok]]
    return out, ok


def _strongest_within(values: np.ndarray, source: np.ndarray, at: np.ndarray,
                      reference: np.ndarray, reach: float = 1.5):
    """For the flat pixel indices ``at``: the value of the ``source`` pixel no further
    than ``reach`` px whose mean channel differs most from ``reference`` (one row per
    index), and whether there is one. For a structure a pixel or two wide, its most
    covered pixel is the best estimate of its colour: the nearest may be a rim pixel of
    10 % coverage."""
    H, W = source.shape
    R = int(math.floor(reach))
    y, x = np.divmod(at, W)
    flat = values.reshape((H * W,) + values.shape[2:])
    ref = reference[:, :3].mean(axis=-1)
    best = np.full(at.shape, -1.0)
    found = np.full(at.shape, -1, np.int64)
    for dy in range(-R, R + 1):
        for dx in range(-R, R + 1):
            if dy * dy + dx * dx > reach * reach:
                continue
            yy, xx = y + dy, x + dx
            inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
            idx = np.where(inside, yy * W + xx, 0)
            hit = inside & source.ravel()[idx]
            contrast = np.abs(flat[idx, :3].mean(axis=-1) - ref)
            better = hit & (contrast > best)
            best = np.where(better, contrast, best)
            found = np.where(better, idx, found)
    ok = found >= 0
    out = np.zeros((at.size,) + values.shape[2:], values.dtype)
    out[ok] = flat[found[ok]]
    return out, ok


#: Colours agree (see :func:`known_background_mask`) within this difference of
#: ``c / (1 + c)`` (0.02 is about 2 % of a mid grey, above render noise of a converged
#: pass and below the change a shadow or a different surface makes).
KNOWN_COLOUR_TOL = 0.02


def known_background_mask(colour, disparity, far_field, near_next, known_rgb, known,
                          known_disparity=None) -> np.ndarray:
    """Where a render without the foreground shows the surface hidden behind it.

    A hidden pixel lies behind the near side of its nearest disparity jump; what is
    hidden there is the surface on the far side of that jump, at disparity
    ``far_field``. The known render shows *a* surface at every pixel, but behind a
    self-occlusion it shows a farther one (the wall behind Suzanne, not her own eye
    socket). It is used where:

    - with its disparity: the known surface is the far side's, i.e. nearer to
      ``far_field`` than half the jump: ``|d_known - d_far| < (d - d_far) / 2``;
    - without: at the nearest far-side pixel of a jump, the known render agrees with
      the visible colour (in ``c / (1 + c)``, within :data:`KNOWN_COLOUR_TOL`): the
      far side visible there is the known background's surface.

    Returns a boolean ``(H, W)`` map (also False where ``known`` is False).
    """
    from scipy import ndimage

    D = np.asarray(disparity, np.float64)
    use = np.asarray(known, bool).copy()
    ff = np.asarray(far_field, np.float64)
    if np.isnan(ff).all():
        return use
    if known_disparity is not None:
        kd = np.asarray(known_disparity, np.float64)
        return use & ~np.isnan(ff) & (np.abs(kd - ff) < 0.5 * np.maximum(D - ff, 0.0))
    k = np.maximum(np.asarray(known_rgb, np.float64)[..., :3], 0.0)
    c = np.maximum(np.asarray(colour, np.float64)[..., :3], 0.0)
    kc, cc = k / (1.0 + k), c / (1.0 + c)
    agree = (np.abs(kc - cc).max(axis=-1) <= KNOWN_COLOUR_TOL) & use
    # a seed (near side of a jump) is trusted when a far-side 4-neighbour at the jump's
    # far disparity agrees; each hidden pixel follows its nearest seed, as far_field does
    ff_safe = np.where(np.isnan(ff), -np.inf, ff)
    seed_ok = np.zeros(D.shape, bool)
    seed = np.zeros(D.shape, bool)
    H, W = D.shape
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        src = (slice(max(dy, 0), H + min(dy, 0)), slice(max(dx, 0), W + min(dx, 0)))
        dst = (slice(max(-dy, 0), H + min(-dy, 0)), slice(max(-dx, 0), W + min(-dx, 0)))
        far_here = D[src] < D[dst] - 0.5 * np.maximum(D[dst] - ff_safe[dst], 0.0)
        seed[dst] |= far_here & np.isfinite(near_next[src])
        seed_ok[dst] |= far_here & agree[src]
    if not seed.any():
        return np.zeros(D.shape, bool)
    _, (iy, ix) = ndimage.distance_transform_edt(~seed, return_indices=True)
    return use & seed_ok[iy, ix]


def layer_plan(values, blur_parameter: float, settings: PassesSettings,
               exact: bool = True, max_planes: int | None = None) -> LayerPlan:
    """The :class:`~mpib_validate.runtime.layers.mpi.LayerPlan` the builder follows for
    content at the disparities ``values`` (1/scene-unit): adaptive planes
    (:func:`~mpib_validate.runtime.layers.mpi.adaptive_planes`, spaced at most ``2 tol / A``)
    over the :func:`content_intervals`, or ``n_uniform`` planes up to the largest
    disparity; its layers and slabs for the setting's split and ``slab_px / A``.

    ``exact=False``: the intervals as :func:`content_intervals` estimates them (the
    memory estimate, on a disparity map before the fill: the builder's values are a
    subset of the map's). ``max_planes``: when more planes than that would be placed,
    the plan holds only their count (``planes`` None)."""
    A = blur_parameter
    if settings.planes == "uniform":
        v = np.asarray(values, np.float64)
        top = float(v.max()) if v.size else 0.0
        planes = uniform_planes(settings.n_uniform, max(top, 1e-9) * (1 + 1e-9))
    elif settings.planes == "adaptive":
        step = plane_spacing(A, settings.tolerance_px)
        intervals = content_intervals(values, step, exact)
        if max_planes is not None:
            count = sum(1 if hi <= lo else math.ceil(min((hi - lo) / step, 1e300)) + 1
                        for lo, hi in intervals)
            if count > max_planes:
                return LayerPlan(None, count, settings.split)
        planes = adaptive_planes(intervals, A, settings.tolerance_px)
    else:
        raise ValueError(f"planes must be 'adaptive' or 'uniform', got {settings.planes!r}")
    return plan_layers(planes, settings.split, settings.slab_px / A)


def mpi_from_sheets(sheets, blur_parameter: float, settings: PassesSettings, height: int,
                    width: int) -> MPI:
    """Cut ``sheets`` (far to near; :class:`~mpib_validate.runtime.layers.mpi.Sheet` or
    :class:`~mpib_validate.runtime.layers.mpi.Pixels`) into the planes of their
    :func:`layer_plan` (over the disparities that hold content, alpha > 0) with
    :func:`~mpib_validate.runtime.layers.mpi.layers_from_sheets`."""
    values = np.concatenate([np.asarray(sh.disparity, np.float64)[np.asarray(sh.alpha) > 0]
                             for sh in sheets])
    plan = layer_plan(values, blur_parameter, settings)
    return layers_from_sheets(sheets, plan, height, width, 0,
                              snap=SNAP_PX / blur_parameter)


def sheets_from_passes(colour: np.ndarray, disparity: np.ndarray, blur_parameter: float,
                       settings: PassesSettings = PassesSettings(),
                       background=None, progress=None) -> tuple[list, PassesInfo]:
    """The sheets (far to near) of a colour + disparity image, before they are cut into
    planes (see the module docstring): hidden-background fill, unmixed edge parts and
    the visible pixels. Returns them and the info (``planes`` not yet set).

    Args:
        colour: ``(H, W, 3)`` linear radiance (all in focus), or ``(H, W, 3 + E)`` with
            extra channels that travel with the colour (premultiplied like it; e.g. the
            film alpha of a transparent render as a fourth channel).
        disparity: ``(H, W)`` 1/scene-unit, 0 = infinitely far.
        blur_parameter: ``A`` (pixels per unit disparity); it sets the plane spacing and
            how far behind each edge the background is filled (both focus-independent).
        background: optional ``(colour (H, W, K), valid (H, W)[, disparity (H, W)])``:
            what a second render without the foreground shows (or a card scene's
            truth). It replaces the fill only where it shows the surface that is hidden
            there (see :func:`known_background_mask`): behind a self-occlusion (a brow
            over an eye socket) the hidden surface is the object's own, which that render
            does not show, and the fill is used.
        progress: optional ``progress(fraction)``, called between the steps; raising
            from it stops the work (how a caller cancels).
    """
    step_done = progress if progress is not None else (lambda fraction: None)
    t0 = time.perf_counter()
    rgb = np.asarray(colour, np.float64)
    D = np.asarray(disparity, np.float64)
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        raise PassError(f"colour must be (H, W, 3) or (H, W, 3 + extras), got {rgb.shape}")
    K = rgb.shape[2]
    if rgb.shape[:2] != D.shape:
        raise PassError(f"colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                        f"{D.shape[1]}x{D.shape[0]}")
    if not blur_parameter > 0:
        raise PassError(f"the blur parameter must be > 0 (a zero aperture has no defocus), "
                        f"got {blur_parameter}")
    H, W = D.shape
    if settings.refine in ("guided", "guided-thin"):
        from mpib_validate.runtime.layers.refine import refine_disparity

        thin = settings.refine == "guided-thin"
        D = refine_disparity(rgb, D, blur_parameter, thin=thin,
                             **({"flip_px": max(H, W)} if thin else {}))
    elif settings.refine != "off":
        raise ValueError(f"refine must be 'off', 'guided' or 'guided-thin', got "
                         f"{settings.refine!r}")
    if background is not None:
        known_rgb, known, known_d = (tuple(background) + (None,))[:3]
        shapes = [np.shape(known_rgb)[:2], np.shape(known)]
        if known_d is not None:
            shapes.append(np.shape(known_d))
        if any(tuple(sh) != D.shape for sh in shapes):
            raise PassError(f"the background is {np.shape(known_rgb)[1]}x"
                            f"{np.shape(known_rgb)[0]} but depth is {W}x{H}")
        if np.shape(known_rgb)[2] < K:
            raise PassError(f"the background has {np.shape(known_rgb)[2]} colour channels, "
                            f"the passes {K}")
    thr = settings.jump_px / blur_parameter
    info = PassesInfo(disparity_range=(float(D.min()), float(D.max())))

    jumps = _fill.disparity_jumps(D, thr)
    seed, _, near_next = jumps
    region, far_field, reach_far = _fill.occlusion_region(D, blur_parameter, thr,
                                                          jumps=jumps, reach=True)
    step_done(0.25)
    if not settings.fill:
        region[:] = False
    unmix = settings.unmix_edges and settings.fill
    farside = np.isfinite(near_next)
    band = (seed | farside) if unmix else np.zeros(D.shape, bool)
    # A far-side pixel that touches a nearer one only at a corner (the rim of a disk one
    # or two pixels across, whose anti-aliased ring takes the background's depth) is
    # unmixed too, but only around structures with no pure pixel of their own within
    # reach: the corner pixels of a larger object's staircase edge are left as they were
    # (unmixing those too cost 0.2 dB PSNR_ob on the card scenes).
    near_corner = _fill.nearer_diagonal(D, thr)
    corner = (~band & np.isfinite(near_corner)) if unmix else np.zeros(D.shape, bool)
    # which side of its nearest edge each pixel is on (near: in front of the far field)
    near_side = D > np.where(np.isnan(far_field), -np.inf, far_field) + 0.5 * thr
    if corner.any():
        ci = np.flatnonzero(corner)
        _, has_pure = _nearest_within(rgb, ~band & near_side, ci, UNMIX_REACH)
        corner.flat[ci[has_pure]] = False

    sheets_far, sheets_near = [], []
    visible = ~band
    flat_rgb = rgb.reshape(-1, K)
    flat_d = D.ravel()
    if settings.fill and (region.any() or band.any()):
        # background: filled only from pure pixels on the farther side of the edges
        bg_rgb = _fill.fill_hidden(rgb, D, region, far_field, thr, exclude=band | corner,
                                   reach_far=reach_far)
        if background is not None:
            use = known_background_mask(rgb, D, far_field, near_next, known_rgb, known,
                                        known_d)
            info.extra["background_used"] = float(use[region].mean()) if region.any() else 0.0
            bg_rgb = np.where(use[..., None], np.asarray(known_rgb, np.float64)[..., :K],
                              bg_rgb)
        flat_bg = bg_rgb.reshape(-1, K)
        step_done(0.45)
        hidden = np.flatnonzero(region | (band & seed))  # behind near-side edge pixels too
        # what is hidden lies on the far side of the nearest edge: its disparity is that
        # surface's (a push-pull average of depths would invent surfaces in between)
        ff = far_field.ravel()[hidden]
        hid_d = np.where(np.isnan(ff), flat_d[hidden], np.fmin(ff, flat_d[hidden]))
        sheets_far.append(Pixels(hidden, flat_bg[hidden], np.ones(hidden.size), hid_d))
        if band.any():
            # everything below is evaluated on the edge pixels only
            bi = np.flatnonzero(band | corner)
            on_near = seed.ravel()[bi]
            # nearest pure pixel of each side within UNMIX_REACH: local colours, no
            # averaging across texture (colours from further say nothing about the pixel)
            near_c, near_ok = _nearest_within(rgb, visible & near_side, bi, UNMIX_REACH)
            # a structure one or two pixels wide has no pure pixel: its own (mixed) pixels
            # are the best estimate of its colour for the far-side pixels around it
            far_own, far_ok = _nearest_within(rgb, visible & ~near_side & ~corner, bi,
                                              UNMIX_REACH)
            thin_c, thin_ok = _strongest_within(rgb, seed, bi, far_own)
            use_thin = ~near_ok & thin_ok & ~on_near
            near_c = np.where(use_thin[:, None], thin_c, near_c)
            near_ok = near_ok | use_thin
            c = flat_rgb[bi]
            far_c = np.where(on_near[:, None], flat_bg[bi], far_own)
            local = near_ok & (on_near | far_ok)
            near_d = np.where(on_near, flat_d[bi],
                              np.where(corner.ravel()[bi], near_corner.ravel()[bi],
                                       near_next.ravel()[bi]))
            a, explained = _unmix(c, near_c, far_c)
            # The depth says which side the pixel centre is on: keep a >= 1/4 on the near
            # side and <= 3/4 on the far side; a pixel the two colours do not explain is
            # left whole at its own depth.
            a = np.where(on_near, np.clip(a, 0.25, 1.0),
                         np.clip(a, 0.0, np.where(use_thin, 1.0, 0.75)))
            a = np.where(explained & local, a, np.where(on_near, 1.0, 0.0))
            # the side the depth names takes the rest of the colour, so that the pinhole
            # composite is the pixel's own colour
            a3 = a[:, None]
            near_c = np.where(on_near[:, None],
                              np.maximum((c - (1.0 - a3) * far_c) / np.maximum(a3, 1e-6), 0.0),
                              near_c)
            far_c = np.where(~on_near[:, None] & (a3 < 0.999),
                             np.maximum((c - a3 * near_c) / np.maximum(1.0 - a3, 1e-6), 0.0),
                             far_c)
            off = ~on_near  # far-side pixels keep their own (far) depth
            sheets_far.append(Pixels(bi[off], far_c[off], np.ones(int(off.sum())),
                                     flat_d[bi[off]]))
            sheets_near.append(Pixels(bi, near_c, a, near_d))
            info.edge_fraction = float(bi.size / D.size)
    shown = visible & ~corner if band.any() else visible
    # the visible sheet reads the caller's float32 colour when it has one (the same
    # values as ``rgb``; 24 B per pixel less while the layers are cut)
    given = colour if isinstance(colour, np.ndarray) else None
    vis = given if given is not None and given.dtype == np.float32 else rgb
    sheets = sheets_far + [Sheet((0, 0), vis, shown.astype(np.float64), D)] + sheets_near
    step_done(0.6)
    info.fill_fraction = float(region.mean())
    info.seconds = time.perf_counter() - t0
    return sheets, info


def layers_from_passes(colour: np.ndarray, disparity: np.ndarray, blur_parameter: float,
                       settings: PassesSettings = PassesSettings(),
                       background=None, progress=None) -> tuple[MPI, PassesInfo]:
    """Build the MPI of a colour + disparity image (see the module docstring): the
    sheets of :func:`sheets_from_passes` cut into planes by :func:`mpi_from_sheets`.
    Arguments as for :func:`sheets_from_passes`."""
    t0 = time.perf_counter()
    sheets, info = sheets_from_passes(colour, disparity, blur_parameter, settings,
                                      background, progress)
    mpi = mpi_from_sheets(sheets, blur_parameter, settings, *np.shape(disparity))
    if progress is not None:
        progress(1.0)
    info.planes = mpi.plane_count
    info.seconds = time.perf_counter() - t0
    return mpi, info
