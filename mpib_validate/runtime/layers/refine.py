"""Edge-aware refinement of an unreliable disparity map (a monocular prediction).

A predicted disparity is smooth across object edges and misregistered with the colour
by a pixel or two, so a layer split along its contour cuts the foreground inside or
outside its true outline: outer hairs blur away with the background, a halo of sharp
background hugs the object. Where the disparity jumps, the colour image knows better
where the edge is. :func:`refine_disparity` moves the disparity edges onto the colour
edges:

1. the uncertain band: pixels whose ``(2 r + 1)^2`` window spans a blur-radius range
   ``A (max d - min d) > jump_px`` (a disparity edge within ``r`` pixels), less what
   a smooth slope explains: a steep plane (the ground near the camera) spans more than
   ``jump_px`` too, so an edge must exceed by ``jump_px`` the range of a plane with the
   large-scale gradient (:func:`_edges`), and the refined values fade into the input's
   where an edge ends;
2. the two sides of each edge: ``d_hi`` and ``d_lo``, the window's maximum and minimum,
   and the predicted side ``m = d > (d_hi + d_lo) / 2`` (the ramp's mid-crossing);
3. the guided filter (He, Sun and Tang, PAMI 2013; colour guide, O(N) box filters) of
   ``m`` with the image as the guide: ``q = a^T I + b`` per window, fitted by least
   squares with ridge ``eps``, the coefficients averaged over the windows that hold each
   pixel. Where the colours of the two sides differ, ``q`` steps at the colour edge
   (guided feathering); where they do not, it is the box-blurred mask, whose
   mid-crossing is the predicted one. A second pass filters the sides ``q >= 1/2`` that
   the first gave (:data:`GUIDE_PASSES`): one pass undoes only part of an offset of
   several pixels. ``a`` and ``b`` are fitted at half resolution and interpolated back
   (He and Sun's fast guided filter, subsampling 2): they vary at the scale of the
   window, and the edge comes from the full-resolution ``I``;
4. each band pixel within ``flip_px`` of the predicted edge takes the side ``q >= 1/2``
   (deeper inside, its predicted side: a texture whose colours straddle the other
   side's would flip under the filter's linear colour model), then that side's value:
   the disparity of the nearest pixel outside the band on that side of the edge (the
   side of the nearest band pixel's mid-level), where one lies within ``3 r``; else
   ``d_hi`` or ``d_lo``. The ramp's in-between values become the surfaces they lie
   between, and a slanted surface continues with its own disparity instead of the
   window's extreme. Each band pixel then takes the mean of the values of the band
   pixels on its side in the 5x5 window around it (:func:`_smooth_sides`). Outside the
   band the disparity is unchanged.
5. no thin structure that the prediction does not hold (:func:`_thick_flips`,
   :func:`_no_new_slivers`; not with ``thin=True``, whose purpose they are): a pixel
   moved across the predicted edge by the colour keeps the move only where it joins a
   wide part of its new side, and where the colour moved pixels, a disparity structure
   narrower than 3 px that differs from both sides by more than ``jump_px`` of blur
   radius takes its surroundings' value. A colour line near an edge (a temple of
   sunglasses, a gap between boxes) otherwise became a line at the other side's depth:
   sharp inside the blur when that side is in focus, which a lens cannot do
   (:func:`mpib_validate.metrics.sharp_remnants` counts it).
6. no strip of background on the near side (:func:`_far_coloured_strips`; not with
   ``thin=True``): a network's map that overshoots an outline puts one there, beyond
   the colour's reach of ``flip_px``. Near-side pixels on the map's ramp, within a few
   pixels of the predicted edge, whose colour is much closer to the nearest far-side
   pixel's than to any of the near side's nearby colours, and which touch the far side
   through each other, go to the far side.

The guide is ``(c / (1 + c))^(1/2.2)`` of the linear colour (bounded for HDR, contrast
roughly as the eye sees it). Pure numpy/scipy; the guided filter runs only on the
boxes of 32 px tiles near the predicted edges (with a margin of what a pass reaches,
so the result is that of the whole image), cut into blocks that run on one thread per
core (:data:`MAX_THREADS`); ``mpib bench --suite photos`` states the cost at 2000x1333
against the rest of the pipeline.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from mpib_validate.runtime.resample import bilinear_separable, double, half


#: The guided filter's ridge (squared guide units; the guide is gamma-encoded, about
#: [0, 1]): colour contrast with a variance below it is smoothed, not followed. 1e-4 is
#: the variance of a noise of 2.5/255, about an 8-bit JPEG's. Measured with the degraded
#: disparity of the photos suite (PSNR_ob, default preset, `guided` with the window's
#: extremes as side values, before :data:`SIDE_REACH`; 12 Blender scenes
#: against Cycles; 8 card scenes per family against the tracer, degraded / exact depth):
#: 1e-2: Blender 28.80, constant 26.23 / 30.40, varying 30.27 / 31.92; 1e-3: 29.08,
#: 26.58 / 37.78, 30.58 / 32.34; 1e-4: 29.32, 26.61 / 38.03, 30.62 / 32.75; 3e-5 and 1e-5
#: within 0.1 dB of 1e-4 on each.
GUIDE_EPS = 1e-4


def box_mean(x: np.ndarray, r: int) -> np.ndarray:
    """Mean of ``x`` (``(H, W)`` or ``(H, W, C)``) over the ``(2r+1)^2`` window centred on
    each pixel, the window clipped at the borders (divided by the pixels it holds)."""
    from scipy import ndimage

    size = (2 * r + 1, 2 * r + 1) + (1,) * (x.ndim - 2)
    # uniform_filter with a constant-0 border, divided by the same filter of ones, is the
    # mean over the clipped window
    s = ndimage.uniform_filter(x, size, mode="constant", cval=0.0)
    # the same filter of ones is separable: the share of each axis's window inside the
    # image, below 1 only within r of a border, so only those rows and columns are divided
    H, W = x.shape[:2]
    sy, sx = _window_share(H, r), _window_share(W, r)
    top, bottom = slice(0, min(r, H)), slice(max(min(r, H), H - r), H)
    left, right = slice(0, min(r, W)), slice(max(min(r, W), W - r), W)
    middle = slice(top.stop, bottom.start)
    for rows, cols in ((top, slice(None)), (bottom, slice(None)),
                       (middle, left), (middle, right)):
        n = np.outer(sy[rows], sx[cols]).astype(x.dtype)
        s[rows, cols] /= n[..., None] if x.ndim == 3 else n
    return s


def _window_share(n: int, r: int) -> np.ndarray:
    """``(n,)``: the share of a ``2r+1`` window centred on each index that lies in ``[0, n)``."""
    i = np.arange(n)
    return (np.minimum(i + r, n - 1) - np.maximum(i - r, 0) + 1) / (2 * r + 1)


def guided_filter(guide: np.ndarray, p: np.ndarray, r: int, eps: float) -> np.ndarray:
    """The colour guided filter: ``q_i = mean_k(a_k)^T I_i + mean_k(b_k)`` over the windows
    ``k`` holding pixel ``i``, with ``a_k = (Sigma_k + eps U)^-1 cov_k(I, p)`` and
    ``b_k = mean_k(p) - a_k^T mean_k(I)`` (He et al. 2013, Eq. 19-21).

    Args:
        guide: ``(H, W, 3)`` guide image ``I`` (values of order 1).
        p: ``(H, W)`` input to filter.
        r: window radius (pixels); eps: ridge, in squared guide units (an edge whose
            contrast variance is below ``eps`` is smoothed rather than kept).

    Computed in float32 (the guide is about [0, 1] and ``eps`` 1e-4 or more, so the
    window variances keep 3 significant digits or more; the refinement only compares
    ``q`` with 1/2). :func:`guide_statistics` and :func:`guided_apply` are its two
    halves, for filtering several inputs with one guide.
    """
    stats = guide_statistics(guide, r, eps)
    return guided_apply(stats, p, r)


def guide_statistics(guide: np.ndarray, r: int, eps: float) -> tuple:
    """The part of :func:`guided_filter` that depends on the guide only: the guide
    ``I`` (float32), its window means ``mean_k(I)`` and ``(Sigma_k + eps U)^-1`` as the
    adjugate's six distinct entries and the determinant. Each channel is a separate
    contiguous ``(H, W)`` plane: a box filter of a plane runs about 1.3 times as fast as
    the same filter of a channel of an ``(H, W, C)`` stack, with the same sums."""
    I = [np.ascontiguousarray(np.asarray(guide[..., k], np.float32)) for k in range(3)]
    mI = [box_mean(c, r) for c in I]
    # covariance of the guide: 6 distinct entries of the symmetric 3x3 matrix
    idx = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    # a = (Sigma + eps U)^-1 cov(I, p), by the adjugate of the symmetric 3x3 matrix
    s00, s01, s02, s11, s12, s22 = (box_mean(I[i] * I[j], r) - mI[i] * mI[j]
                                    for i, j in idx)
    s00, s11, s22 = s00 + eps, s11 + eps, s22 + eps
    c00, c01, c02 = s11 * s22 - s12 * s12, s02 * s12 - s01 * s22, s01 * s12 - s02 * s11
    c11, c12, c22 = s00 * s22 - s02 * s02, s01 * s02 - s00 * s12, s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02  # > 0: Sigma is positive semi-definite
    return I, mI, (c00, c01, c02, c11, c12, c22), det


def guided_apply(stats: tuple, p: np.ndarray, r: int, guide=None, inner=None) -> np.ndarray:
    """:func:`guided_filter` of ``p`` with the guide's :func:`guide_statistics`
    (same ``r``).

    With ``guide`` (the full-resolution guide ``I`` as three ``(H, W)`` planes) and the
    statistics of the guide halved by :func:`half`, the fast guided filter (He and Sun,
    "Fast Guided Filter", 2015) with subsampling 2: ``p`` is halved too, ``a`` and ``b`` are fitted
    and window-averaged at half resolution (``r`` in half-resolution pixels), and
    ``q = up(mean(a))^T I + up(mean(b))`` with :func:`double` (bilinear) and the
    full-resolution ``I``: a quarter of the box filters, and the same edge, since ``a``
    and ``b`` vary at the scale of the window, not of the colour edge that ``I`` carries.
    ``q`` at a pixel depends on the guide and ``p`` within ``2 (2 r + 2)`` px of it.

    ``inner`` (``((y0, y1), (x0, x1))``, pixels of ``q``), if given, is the part of ``q``
    to return (the fast filter then interpolates that part only)."""
    I, mI, (c00, c01, c02, c11, c12, c22), det = stats
    p = np.asarray(p, np.float32)
    if guide is not None:
        p = half(p)
    mp = box_mean(p, r)
    v0, v1, v2 = (box_mean(I[k] * p, r) - mI[k] * mp for k in range(3))
    a = (c00 * v0 + c01 * v1 + c02 * v2, c01 * v0 + c11 * v1 + c12 * v2,
         c02 * v0 + c12 * v1 + c22 * v2)
    a = [ak / det for ak in a]
    b = mp - (a[0] * mI[0] + a[1] * mI[1] + a[2] * mI[2])
    ma = [box_mean(ak, r) for ak in a]
    mb = box_mean(b, r)
    if guide is None:
        q = ma[0] * I[0] + ma[1] * I[1] + ma[2] * I[2] + mb
        return q if inner is None else q[slice(*inner[0]), slice(*inner[1])]
    (y0, y1), (x0, x1) = inner or ((0, guide[0].shape[0]), (0, guide[0].shape[1]))
    # the half-resolution pixels that the bilinear doubling reads for rows y0..y1 - 1
    # (and columns): one more on each side, clipped (where the clamp is the image's)
    hy0, hx0 = max(0, y0 // 2 - 1), max(0, x0 // 2 - 1)
    hy1, hx1 = min(mb.shape[0], -(-y1 // 2) + 1), min(mb.shape[1], -(-x1 // 2) + 1)
    shape = (y1 - 2 * hy0, x1 - 2 * hx0)
    crop = (slice(y0 - 2 * hy0, None), slice(x0 - 2 * hx0, None))

    def up(x):
        return double(x[hy0:hy1, hx0:hx1], shape)[crop]

    q = up(mb)
    for k in range(3):
        q += up(ma[k]) * guide[k][y0:y1, x0:x1]
    return q


def colour_guide(colour: np.ndarray) -> np.ndarray:
    """``(c / (1 + c))^(1/2.2)`` of the first three (linear, >= 0) channels."""
    c = np.maximum(np.asarray(colour, np.float32)[..., :3], 0.0)
    g = c / (1.0 + c)
    with np.errstate(divide="ignore"):  # log 0 = -inf, and exp(-inf) = 0
        np.log(g, out=g)
    g *= np.float32(1.0 / 2.2)
    return np.exp(g, out=g)


def refine_disparity(colour: np.ndarray, disparity: np.ndarray, blur_parameter: float,
                     radius: int = 6, guide_radius: int = 8, eps: float = GUIDE_EPS,
                     jump_px: float = 2.0, keep_px: float = 0.0, flip_px: int = 3,
                     thin: bool = False) -> np.ndarray:
    """Disparity (``(H, W)``, same units as ``disparity``) with its edges moved onto the
    colour edges (see the module docstring for the steps).

    Args:
        colour: ``(H, W, 3+)`` linear radiance (all in focus).
        disparity: ``(H, W)`` 1/scene-unit, e.g. a monocular prediction.
        blur_parameter: ``A`` (px per unit disparity): edges are judged by the blur
            radius difference ``A |d_1 - d_2|`` they make.
        radius: ``r`` of the uncertain band and of the window's side values (pixels):
            at least the predicted edge's half-width plus its misregistration.
        guide_radius, eps: the guided filter's window radius (pixels; the filter runs at
            half resolution with half this radius, rounded) and ridge. Where
            the two sides' colours differ, a pixel between the colour edge and a mask
            edge ``s`` pixels off gets ``q`` near ``s / (2 guide_radius + 1)`` of the
            wrong side, so ``s`` up to about ``guide_radius / 2`` is undone (3 px at 8;
            4 corrected only 1 of a 2 px misregistration). ``eps``:
            :data:`GUIDE_EPS`.
        jump_px: an edge whose sides differ by less blur radius than this is left alone.
        keep_px: a band pixel on its predicted side keeps its own disparity when it is
            within this much blur radius of its side's value (0: never; measured: the
            nearest outside pixel's value is the better estimate, see
            :data:`SIDE_REACH`).
        flip_px: the colour may change a pixel's side only within this many pixels of
            the predicted edge (the misregistration it can undo).
        thin: also give structures thinner than the prediction's blur (wires, strands,
            whose predicted bump is a fraction of their jump) the near value that the
            local mean implies (see the code); use with a large ``flip_px`` so the
            colour can split a grid of wires from its gaps. It assumes the prediction
            keeps the local mean, and on exact depth it errs (``mpib bench --suite
            photos`` measures both).
    """
    D = np.asarray(disparity, np.float64)
    # each pixel's predicted side: above or below the mid-level of a window that reaches
    # flip_px (at most radius) beyond the band, so that a flat region next to the band
    # (hi == lo there in the band's own window) keeps its side instead of making a false
    # edge inside an object, where the colour of a texture would then flip pixels. The
    # four window extremes are taken on the threads at once.
    wide = 2 * (radius + min(flip_px, radius)) + 1
    hi, lo, w_hi, w_lo = _run_tasks(_max_min_tasks(D, 2 * radius + 1)
                                    + _max_min_tasks(D, wide))
    band = _jumps(hi, lo, blur_parameter, jump_px)
    if not band.any():
        return D.copy()
    f = 2 * flip_px + 1

    def predicted():
        m = D > 0.5 * (w_hi + w_lo)
        return m, _extreme(m, f, np.maximum) != _extreme(m, f, np.minimum)

    # the edges, and where the predicted side changes within flip_px, on two threads
    (band, weight), (m, flips) = _run_tasks(
        [lambda: _edges(D, band, hi, lo, blur_parameter, radius, jump_px), predicted])
    if not band.any():
        return D.copy()
    # the colour may move the side only within flip_px of the predicted edge: deeper
    # inside, a texture whose colours straddle the other side's (red and cyan stripes
    # before a grey wall) would flip under the guided filter's linear colour model
    zone = band & flips
    # the filter runs at half resolution (guided_apply), with windows of about the same
    # size; q at a pixel depends on the guide and the filtered mask within 2 (2 r + 2) px
    # of it per pass. The margin is even, so that every box halves on the image's grid.
    r_half = max(1, int(round(guide_radius / 2)))
    margin = 2 * (2 * r_half + 2) * GUIDE_PASSES

    def guided_box(box):
        y0, y1, x0, x1 = box
        Y0, Y1 = max(0, y0 - margin), min(D.shape[0], y1 + margin)
        X0, X1 = max(0, x0 - margin), min(D.shape[1], x1 + margin)
        guide = colour_guide(colour[Y0:Y1, X0:X1])
        stats = guide_statistics(half(guide), r_half, eps)
        guide = [np.ascontiguousarray(guide[..., k]) for k in range(3)]
        mb, zb = m[Y0:Y1, X0:X1], zone[Y0:Y1, X0:X1]
        p = mb
        for _ in range(GUIDE_PASSES - 1):
            p = np.where(zb, guided_apply(stats, p, r_half, guide) >= 0.5, mb)
        qb = guided_apply(stats, p, r_half, guide, ((y0 - Y0, y1 - Y0), (x0 - X0, x1 - X0)))
        return np.where(zone[y0:y1, x0:x1], qb >= 0.5, m[y0:y1, x0:x1])

    # the side q >= 1/2 in the zone (whose tiles the boxes cover), the predicted one elsewhere
    near = m.copy()
    boxes = list(_boxes(zone, TILE))
    for (y0, y1, x0, x1), nb in zip(boxes, _map_blocks(guided_box, boxes)):
        near[y0:y1, x0:x1] = nb
    if not thin:
        near = _thick_flips(near, m)
        near = _far_coloured_strips(colour, near, band & (D < lo + STRIP_TOP * (hi - lo)),
                                    band, m)
    if thin:
        # the degradation keeps the local mean: mean(d) = lo + f (hi - lo), f the near
        # fraction of the window; a structure thinner than the blur, whose window
        # maximum is a fraction of its jump, gets hi = lo + (mean(d) - lo) / f (for
        # 0.1 < f < 1/2: at most 10 times the mean's excess over lo)
        md = box_mean(D, radius)
        fn = box_mean(near.astype(np.float64), radius)
        with np.errstate(divide="ignore", invalid="ignore"):
            hi_t = lo + (md - lo) / fn
        thin_hi = band & (fn > 0.1) & (fn < 0.5)
    # each band pixel takes its side's value, written on the band pixels only, then the
    # mean of its side's values around it; with keep_px, one on its predicted side
    # within keep_px of its own value keeps that (at 0 the two are equal)
    out = D.copy()
    for box, at, h, l in _outside_side_blocks(D, band, hi, lo, SIDE_REACH * radius):
        if thin:
            t = thin_hi[box][at]
            h = np.where(t, np.maximum(hi_t[box][at], h), h)
        out[box][at] = np.where(near[box][at], h, l)
    out = _smooth_sides(out, band, near, SIDE_SMOOTH)
    if keep_px > 0:
        own = band & (near == m) & (blur_parameter * np.abs(D - out) <= keep_px)
        out[own] = D[own]
    if not thin:
        # slivers where the colour moved a pixel across the predicted edge (and next to it)
        moved = band & (near != m)
        grown = _extreme(moved, 3, np.maximum)
        out = _no_new_slivers(out, D, grown, blur_parameter, jump_px, moved)
    # D + weight (out - D), in place
    out -= D
    out *= weight
    out += D
    return out


#: Passes of the guided filter (:func:`refine_disparity`, step 3): each pass after the
#: first filters the sides that the last one gave in the flip zone (the predicted side
#: elsewhere), with the same guide statistics. One pass moves a mask edge that lies
#: ``s`` px off the colour edge only part of the way, so it leaves part of a larger
#: offset, as where a blurred and reduced map rounds off a card's corner (q 0.37 to
#: 0.49 on plainly brown pixels of a brown card before cyan). Measured with the default
#: preset and `guided` on the degraded maps; one pass -> two (-> three):
#:
#: - re-scoped PSNR_ob from exact depth: constant cards -4.73 -> -3.35 (-> -3.5) dB
#:   (constant-1 -8.0 -> -2.3, constant-5 -7.8 -> -3.5), varying -3.23 -> -3.14
#:   (-> -3.2), Blender scenes -0.53 -> -0.43;
#: - photographs: PSNR 40.29 -> 40.27 dB, remnants against the truth 590 -> 593, against
#:   the unrefined output where both maps blur 40 -> 42 with every row within 0.02 %
#:   (astronaut near 0.022 % -> 0.016 %);
#: - cost on the busy photograph at 2000x1333: about +0.2 s wall (1.58-1.70 ->
#:   1.74-2.06 s, alternated, load 1.2 to 1.4).
GUIDE_PASSES = 2


#: Side of the square (px) that a pixel moved across the predicted edge by the colour
#: must lie in, on its new side (:func:`_thick_flips`). Measured with the sliver step
#: on four scikit-image photographs and two network-like maps each, with and without
#: a 2 px fattening (focus near and far; sharp remnants against the true-disparity
#: render, summed, and mean PSNR against it): 5: 336 / 54 remnants, 40.68 / 42.01 dB;
#: 3: 371 / 65, 40.66 / 41.97; without either step: 404 / 77, 40.50 / 41.83.
FLIP_SQUARE = 5


def _thick_flips(near: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``near`` where the colour kept the predicted side ``m``; where it moved a pixel to
    the other side, only the pixels that lie in a :data:`FLIP_SQUARE` square of that side
    (a binary opening) keep the move, the others go back to ``m``. A colour structure a
    few pixels wide next to an edge (a temple of sunglasses, the gap between two boxes, a
    shadow line) is not a surface of the other side: moved, it became a line at the
    other side's depth, sharp when that side is in focus and the region blurred. An edge
    that moves by one or two pixels along its length moves as a whole: its pixels lie in
    squares of the side they join."""
    def opening(x):
        # binary opening by the FLIP_SQUARE square, the image's outside counted as True
        # (scipy's binary_opening with border_value=1): the erosion's windows clipped to
        # the box, the dilation's True within FLIP_SQUARE // 2 of its border
        k = FLIP_SQUARE // 2
        d = _extreme(_extreme(x, FLIP_SQUARE, np.minimum), FLIP_SQUARE, np.maximum)
        d[:k], d[-k:], d[:, :k], d[:, -k:] = True, True, True, True
        return d

    def kept(side, predicted):
        # the move stays where it joins a wide part of its side, or next to a structure
        # that the prediction itself holds thin (a wire of a renderer's exact depth,
        # whose anti-aliased rim the colour rightly moves)
        thin = predicted & ~opening(predicted)
        return (opening(side) | predicted
                | _extreme(thin, 3, np.maximum))

    moved = near != m
    out = near.copy()
    # on the boxes of the moved pixels only; a 5x5 opening, the thin test (another
    # opening) and its 3x3 dilation reach 2 (FLIP_SQUARE - 1) + 1 px
    def block(item):
        _, sub, inner = item
        n, p = near[sub], m[sub]
        return np.where(n, kept(n, p), ~kept(~n, ~p))[inner]

    blocks = list(_blocks(moved, 2 * (FLIP_SQUARE - 1) + 2))
    for (box, _, _), value in zip(blocks, _map_blocks(block, blocks)):
        out[box] = value
    return out


