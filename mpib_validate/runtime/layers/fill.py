"""Occlusion regions and the hidden-background fill, with no learned weights.

A colour + depth render holds nothing behind the foreground, but a defocused view sees
some of it. Where a foreground pixel at disparity ``d_n`` borders background at ``d_f``
(a disparity jump), the aperture shifts the two layers against each other by up to
``A (d_n - d_f)`` pixels, so background hidden up to that distance behind the
foreground edge becomes visible. :func:`occlusion_region` finds those pixels the
paper's way: a disparity-gradient seed, grown towards the occluder by that amount
(exact, since the jump and ``A`` are known; it does not depend on the focus, so one
MPI serves every focus setting).

:func:`push_pull` fills them with a weighted push-pull pyramid (Gortler et al. 1996)
that draws only from pixels on the farther side of the edge, so the foreground's
colour never leaks into the background behind it.
"""

from __future__ import annotations

import math

import numpy as np


def jump_pixels(disparity: np.ndarray, threshold: float) -> np.ndarray:
    """Both sides of every 4-neighbour disparity jump larger than ``threshold``: the
    pixels the layer builder treats as edge pixels (:func:`disparity_jumps` marks the
    near side and gives the disparities across)."""
    d = np.asarray(disparity, np.float64)
    mask = np.zeros(d.shape, bool)
    dx = np.abs(np.diff(d, axis=1)) > threshold
    dy = np.abs(np.diff(d, axis=0)) > threshold
    mask[:, :-1] |= dx
    mask[:, 1:] |= dx
    mask[:-1] |= dy
    mask[1:] |= dy
    return mask


def disparity_jumps(disparity: np.ndarray, threshold: float):
    """Near-side pixels of 4-neighbour disparity jumps larger than ``threshold``.

    Returns ``(seed, far, near)``: boolean map of the near-side pixels, the smallest
    far-side disparity next to each (inf elsewhere), and the largest near-side disparity
    next to each far-side pixel (-inf elsewhere).
    """
    D = np.asarray(disparity, np.float64)
    far = np.full(D.shape, np.inf)
    near = np.full(D.shape, -np.inf)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        da, db = D[a], D[b]
        diff = da - db
        jump_ab = diff > threshold  # a nearer than b
        jump_ba = np.negative(diff, out=diff) > threshold  # db - da, exactly
        # in place where the jump is (the views far[a], ... are written through)
        np.minimum(far[a], db, out=far[a], where=jump_ab)
        np.minimum(far[b], da, out=far[b], where=jump_ba)
        np.maximum(near[b], da, out=near[b], where=jump_ab)
        np.maximum(near[a], db, out=near[a], where=jump_ba)
    return np.isfinite(far), far, near


def nearer_diagonal(disparity: np.ndarray, threshold: float) -> np.ndarray:
    """The largest disparity among a pixel's four diagonal neighbours that is nearer
    than the pixel by more than ``threshold`` (-inf where none is)."""
    D = np.asarray(disparity, np.float64)
    near = np.full(D.shape, -np.inf)
    H, W = D.shape
    for dy, dx in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        ys = slice(max(dy, 0), H + min(dy, 0))
        yd = slice(max(-dy, 0), H + min(-dy, 0))
        xs = slice(max(dx, 0), W + min(dx, 0))
        xd = slice(max(-dx, 0), W + min(-dx, 0))
        nb = D[ys, xs]  # the neighbour at (y + dy, x + dx) of pixel (y, x) = D[yd, xd]
        own = D[yd, xd]
        np.maximum(near[yd, xd], nb, out=near[yd, xd], where=nb - own > threshold)
    return near


