"""The matting variant of the default refocus, for comparison (``mpib bench --suite photos``).

The default layers split a photograph's edge pixels by the refined disparity and unmix
only a one-pixel rim (:mod:`mpib_validate.runtime.layers.passes`). The variant mattes a
wider band instead: pymatting's closed-form matte (Levin, Lischinski and Weiss, PAMI
2008: ``alpha`` minimises ``alpha^T L alpha`` with the matting Laplacian ``L`` of 3x3
windows, in which the colour is locally a linear function of ``alpha``) in the pixels
within :data:`BAND_PX` of the refined map's jumps, the pixels beyond the band known near
or far as the layer builder tells them (in front of the far side of the nearest edge, or
not); its foreground and background colours by
``estimate_foreground_ml`` (Germer et al. 2020). In the band the nearer layer gets the
foreground colour with ``alpha`` at the nearest known near pixel's disparity, the
farther layer the background colour (alpha 1) at the nearest known far pixel's; the
rest of the layers are the default's.

It is not used by the refocus: measured on the photographs, cards and Blender scenes it
scores below the default (``docs/photos.md``, Sharp remnants). The bench shows it so that
a reader can see why.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Half-width (px) of the band around the refined map's jumps whose alpha the matte
#: decides: the 1.5 px shift of a network-like map plus its 2 px fattening, rounded up.
BAND_PX = 4


def matte_sheets(colour: np.ndarray, disparity: np.ndarray, blur_parameter: float,
                 settings, gamma: float = 2.2) -> list:
    """The default's sheets of ``colour`` (``(H, W, 3+)`` linear; the first three
    channels are used) over the already refined ``disparity`` (``settings.refine`` is
    not applied again), with the band around its jumps matted (see the module
    docstring). The matte is computed on the display values ``clip(colour, 0, 1)^(1 /
    gamma)``, where a photograph's colour model holds."""
    from pymatting import estimate_alpha_cf, estimate_foreground_ml
    from scipy import ndimage

    from mpib_validate.runtime.layers import fill as _fill
    from mpib_validate.runtime.layers.mpi import Pixels, Sheet
    from mpib_validate.runtime.layers.passes import sheets_from_passes

    colour = np.asarray(colour, np.float64)[..., :3]
    D = np.asarray(disparity, np.float64)
    sheets, _ = sheets_from_passes(colour, D, blur_parameter,
                                   dataclasses.replace(settings, refine="off"))
    thr = settings.jump_px / blur_parameter
    jumps = _fill.disparity_jumps(D, thr)
    jump = jumps[0] | np.isfinite(jumps[2])  # both sides of every jump
    if not jump.any():
        return sheets
    band = ndimage.distance_transform_edt(~jump) <= BAND_PX
    # beyond the band, a pixel's side as the layer builder tells it: near when in front
    # of the far side of its nearest near-side jump pixel
    _, far_field = _fill.occlusion_region(D, blur_parameter, thr, jumps=jumps)
    known_near = ~band & (D > far_field + 0.5 * thr)
    known_far = ~band & ~known_near
    if not (known_near.any() and known_far.any()):
        return sheets
    display = np.clip(colour, 0.0, 1.0) ** (1.0 / gamma)
    trimap = np.where(band, 0.5, known_near.astype(np.float64))
    alpha = np.clip(estimate_alpha_cf(display, trimap), 0.0, 1.0)
    fg, bg = estimate_foreground_ml(display, alpha, return_background=True)
    fg, bg = (np.clip(c, 0.0, 1.0) ** gamma for c in (fg, bg))
    # the depth of each side: that of the nearest known pixel of the side
    _, (ny, nx) = ndimage.distance_transform_edt(~known_near, return_indices=True)
    _, (fy, fx) = ndimage.distance_transform_edt(~known_far, return_indices=True)
    t = np.flatnonzero(band)
    flat_band = band.ravel()
    out = []
    for sh in sheets:
        if isinstance(sh, Sheet):
            out.append(Pixels(t, bg.reshape(-1, 3)[t], np.ones(t.size), D[fy, fx].ravel()[t]))
            out.append(Sheet(sh.origin, sh.colour, np.where(band, 0.0, sh.alpha),
                             sh.disparity))
            continue
        keep = ~flat_band[sh.index]
        out.append(Pixels(sh.index[keep], sh.colour[keep], sh.alpha[keep],
                          sh.disparity[keep]))
    out.append(Pixels(t, fg.reshape(-1, 3)[t], alpha.ravel()[t], D[ny, nx].ravel()[t]))
    return out


def matte_render(colour: np.ndarray, refined: np.ndarray, blur_parameter: float,
                 focus: float, gamma: float = 2.2) -> np.ndarray:
    """The default preset's refocus (``(H, W, 3)`` linear) of ``colour`` over ``refined``,
    a disparity the default refinement has already refined
    (:func:`mpib_validate.runtime.layers.refine.refine_disparity`), with the band around
    its jumps matted (:func:`matte_sheets`); ``blur_parameter`` is ``K`` (px per unit
    disparity), ``focus`` the disparity in focus."""
    from mpib_validate.runtime.compositor.composite import render_subapertures
    from mpib_validate.runtime.layers.passes import mpi_from_sheets
    from mpib_validate.runtime.presets import PRESETS

    p = PRESETS["default"]
    sheets = matte_sheets(colour, refined, blur_parameter, p.passes, gamma)
    mpi = mpi_from_sheets(sheets, blur_parameter, p.passes, *np.shape(refined))
    return render_subapertures(mpi, blur_parameter, focus, p.subapertures,
                               p.composite)[..., :3]