#: :func:`_far_coloured_strips`: how far (px) from a change of the predicted side a
#: near-side pixel may be given to the far side; the share of the window's jump above
#: which a pixel's input disparity is too near to be a strip (it must lie on the map's
#: ramp, below ``lo + STRIP_TOP (hi - lo)``); and how much closer to the far side's colour
#: than to the near side's its colour must be. Measured with the photographs' network-like
#: maps and the cards' degraded maps (``mpib bench --suite photos``; CHANGELOG,
#: 2026-12-04): without the ramp condition, or with the sides' local means as their only
#: colours, a grey card's rim before a blue-to-orange background went to the far side
#: (-4.6 and -3.5 dB on the constant cards against exact depth).
STRIP_REACH = 8
STRIP_TOP = 0.75
STRIP_RATIO = 0.5
#: The radius (px) of the near side's local mean colour, and the offsets (px) around a
#: pixel whose nearest near-side pixels also stand for that side's colours.
STRIP_MEAN_RADIUS = 16
STRIP_SAMPLE_PX = 4


def _far_coloured_strips(colour, near, candidates, band, m):
    """``near`` with the far-coloured strips on its near side given to the far side.

    A network's map that overshoots an outline puts a strip of the background on the
    near side, beyond the reach of the guided filter, which follows the mask where the
    strip's colour is uniform across the mask's edge; kept in focus with the object, the
    strip is sharp inside the blur around it (``metrics.sharp_remnants``). A pixel of
    ``candidates`` (band pixels on the map's ramp) on the near side, within
    :data:`STRIP_REACH` px of a change of the predicted side ``m``, is far-coloured where
    ``|c - c_far| < STRIP_RATIO * |c - c_near|``: ``c`` its guide colour (3x3 mean),
    ``c_far`` that of the nearest far-side pixel outside the band, ``c_near`` the closest
    to ``c`` of the near side's colours around it: the nearest near-side pixel outside
    the band to the pixel and to each of its 8 neighbours :data:`STRIP_SAMPLE_PX` px
    away, and the near side's mean over :data:`STRIP_MEAN_RADIUS` px (a textured near
    side has several colours). The far-coloured pixels connected to the far side through
    each other (8-connected) go to it. Computed on the blocks of the candidates' tiles,
    grown by the distance that the answer reads."""
    f = 2 * STRIP_REACH + 1
    close = _extreme(m, f, np.maximum) != _extreme(m, f, np.minimum)
    cand = candidates & near & close
    if not cand.any():
        return near
    # the nearest pixels outside the band lie within the band's width of a candidate;
    # the mean, the samples and the connectivity read a little farther
    margin = STRIP_MEAN_RADIUS + STRIP_SAMPLE_PX + 2 * STRIP_REACH

    def block(item):
        _, sub, inner = item
        return _strips_box(colour[sub], near[sub], cand[sub], band[sub])[inner]

    out = near.copy()
    blocks = list(_blocks(cand, margin))
    for (box, _, _), value in zip(blocks, _map_blocks(block, blocks)):
        out[box] = value
    return out