def occlusion_region(disparity: np.ndarray, blur_parameter: float, threshold: float,
                     levels: float = 1.5, jumps=None, reach: bool = False):
    """Pixels on the near side of a disparity jump, within ``A (d_near - d_far)`` of it.

    Seeds are grouped by radius into geometric buckets (ratio ``levels``); each bucket is
    grown with one Euclidean distance transform by its largest radius, so the region is
    never smaller than the exact union of disks (at most ``levels`` times wider).
    Only pixels nearer than the far side of their nearest seed (by more than half the
    threshold) belong to the region.

    ``jumps`` may pass :func:`disparity_jumps` of the same disparity and threshold, if
    already computed.

    Returns ``(region, far_disparity)``: the boolean region and, for every pixel, the
    far-side disparity of its nearest seed (the disparity of what is hidden there;
    ``nan`` when the image has no jump). With ``reach``, a third map: the far side of
    the nearest seed *whose bucket reaches the pixel* (that of the nearest seed where
    none does), for :func:`fill_hidden`.
    """
    from scipy import ndimage

    D = np.asarray(disparity, np.float64)
    seed, far, _ = jumps if jumps is not None else disparity_jumps(D, threshold)
    region = np.zeros(D.shape, bool)
    if not seed.any():
        none = np.full(D.shape, np.nan)
        return (region, none, none.copy()) if reach else (region, none)
    radius = np.where(seed, blur_parameter * (D - np.where(seed, far, D)), 0.0)
    iy, ix = ndimage.distance_transform_edt(~seed, return_distances=False, return_indices=True)
    far_field = far[iy, ix]
    r = radius[seed]
    lo, hi = max(r.min(), 1.0), max(r.max(), 1.0)
    n_levels = 1 + int(math.ceil(math.log(hi / lo) / math.log(levels))) if hi > lo else 1
    edges = lo * levels ** np.arange(n_levels + 1)
    if reach:
        best = np.full(D.shape, np.inf)  # distance to the nearest seed whose bucket reaches
        reach_far = far_field.copy()  # that seed's far side (the nearest seed's if none)
    for k in range(n_levels):
        bucket = seed & (radius <= edges[k + 1]) & ((radius > edges[k]) if k else True)
        if not bucket.any():
            continue
        # only pixels within R of the bucket can join: the transform runs on the
        # bucket's box grown by R (it holds every seed of the bucket, so each distance
        # there is the full frame's)
        R = math.ceil(radius[bucket].max())
        y0, y1, x0, x1 = _grown_box(bucket, R)
        if reach:
            dist, (jy, jx) = ndimage.distance_transform_edt(~bucket[y0:y1, x0:x1],
                                                            return_indices=True)
            box_best = best[y0:y1, x0:x1]
            nearer = dist <= np.minimum(R, box_best)
            box_best[nearer] = dist[nearer]
            reach_far[y0:y1, x0:x1][nearer] = far[y0:y1, x0:x1][jy[nearer], jx[nearer]]
        else:
            dist = ndimage.distance_transform_edt(~bucket[y0:y1, x0:x1])
        region[y0:y1, x0:x1] |= dist <= R
    region &= D > far_field + 0.5 * threshold
    return (region, far_field, reach_far) if reach else (region, far_field)


def _grown_box(mask: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)``: the bounding box of a non-empty ``mask`` grown by
    ``margin`` pixels on every side, clipped to the image."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return (max(rows[0] - margin, 0), min(rows[-1] + margin + 1, mask.shape[0]),
            max(cols[0] - margin, 0), min(cols[-1] + margin + 1, mask.shape[1]))


