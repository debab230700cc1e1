"""Edge-aware refinement of an unreliable disparity map (a monocular prediction).

A predicted disparity is smooth across object edges and misregistered with the colour
by a pixel or two, so a layer split along its contour cuts the foreground inside or
outside its true outline: outer hairs blur away with the background, a halo of sharp
background hugs the object. Where the disparity jumps, the colour image knows better
where the edge is. :func:`refine_disparity` moves the disparity edges onto the colour
edges:

1. the uncertain band: pixels whose ``(2 r + 1)^2`` window spans a blur-radius range
   ``A (max d - min d) > jump_px`` (a disparity edge within ``r`` pixels; a smooth
   surface's slope spans less);
2. the two sides of each edge: ``d_hi`` and ``d_lo``, the window's maximum and minimum,
   and the predicted side ``m = d > (d_hi + d_lo) / 2`` (the ramp's mid-crossing);
3. the guided filter (He, Sun and Tang, PAMI 2013; colour guide, O(N) box filters) of
   ``m`` with the image as the guide: ``q = a^T I + b`` per window, fitted by least
   squares with ridge ``eps``, the coefficients averaged over the windows that hold each
   pixel. Where the colours of the two sides differ, ``q`` steps at the colour edge
   (guided feathering); where they do not, it is the box-blurred mask, whose
   mid-crossing is the predicted one;
4. each band pixel takes the side ``q >= 1/2``: its own disparity if that is its
   predicted side and within ``keep_px`` of blur radius of the side's value, else the
   side's value ``d_hi`` or ``d_lo`` (the ramp's in-between values become the
   surfaces they lie between). Outside the band the disparity is unchanged.

The guide is ``(c / (1 + c))^(1/2.2)`` of the linear colour (bounded for HDR, contrast
roughly as the eye sees it). Pure numpy/scipy; cost is a few dozen full-image box
filters (``mpib bench --suite photos`` states it against the rest of the pipeline).
"""

from __future__ import annotations

import numpy as np


def box_mean(x: np.ndarray, r: int) -> np.ndarray:
    """Mean of ``x`` (``(H, W)`` or ``(H, W, C)``) over the ``(2r+1)^2`` window centred on
    each pixel, the window clipped at the borders (divided by the pixels it holds)."""
    from scipy import ndimage

    size = (2 * r + 1, 2 * r + 1) + (1,) * (x.ndim - 2)
    # uniform_filter with a constant-0 border, divided by the same filter of ones, is the
    # mean over the clipped window
    s = ndimage.uniform_filter(x, size, mode="constant", cval=0.0)
    n = ndimage.uniform_filter(np.ones(x.shape[:2]), size[:2], mode="constant", cval=0.0)
    return s / (n[..., None] if x.ndim == 3 else n)


def guided_filter(guide: np.ndarray, p: np.ndarray, r: int, eps: float) -> np.ndarray:
    """The colour guided filter: ``q_i = mean_k(a_k)^T I_i + mean_k(b_k)`` over the windows
    ``k`` holding pixel ``i``, with ``a_k = (Sigma_k + eps U)^-1 cov_k(I, p)`` and
    ``b_k = mean_k(p) - a_k^T mean_k(I)`` (He et al. 2013, Eq. 19-21).

    Args:
        guide: ``(H, W, 3)`` guide image ``I`` (values of order 1).
        p: ``(H, W)`` input to filter.
        r: window radius (pixels); eps: ridge, in squared guide units (an edge whose
            contrast variance is below ``eps`` is smoothed rather than kept).
    """
    I = np.asarray(guide, np.float64)
    p = np.asarray(p, np.float64)
    mI = box_mean(I, r)
    mp = box_mean(p, r)
    cIp = box_mean(I * p[..., None], r) - mI * mp[..., None]
    # covariance of the guide: 6 distinct entries of the symmetric 3x3 matrix
    idx = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    prods = np.stack([I[..., i] * I[..., j] for i, j in idx], axis=-1)
    mII = box_mean(prods, r)
    S = np.empty(I.shape[:2] + (3, 3))
    for k, (i, j) in enumerate(idx):
        S[..., i, j] = S[..., j, i] = mII[..., k] - mI[..., i] * mI[..., j]
    S[..., 0, 0] += eps
    S[..., 1, 1] += eps
    S[..., 2, 2] += eps
    a = np.linalg.solve(S, cIp[..., None])[..., 0]
    b = mp - (a * mI).sum(axis=-1)
    return (box_mean(a, r) * I).sum(axis=-1) + box_mean(b, r)


def colour_guide(colour: np.ndarray) -> np.ndarray:
    """``(c / (1 + c))^(1/2.2)`` of the first three (linear, >= 0) channels."""
    c = np.maximum(np.asarray(colour, np.float64)[..., :3], 0.0)
    return (c / (1.0 + c)) ** (1.0 / 2.2)


def refine_disparity(colour: np.ndarray, disparity: np.ndarray, blur_parameter: float,
                     radius: int = 6, guide_radius: int = 8, eps: float = 1e-3,
                     jump_px: float = 2.0, keep_px: float = 0.5) -> np.ndarray:
    """Disparity (``(H, W)``, same units as ``disparity``) with its edges moved onto the
    colour edges (see the module docstring for the steps).

    Args:
        colour: ``(H, W, 3+)`` linear radiance (all in focus).
        disparity: ``(H, W)`` 1/scene-unit, e.g. a monocular prediction.
        blur_parameter: ``A`` (px per unit disparity): edges are judged by the blur
            radius difference ``A |d_1 - d_2|`` they make.
        radius: ``r`` of the uncertain band and of the side values (pixels): at least
            the predicted edge's half-width plus its misregistration.
        guide_radius, eps: the guided filter's window radius (pixels) and ridge. Where
            the two sides' colours differ, a pixel between the colour edge and a mask
            edge ``s`` pixels off gets ``q`` near ``s / (2 guide_radius + 1)`` of the
            wrong side, so ``s`` up to about ``guide_radius / 2`` is undone (3 px at 8;
            4 corrected only 1 of a 2 px misregistration).
        jump_px: an edge whose sides differ by less blur radius than this is left alone.
        keep_px: a band pixel keeps its own disparity when it is within this much blur
            radius of its side's value.
    """
    from scipy import ndimage

    D = np.asarray(disparity, np.float64)
    size = 2 * radius + 1
    hi = ndimage.maximum_filter(D, size, mode="nearest")
    lo = ndimage.minimum_filter(D, size, mode="nearest")
    band = blur_parameter * (hi - lo) > jump_px
    if not band.any():
        return D.copy()
    mid = 0.5 * (hi + lo)
    m = (D > mid).astype(np.float64)
    q = guided_filter(colour_guide(colour), m, guide_radius, eps)
    near = q >= 0.5
    side = np.where(near, hi, lo)
    own = (near == (m > 0.5)) & (blur_parameter * np.abs(D - side) <= keep_px)
    return np.where(band & ~own, side, D)