def _strips_box(colour, near, cand, band):
    """:func:`_far_coloured_strips` on one box: its ``near`` with the strips moved.
    Squared colour distances; the near side's colours are tried one after the other on
    the pixels that none so far has shown to be near-coloured."""
    from scipy import ndimage

    far_out, near_out = ~near & ~band, near & ~band
    if not far_out.any() or not near_out.any():
        return near
    g = colour_guide(colour)
    g = [box_mean(np.ascontiguousarray(g[..., k]), 1).ravel() for k in range(3)]
    H, W = near.shape
    ys, xs = np.nonzero(cand)
    flat = ys * W + xs
    c = [gk.take(flat) for gk in g]

    def dist2(at, idx):
        # squared colour distance from the pixels ``at`` (indices into ys, xs) to the
        # pixels of flat index ``idx``
        return sum((gk.take(idx) - ck[at]) ** 2 for gk, ck in zip(g, c))

    fy, fx = _nearest_in(far_out)
    alive = np.arange(ys.size)
    bound = dist2(alive, (fy * W + fx).ravel().take(flat)) / (STRIP_RATIO * STRIP_RATIO)
    del fy, fx
    # far-coloured: every near-side colour farther than bound (squared)
    ny, nx = _nearest_in(near_out)
    nearest = (ny * W + nx).ravel()
    del ny, nx
    offsets = (0, -STRIP_SAMPLE_PX, STRIP_SAMPLE_PX)
    for oy, ox in itertools.product(offsets, offsets):
        if not alive.size:
            break
        at = np.clip(ys[alive] + oy, 0, H - 1) * W + np.clip(xs[alive] + ox, 0, W - 1)
        alive = alive[dist2(alive, nearest.take(at)) > bound[alive]]
    if alive.size:
        r = STRIP_MEAN_RADIUS
        w = box_mean(near_out.astype(np.float32), r).ravel()
        at = flat[alive]
        share = w.take(at)
        d2 = sum((box_mean(gk.reshape(H, W) * near_out, r).ravel().take(at)
                  / np.maximum(share, 1e-6) - ck[alive]) ** 2 for gk, ck in zip(g, c))
        # a mean of fewer than 2 % of the window's pixels stands for nothing
        alive = alive[(share <= 0.02) | (d2 > bound[alive])]
    strip = np.zeros_like(near)
    strip[ys[alive], xs[alive]] = True
    far = ~near
    grown = ndimage.binary_propagation(far, structure=np.ones((3, 3), bool), mask=far | strip)
    return near & ~grown