def push_pull(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Fill a ``(H, W, C)`` image from the pixels with weight > 0 (Gortler et al. 1996).

    Pull: build a pyramid of weighted 2x2 means, each level's weight clamped to 1.
    Push: from coarse to fine, ``v = w v + (1 - w) up(v_coarse)`` with bilinear ``up``.
    Pixels with weight 1 keep their value exactly; where no pixel has weight, zeros.
    """

    v = np.asarray(values, np.float64)
    w = np.clip(np.asarray(weights, np.float64), 0.0, 1.0)
    if not (w > 0).any():
        return np.zeros_like(v)
    pyr = []
    cur_v, cur_w = v * w[..., None], w
    while True:
        pyr.append((cur_v, cur_w))
        h, wd = cur_w.shape
        if h <= 1 and wd <= 1:
            break
        ph, pw = h + (h % 2), wd + (wd % 2)
        if (ph, pw) == (h, wd):  # even: nothing to pad (zeros would add nothing)
            pv, pwgt = cur_v, cur_w
        else:
            pv = np.zeros((ph, pw, v.shape[2]))
            pwgt = np.zeros((ph, pw))
            pv[:h, :wd], pwgt[:h, :wd] = cur_v, cur_w
        sv = _sum2x2(pv)
        sw = _sum2x2(pwgt)
        # normalised colour times clamped weight (premultiplied again)
        mean = np.divide(sv, sw[..., None], out=np.zeros_like(sv), where=sw[..., None] > 0)
        cw = np.minimum(sw, 1.0)
        cur_v, cur_w = mean * cw[..., None], cw
    # push
    filled = np.divide(pyr[-1][0], pyr[-1][1][..., None], out=np.zeros_like(pyr[-1][0]),
                       where=pyr[-1][1][..., None] > 0)
    binary = bool(((w == 0) | (w == 1)).all())
    for level, (lv, lw) in reversed(list(enumerate(pyr[:-1]))):
        up = _upsample2(filled, lw.shape)
        if level == 0 and binary:
            # weights 0 or 1: w own + (1 - w) up is own or up (+ 0.0, as the sum gives +0
            # for -0), the same bits without the blend
            filled = np.where(lw[..., None] > 0, lv, up)
            filled += 0.0
            continue
        own = np.divide(lv, lw[..., None], out=np.zeros_like(lv), where=lw[..., None] > 0)
        filled = lw[..., None] * own + (1.0 - lw[..., None]) * up
    return filled


def _sum2x2(a: np.ndarray) -> np.ndarray:
    """Sums of 2x2 blocks (even height and width); four strided adds are several times
    faster than a reshape-and-sum."""
    return a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]


def _upsample2(coarse: np.ndarray, shape) -> np.ndarray:
    """Bilinear 2x up-sampling with pixel-area alignment (fine pixel i sits at coarse
    coordinate (i + 0.5) / 2 - 0.5), edges clamped; separable, so two passes of
    weights 3/4 and 1/4."""
    def axis_up(a, n, ax):
        # with slices: fine index 2k is 3/4 coarse k + 1/4 coarse k - 1, fine 2k + 1 is
        # 3/4 coarse k + 1/4 coarse k + 1 (indices clamped to the coarse range)
        def sl(*args):
            idx = [slice(None)] * a.ndim
            idx[ax] = slice(*args)
            return tuple(idx)

        m = a.shape[ax]
        ne, no = (n + 1) // 2, n // 2
        shape_out = list(a.shape)
        shape_out[ax] = n
        out = np.empty(shape_out)
        ev, od = out[sl(0, None, 2)], out[sl(1, None, 2)]
        np.multiply(a[sl(0, ne)], 0.75, out=ev)
        ev[sl(1, None)] += 0.25 * a[sl(0, ne - 1)]
        ev[sl(0, 1)] += 0.25 * a[sl(0, 1)]
        np.multiply(a[sl(0, no)], 0.75, out=od)
        last = min(no, m - 1)  # odd fine indices whose k + 1 is a coarse index
        od[sl(0, last)] += 0.25 * a[sl(1, last + 1)]
        if last < no:
            od[sl(last, None)] += 0.25 * a[sl(m - 1, m)]
        return out

    return axis_up(axis_up(coarse, shape[0], 0), shape[1], 1)


#: How near (px) a region pixel hiding a deeper surface must be for :func:`fill_hidden`
#: to take a pixel for part of its occluder: the half-width of the refinement's
#: uncertain band (``refine.uncertain_band``, radius 6), within which the steps that a
#: refined map leaves inside a surface lie. Measured against 4 px on the photographs'
#: remnant table: 4 px gives fewer sharp edges on coffee far (29 against 44) but loses
#: 0.03 dB on motorcycle far and 0.01 dB on chelsea far.
OCCLUDER_PX = 6


def fill_hidden(colour: np.ndarray, disparity: np.ndarray, region: np.ndarray,
                far_disparity: np.ndarray, threshold: float, exclude=None, reach_far=None):
    """Colour and disparity of the background hidden in ``region``.

    Sources are pixels outside ``region`` (and outside ``exclude``, e.g. mixed edge
    pixels) whose disparity is no nearer than the far side of their nearest jump (plus
    half the threshold): only the farther side feeds the fill.

    With ``reach_far`` (the third map of :func:`occlusion_region` with ``reach``), a
    pixel is no source either where it is part of the occluder of a region pixel next
    to it: nearer than the far side of the nearest jump that reaches it, and within
    :data:`OCCLUDER_PX` of a region pixel whose hidden surface lies deeper than it. A
    small step inside a near surface (a refined map's step of one or two pixels of
    blur) is the nearest jump of the pixels just past it, which thus passed as far-side
    pixels: they fed the fill behind the surface's own silhouette with the surface's
    colour, a patch in focus at the far surface's depth showing through the blurred
    silhouette. Pixels past such a step with no deeper hidden surface next to them
    stay sources (the fill behind the step itself needs them).

    Colour is averaged in the compressed domain ``c / (1 + c)`` (then expanded back),
    so that an HDR highlight near the edge is not smeared over the whole fill: the fill
    guesses ordinary background, not bokeh balls.

    Returns the colour ``(H, W, 3)``, filled everywhere (use it inside the region).
    The hidden disparity is not filled: it is that of the far side of the nearest jump
    (``far_disparity``), since an average of depths would invent surfaces in between.
    """
    D = np.asarray(disparity, np.float64)
    ref = np.where(np.isnan(far_disparity), np.inf, far_disparity)
    source = ~region & (D <= ref + 0.5 * threshold)
    if reach_far is not None:
        cand = source & (D > np.where(np.isnan(reach_far), np.inf, reach_far)
                         + 0.5 * threshold)
        if cand.any():
            from scipy import ndimage

            # the deepest hidden surface among the region pixels within OCCLUDER_PX,
            # on the candidates' box grown by that much
            p = OCCLUDER_PX
            y0, y1, x0, x1 = _grown_box(cand, p)
            yy, xx = np.mgrid[-p:p + 1, -p:p + 1]
            hidden = np.where(region[y0:y1, x0:x1], ref[y0:y1, x0:x1], np.inf)
            deepest = ndimage.grey_erosion(hidden, footprint=yy ** 2 + xx ** 2 <= p * p,
                                           mode="nearest")
            box = cand[y0:y1, x0:x1]
            box &= deepest < D[y0:y1, x0:x1] - 0.5 * threshold
            source[y0:y1, x0:x1] &= ~box
    if exclude is not None:
        source &= ~exclude
    c = np.maximum(np.asarray(colour, np.float64), 0.0)
    out = push_pull(c / (1.0 + c), source.astype(np.float64))
    v = np.clip(out, 0.0, 1.0 - 1e-9)
    return v / (1.0 - v)