#: :func:`_no_new_slivers`: passes of the 3x3 opening and closing (2: a sliver two
#: pixels wide on a slope goes too), and the jump (in units of ``jump_px``) a sliver
#: must make against both sides. One pass, or a jump of 3, score within 0.05 dB of these
#: on the varying cards with degraded depth (30.87, 30.92 against 30.87 dB PSNR_ob) and
#: also clear the test's temple line.
SLIVER_PASSES = 2
SLIVER_JUMP = 1.0
#: A pixel next to the moved ones, not moved itself, keeps its sliver where the input
#: has a bump (dip) of more than this much blur radius there (px): the trace of a strand
#: that the map blurred to a tenth of its jump. Without it the step took the fences' 1 px
#: strands for lines (degraded Blender scenes, PSNR_ob: fence-far 26.57 -> 24.98 dB,
#: with it 25.68; mean of 12: 29.49, with it 29.56, before the step 29.57).
TRACE_PX = 0.25


def _no_new_slivers(R: np.ndarray, D: np.ndarray, band: np.ndarray, blur_parameter: float,
                    jump_px: float, moved=None) -> np.ndarray:
    """``R`` with the structures narrower than 3 px that it has and ``D`` has not taken
    away on the band: where the grey opening of ``R`` (3x3 square) lies more than
    ``jump_px`` of blur radius below it, ``A (R - open(R)) > jump_px`` (a sliver nearer
    than both sides) and ``D`` has no such bump, the pixel takes ``open(R)``, the value
    of its surroundings; a sliver farther than both sides likewise takes the closing.
    Twice, so that a sliver two pixels wide on a slope goes too. With ``moved``, the
    pixels not in it keep a sliver wherever ``D`` has any trace of it (above
    :data:`TRACE_PX`). Side values from
    different outside pixels can leave such a line between two surfaces (a refined
    disparity nearer or farther than both sides of its edge); a lens cannot keep a line
    one pixel wide sharp inside a blur, and a colour cue that thin is no depth."""
    out = R.copy()
    margin = 8  # two openings and closings of a 3x3 square reach 4 px

    def block(item):
        _, sub, inner = item
        r, d, b = R[sub], D[sub], band[sub]
        # a pixel that was not moved itself keeps its sliver wherever the input has a
        # trace of it (a strand the map blurred to a tenth of its jump)
        limit = jump_px if moved is None else np.where(moved[sub], jump_px, TRACE_PX)
        # the input's own thin structures (a wire in a renderer's exact depth), within a
        # pixel of where they are: the refinement may have moved them by one
        d_bump = _extreme(blur_parameter * (d - _opening(d)), 3, np.maximum)
        d_dip = _extreme(blur_parameter * (_closing(d) - d), 3, np.maximum)
        for _ in range(SLIVER_PASSES):
            op, cl = _opening(r), _closing(r)
            bump = b & (blur_parameter * (r - op) > SLIVER_JUMP * jump_px) & (d_bump <= limit)
            dip = b & (blur_parameter * (cl - r) > SLIVER_JUMP * jump_px) & (d_dip <= limit)
            if not (bump.any() or dip.any()):
                break  # a pass that changes nothing leaves the next one nothing to change
            r = np.where(bump, op, np.where(dip, cl, r))
        return r[inner]

    blocks = list(_blocks(band, margin))
    for (box, _, _), value in zip(blocks, _map_blocks(block, blocks)):
        out[box] = value
    return out


def _smooth_sides(out: np.ndarray, band: np.ndarray, near: np.ndarray, s: int) -> np.ndarray:
    """``out`` with each band pixel's value replaced by the mean of the values of the
    band pixels on its side (``near`` equal to its own) in the ``(2s+1)^2`` window
    centred on it; in place, and returned. Neighbouring band pixels can take their
    values from outside pixels far apart along the edge, so on a slanted surface the
    side values are piecewise constant with steps of about a pixel of blur; the mean
    gives a ramp instead."""
    if s <= 0:
        return out
    from scipy import ndimage

    rows, cols = np.flatnonzero(band.any(axis=1)), np.flatnonzero(band.any(axis=0))
    y0, y1 = max(0, rows[0] - s), min(band.shape[0], rows[-1] + 1 + s)
    x0, x1 = max(0, cols[0] - s), min(band.shape[1], cols[-1] + 1 + s)
    box = (slice(y0, y1), slice(x0, x1))
    b, n, o = band[box], near[box], out[box]

    def sums(sel):  # the window's sum of the side's values, and its count (float32:
        # the mean's error is about 1e-7 of the disparity's range)
        num = np.where(sel, o, 0.0).astype(np.float32)
        return tuple(ndimage.uniform_filter(a, 2 * s + 1, mode="constant")
                     for a in (num, sel.astype(np.float32)))

    (num_n, den_n), (num_f, den_f) = _run_tasks([lambda: sums(b & n), lambda: sums(b & ~n)])
    num, den = np.where(n, num_n, num_f), np.where(n, den_n, den_f)
    np.divide(num, den, out=num, where=b)
    np.copyto(o, num, where=b)
    return out


#: Half-width (px) of the window over which :func:`refine_disparity` averages the side
#: values of the band pixels on one side (:func:`_smooth_sides`). Measured on the card
#: scenes with degraded maps (re-scoped PSNR_ob against the tracer): 2 gains about 0.45
#: dB over none; 1 missed the constant family's target and left more lines on the
#: photographs (CHANGELOG).
SIDE_SMOOTH = 2


#: How far (in units of the band radius) :func:`refine_disparity` looks for the nearest
#: pixel outside the band on each side of an edge: a band pixel lies within ``r`` of the
#: ramp, which spreads ``r`` at most to either side, so a side that exists lies within
#: about ``2 r``. Measured against the window's maximum and minimum as side values
#: (PSNR_ob, default preset, `guided`; 12 Blender scenes with degraded depth against
#: Cycles; 8 card scenes per family against the tracer, degraded / exact depth):
#: 29.32 -> 29.54 dB, constant 26.61 / 38.03 -> 26.83 / 38.25, varying 30.62 / 32.75 ->
#: 31.00 / 33.17 (keeping a band pixel's own value within 0.5 px of its side's, as
#: before: 29.42, 26.79 / 38.25, 30.95 / 33.22).
SIDE_REACH = 3


def _outside_side_blocks(D, band, hi, lo, reach) -> list:
    """The side values of the band pixels, as ``(box, at, hi_side, lo_side)`` per block
    of the band's tiles: the block's box (a pair of slices), its band pixels (index
    arrays into the box) and their two side values, the disparity of the nearest pixel
    outside the band whose disparity lies above (below or at) the mid-level
    ``(hi + lo) / 2`` of the band pixel nearest to it, where one lies within ``reach``
    px; else ``hi`` (``lo``). Clipped to ``[lo, hi]``. Exact Euclidean nearest (scipy's
    feature transform), computed on the blocks grown by ``2 reach``, which hold every
    pixel that the answer depends on (up to ties between equidistant pixels)."""
    def block(item):
        _, sub, inner = item
        return _outside_sides_box(D[sub], band[sub], hi[sub], lo[sub], reach, inner)

    blocks = list(_blocks(band, 2 * int(np.ceil(reach))))
    return [(box, *res) for (box, _, _), res in zip(blocks, _map_blocks(block, blocks))]


def _outside_sides_box(D, band, hi, lo, reach, inner=(slice(0, None), slice(0, None))):
    """:func:`_outside_side_blocks` on one box: ``(at, hi_side, lo_side)``, the band
    pixels of its ``inner`` part (a pair of slices; index arrays into that part) and
    their two side values."""
    mid = 0.5 * (hi + lo)
    nearest_band = _nearest_in(band)
    # a side value lies within reach of an inner band pixel: the nearest one of each side
    # is looked for in the inner part grown by reach (its pixels' nearest band pixels
    # lie within reach of them, in the box)
    (iy0, iy1, _), (ix0, ix1, _) = (s.indices(n) for s, n in zip(inner, band.shape))
    g = int(math.ceil(reach))
    cy0, cy1 = max(0, iy0 - g), min(band.shape[0], iy1 + g)
    cx0, cx1 = max(0, ix0 - g), min(band.shape[1], ix1 + g)
    crop = (slice(cy0, cy1), slice(cx0, cx1))
    mid_outside = mid[nearest_band[0][crop], nearest_band[1][crop]]
    del nearest_band
    D, band, hi, lo = D[crop], band[crop], hi[crop], lo[crop]
    W = band.shape[1]
    at = np.nonzero(band[iy0 - cy0:iy1 - cy0, ix0 - cx0:ix1 - cx0])
    y, x = at[0] + (iy0 - cy0), at[1] + (ix0 - cx0)
    flat = y * W + x  # the band pixels as flat indices: one take instead of two
    hi_at, lo_at = hi.ravel().take(flat), lo.ravel().take(flat)
    out = []
    for upper, fallback in ((True, hi_at), (False, lo_at)):
        sel = ~band & ((D > mid_outside) if upper else (D <= mid_outside))
        if not sel.any():
            out.append(fallback)
            continue
        iy, ix = (f.ravel().take(flat) for f in _nearest_in(sel))
        # the Euclidean distance as scipy's transform gives it, at the band pixels only
        dy, dx = iy - y, ix - x
        dist = np.sqrt((dy * dy + dx * dx).astype(np.float64))
        value = np.where(dist <= reach, D.ravel().take(iy * W + ix), fallback)
        out.append(np.minimum(np.maximum(value, lo_at), hi_at))
    return at, out[0], out[1]


def _nearest_in(mask: np.ndarray) -> np.ndarray:
    """``(2, H, W)``: for each pixel not in ``mask``, the indices of the nearest pixel of
    ``mask`` (scipy's exact Euclidean feature transform). Only the pixels of ``mask``
    with one outside it among their 8 neighbours can be the nearest (from any other, a
    step towards the pixel reaches a nearer one of ``mask``), so only they are seeds:
    the same answer, about twice as fast where ``mask`` is wide."""
    from scipy import ndimage

    edge = mask & ~_extreme(mask, 3, np.minimum)
    return ndimage.distance_transform_edt(~edge, return_distances=False, return_indices=True)


def _window_sides(D: np.ndarray, blur_parameter: float, radius: int, jump_px: float):
    """``(hi, lo, band)``: the maximum and minimum of ``D`` over each pixel's
    ``(2 radius + 1)^2`` window, and the uncertain band where they differ by more than
    ``jump_px`` of blur radius (``A (hi - lo) > jump_px``)."""
    hi, lo = _max_min(D, 2 * radius + 1)
    return hi, lo, _jumps(hi, lo, blur_parameter, jump_px)


def _jumps(hi: np.ndarray, lo: np.ndarray, blur_parameter: float, jump_px: float) -> np.ndarray:
    """The uncertain band: where a window's extremes differ by more than ``jump_px`` of
    blur radius, ``A (hi - lo) > jump_px``."""
    return blur_parameter * (hi - lo) > jump_px


def _extreme(x: np.ndarray, size: int, fn) -> np.ndarray:
    """``fn`` (``np.maximum`` or ``np.minimum``) of ``x`` (2-D) over each pixel's ``size x
    size`` window (``size`` odd) clipped to the array: scipy's maximum and minimum filters
    with the border repeated, or with a constant that cannot win. As ``size - 1`` shifted
    array operations per axis: for the small windows here, several times faster than
    scipy's running extremes (5 times on a 3x3 float window of a block, 15 times on a
    boolean 5x5), and exact."""
    r = size // 2
    out = x
    for axis in (0, 1):
        src = out
        n = src.shape[axis]
        if r < 1 or n < 2:
            out = src.copy()
            continue
        out = np.empty_like(src)
        for k in range(1, min(r, n - 1) + 1):
            a = (slice(0, n - k),) if axis == 0 else (slice(None), slice(0, n - k))
            b = (slice(k, n),) if axis == 0 else (slice(None), slice(k, n))
            if k == 1:  # the first shift writes the new array: no copy of src
                fn(src[a], src[b], out=out[a])
                last = (slice(n - 1, n),) if axis == 0 else (slice(None), slice(n - 1, n))
                out[last] = src[last]
            else:
                fn(out[a], src[b], out=out[a])
            fn(out[b], src[a], out=out[b])
    return out


def _opening(x: np.ndarray) -> np.ndarray:
    """Grey opening of ``x`` by a 3x3 square, border repeated (scipy's ``grey_opening``
    with ``mode="nearest"``)."""
    return _extreme(_extreme(x, 3, np.minimum), 3, np.maximum)


def _closing(x: np.ndarray) -> np.ndarray:
    """Grey closing of ``x`` by a 3x3 square, border repeated."""
    return _extreme(_extreme(x, 3, np.maximum), 3, np.minimum)


def _max_min(x: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The maximum and the minimum of ``x`` over each pixel's ``size x size`` window
    (the border repeated), the two filters on two threads where there are cores."""
    return tuple(_run_tasks(_max_min_tasks(x, size)))


def _max_min_tasks(x: np.ndarray, size: int) -> list:
    """:func:`_max_min` as two calls, for :func:`_run_tasks` with other work."""
    from scipy import ndimage

    return [lambda f=f: f(x, size, mode="nearest")
            for f in (ndimage.maximum_filter, ndimage.minimum_filter)]


def _run_tasks(tasks: list) -> list:
    """The results of calling each of ``tasks`` (no arguments), in order, on the
    threads of :func:`_map_blocks`."""
    return _map_blocks(lambda task: task(), tasks)


#: The large scale (px, a multiple of the band's ``radius``) over which a smooth slope
#: keeps its gradient (:func:`_edges`): a ground plane near the camera keeps it across
#: the frame, a predicted edge's ramp (a few to 20 px wide) over far less. At 4 r =
#: 24 px a step of ``J`` shows a gradient of ``J / 60`` per px, so an edge keeps
#: ``0.7 J`` of its range over the window's diagonal. Measured with the default preset
#: and `guided` on degraded maps (mean PSNR_ob, dB; photographs: PSNR against the
#: true-disparity render and remnants against it; with a chain's one-pixel inside
#: ramp): 4: Blender 29.86, constant cards 26.78, varying 30.81, photographs 40.26 dB /
#: 604; 8: 29.76, 26.77, 30.98, 39.99 / 631; the code before the slope test: 29.62,
#: 26.83, 31.00, 39.83 / 720.
SLOPE_SCALE = 4


def _edges(D, band, hi, lo, blur_parameter, radius, jump_px):
    """``(edges, weight)``: the pixels of the uncertain ``band`` that lie at an edge, and
    how much of the refinement each pixel takes.

    A plane's disparity is linear in the image; near the camera it is steep enough that
    its window spans more than ``jump_px`` of blur radius, and taken for an edge it was
    cut into flat patches with steps between them (seams across a ground plane's
    checks). A band pixel is at an edge when its window's range exceeds, by ``jump_px``
    of blur radius, the range that a plane with the large-scale gradient spans over the
    window's diagonal: ``A (max d - min d - 2 sqrt(2) r |grad(G_s * d)|) > jump_px``,
    ``s = SLOPE_SCALE r`` (px). ``weight`` is twice the share of edge pixels in the
    pixel's window, clipped to 1: where an edge fades into a slope, the refined values
    fade into the input's instead of ending in a step.

    The gradient is taken on ``D`` reduced 4 times (block means) and read back
    bilinearly: on the scale ``s`` it is smooth."""
    from scipy import ndimage

    f = 4
    H, W = D.shape
    h, w = -(-H // f), -(-W // f)
    small = np.pad(D, ((0, h * f - H), (0, w * f - W)), mode="edge")
    small = small.reshape(h, f, w, f).mean(axis=(1, 3))
    s = SLOPE_SCALE * radius / f
    grad = np.hypot(ndimage.gaussian_filter(small, s, order=(1, 0), mode="nearest"),
                    ndimage.gaussian_filter(small, s, order=(0, 1), mode="nearest"))
    # the range that slope spans over the window's diagonal, in blur radius (px)
    grad *= blur_parameter * 2.0 * math.sqrt(2.0) * radius / f
    slope = bilinear_separable(grad.astype(np.float32), (np.arange(H) + 0.5) / f - 0.5,
                               (np.arange(W) + 0.5) / f - 0.5)
    edges = band & (blur_parameter * (hi - lo) - slope > jump_px)
    weight = np.clip(2.0 * box_mean(edges.astype(np.float32), radius), 0.0, 1.0)
    return edges, weight


def uncertain_band(disparity: np.ndarray, blur_parameter: float, radius: int = 6,
                   jump_px: float = 2.0) -> np.ndarray:
    """Boolean ``(H, W)``: the pixels that :func:`refine_disparity` (same ``radius`` and
    ``jump_px``) may change, those within ``radius`` px of a disparity edge of more than
    ``jump_px`` of blur radius."""
    return _window_sides(np.asarray(disparity, np.float64), blur_parameter, radius,
                         jump_px)[2]


#: tile size (px) of the boxes that the guided filter runs on
TILE = 32


#: Largest side (px, a multiple of :data:`TILE`) of a box that the guided filter and the
#: side values run on: a box of a large photograph's edges is cut into blocks of at most
#: this side, each with its own margin, so that their working memory (about 350 bytes
#: per pixel of a box with its margin, measured) stays near 100 MB whatever the image
#: size; the result does not depend on the cut.
BLOCK_PX = 512


#: Most threads that work on the blocks at once (scipy's filters and numpy's arithmetic
#: release the GIL: 1.7 to 1.9 times the speed on 2 cores, measured). Each holds one
#: block's working set, about 100 MB (:data:`BLOCK_PX`), so 4 stay below the refocus
#: that follows on a photograph large enough to have that many blocks.
MAX_THREADS = 4


def _map_blocks(fn, items: list) -> list:
    """``[fn(item) for item in items]``, on up to :data:`MAX_THREADS` threads (one per
    core available) when there are several items; the order is kept."""
    from mpib_validate.runtime.cores import available_cores

    threads = min(len(items), available_cores(), MAX_THREADS)
    if threads <= 1:
        return [fn(item) for item in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads, thread_name_prefix="mpib-refine") as pool:
        return list(pool.map(fn, items))


def _blocks(mask: np.ndarray, margin: int):
    """``(out, sub, inner)`` slice pairs for each of :func:`_boxes` of ``mask``: the box
    in the image, the box grown by ``margin`` (clipped to the image) that a computation
    reads, and the box inside that grown box."""
    H, W = mask.shape
    for (y0, y1, x0, x1) in _boxes(mask, TILE):
        Y0, Y1 = max(0, y0 - margin), min(H, y1 + margin)
        X0, X1 = max(0, x0 - margin), min(W, x1 + margin)
        yield ((slice(y0, y1), slice(x0, x1)), (slice(Y0, Y1), slice(X0, X1)),
               (slice(y0 - Y0, y1 - Y0), slice(x0 - X0, x1 - X0)))


def _boxes(mask: np.ndarray, tile: int):
    """Boxes ``(y0, y1, x0, x1)`` covering ``mask``: the bounding boxes of the connected
    groups of ``tile x tile`` tiles that hold a True pixel (so the guided filter runs
    near the edges only; its result is the same as on the whole image), each cut into
    blocks of at most :data:`BLOCK_PX` a side (only the blocks that hold a True tile)."""
    from scipy import ndimage

    H, W = mask.shape
    th, tw = -(-H // tile), -(-W // tile)
    padded = np.zeros((th * tile, tw * tile), bool)
    padded[:H, :W] = mask
    coarse = padded.reshape(th, tile, tw, tile).any(axis=(1, 3))
    labels, _ = ndimage.label(coarse, structure=np.ones((3, 3), bool))
    step = max(1, BLOCK_PX // tile)  # tiles per block side
    for sl in ndimage.find_objects(labels):
        for ty in range(sl[0].start, sl[0].stop, step):
            for tx in range(sl[1].start, sl[1].stop, step):
                ty1, tx1 = min(ty + step, sl[0].stop), min(tx + step, sl[1].stop)
                if coarse[ty:ty1, tx:tx1].any():
                    yield (ty * tile, min(H, ty1 * tile), tx * tile, min(W, tx1 * tile))
