"""Image metrics: PSNR, SSIM, FLIP, and their occlusion-boundary variants.

All metrics come from well-kept libraries: PSNR and SSIM from scikit-image (Gaussian
SSIM, window 11, sigma 1.5, as the official MPIB evaluation), FLIP from NVIDIA's
``flip-evaluator``. Two value ranges are reported:

- ``clipped``: values clipped to [0, 1] (the paper's convention; LDR FLIP);
- ``hdr``: linear values with a stated ``peak`` (PSNR/SSIM data range; HDR FLIP).

The occlusion-boundary mask (supplement section 4): boundary pixels where the disparity
changes sharply between neighbours, each dilated to a disk whose radius is the largest
blur radius ``A |d - d_f|`` in its 9x9 neighbourhood. Card scenes know their true
boundaries (where the front-most card changes, :func:`boundaries_from_layers`).
"""

from __future__ import annotations

import math

import numpy as np


def _rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img, np.float64)
    if img.ndim == 3 and img.shape[2] >= 3:
        return img[..., :3]
    if img.ndim == 2:
        return img[..., None]
    raise ValueError(f"expected an (H, W) or (H, W, >=3) image, got {img.shape}")


def psnr(ref, test, mask=None, peak: float = 1.0) -> float:
    """PSNR in dB with data range ``peak`` over all pixels or the ``mask`` ones
    (scikit-image). Identical images give ``inf``."""
    from skimage.metrics import peak_signal_noise_ratio

    a, b = _rgb(ref), _rgb(test)
    if a.shape != b.shape:
        raise ValueError(f"image sizes differ: {a.shape} and {b.shape}")
    if mask is not None:
        a, b = a[mask], b[mask]
        if a.size == 0:
            return math.nan
    if np.array_equal(a, b):
        return math.inf
    return float(peak_signal_noise_ratio(a, b, data_range=peak))


#: Side of the Gaussian SSIM window (sigma 1.5, truncated at 3.5 sigma, as
#: scikit-image sizes it: 2 * int(3.5 * 1.5 + 0.5) + 1); SSIM is undefined (NaN) on
#: smaller images.
SSIM_WINDOW = 11
#: Peak bytes per pixel of ``mpib compare`` above its inputs (all metrics, FLIP included,
#: with or without a mask): measured 295 to 341 B/px at 1500x1000 in fresh processes.
COMPARE_BYTES_PER_PX = 360


def ssim(ref, test, mask=None, peak: float = 1.0) -> float:
    """Gaussian SSIM (window 11, sigma 1.5) with data range ``peak``; the mean of the
    SSIM map over all pixels or over ``mask`` (scikit-image). NaN for images smaller
    than :data:`SSIM_WINDOW` on a side."""
    from skimage.metrics import structural_similarity

    a, b = _rgb(ref), _rgb(test)
    if a.shape != b.shape:
        raise ValueError(f"image sizes differ: {a.shape} and {b.shape}")
    if min(a.shape[:2]) < SSIM_WINDOW:
        return math.nan
    _, smap = structural_similarity(a, b, data_range=peak, channel_axis=2, gaussian_weights=True,
                                    sigma=1.5, use_sample_covariance=False, full=True)
    smap = smap.mean(axis=2)
    if mask is not None:
        return float(smap[mask].mean()) if mask.any() else math.nan
    return float(smap.mean())


def flip(ref, test, hdr: bool = False, mask=None) -> float:
    """Mean FLIP error (NVIDIA flip-evaluator), LDR on [0, 1]-clipped linear colour
    (converted to sRGB by FLIP) or HDR on linear values; over all pixels or ``mask``."""
    import flip_evaluator

    a = np.ascontiguousarray(_rgb(ref), np.float32)
    b = np.ascontiguousarray(_rgb(test), np.float32)
    if a.shape[2] == 1:
        a, b = np.repeat(a, 3, 2), np.repeat(b, 3, 2)
    if hdr:
        a, b = np.maximum(a, 0), np.maximum(b, 0)
        err, mean, _ = flip_evaluator.evaluate(a, b, "HDR", applyMagma=False)
    else:
        a, b = np.clip(a, 0, 1), np.clip(b, 0, 1)
        err, mean, _ = flip_evaluator.evaluate(a, b, "LDR", inputsRGB=False, applyMagma=False)
    if mask is not None:
        return float(np.asarray(err)[mask].mean()) if mask.any() else math.nan
    return float(mean)


# --------------------------------------------------------------------------------------
# Occlusion-boundary masks


def boundaries_from_disparity(disparity: np.ndarray, threshold: float) -> np.ndarray:
    """Pixels whose disparity differs from a 4-neighbour's by more than ``threshold``
    (both sides of the edge are marked): :func:`mpib_validate.runtime.layers.fill.jump_pixels`."""
    from mpib_validate.runtime.layers.fill import jump_pixels

    return jump_pixels(disparity, threshold)


def boundaries_from_layers(layer: np.ndarray, disparity: np.ndarray,
                           threshold: float = 0.0) -> np.ndarray:
    """True occlusion boundaries of a card scene: where the front-most card changes
    between 4-neighbours and the disparity jumps by more than ``threshold``."""
    layer = np.asarray(layer)
    d = np.asarray(disparity, np.float64)
    b = np.zeros(layer.shape, bool)
    for axis in (0, 1):
        change = (np.diff(layer, axis=axis) != 0) & (np.abs(np.diff(d, axis=axis)) > threshold)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        b[tuple(lo)] |= change
        b[tuple(hi)] |= change
    return b


def occlusion_mask(boundary: np.ndarray, disparity: np.ndarray, blur_parameter: float,
                   focus_disparity: float, window: int = 9) -> np.ndarray:
    """Dilate each boundary pixel to a disk whose radius is the largest blur radius
    ``A |d - d_f|`` (px) in its ``window x window`` neighbourhood (supplement sec. 4)."""
    from scipy import ndimage

    radius = blur_parameter * np.abs(np.asarray(disparity, np.float64) - focus_disparity)
    rmax = ndimage.maximum_filter(radius, size=window, mode="nearest")
    mask = np.zeros(boundary.shape, bool)
    rb = np.ceil(rmax[boundary]).astype(int)
    ys, xs = np.nonzero(boundary)
    for r in np.unique(rb):
        seeds = np.zeros(boundary.shape, bool)
        sel = rb == r
        seeds[ys[sel], xs[sel]] = True
        if r <= 0:
            mask |= seeds
            continue
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        disk = (xx * xx + yy * yy) <= r * r
        mask |= ndimage.binary_dilation(seeds, structure=disk)
    return mask


def all_metrics(ref, test, mask=None, peak: float | None = None, with_flip: bool = True) -> dict:
    """Every figure the project reports, for one pair of images.

    ``clipped``: on values clipped to [0, 1]; ``hdr``: on linear values with data range
    ``peak`` (default: the reference's largest value, at least 1).
    """
    a, b = _rgb(ref), _rgb(test)
    if peak is None:
        peak = max(1.0, float(a.max()))
    if not (math.isfinite(peak) and peak > 0):
        raise ValueError(f"the HDR data range (peak) must be finite and > 0, got {peak}")
    ac, bc = np.clip(a, 0, 1), np.clip(b, 0, 1)
    out = {
        "psnr": psnr(ac, bc), "ssim": ssim(ac, bc),
        "psnr_hdr": psnr(a, b, peak=peak), "ssim_hdr": ssim(a, b, peak=peak), "peak": peak,
    }
    if mask is not None:
        out.update(psnr_ob=psnr(ac, bc, mask), ssim_ob=ssim(ac, bc, mask),
                   psnr_ob_hdr=psnr(a, b, mask, peak=peak), mask_fraction=float(mask.mean()))
    if with_flip:
        out["flip"] = flip(ac, bc)
        out["flip_hdr"] = flip(a, b, hdr=True)
    return out


#: :func:`sharp_remnants`' defaults. A lens blurs a point by a disk of radius
#: ``r = A |d - d_f|``; past ``REMNANT_BLUR_PX`` px a disk spreads a line one or two
#: pixels wide over at least 12 px, dividing its contrast by 6 or more, and its 3x3
#: top-hat (below) drops further, so a line kept at more than ``REMNANT_KEEP`` (6/255 of
#: display value, about 2.5 times an 8-bit JPEG's noise) cannot come from the lens. The
#: reference must itself hold less than ``REMNANT_SMOOTH`` (2/255, under JPEG noise)
#: there: a line that the reference keeps is the scene's, not the method's.
REMNANT_BLUR_PX = 6.0
REMNANT_SMOOTH = 2.0 / 255.0
REMNANT_KEEP = 6.0 / 255.0


def thin_structure(img: np.ndarray, size: int = 3) -> np.ndarray:
    """``(H, W)``: the contrast of structures narrower than ``size`` px (lines, dots), the
    larger of the white top-hat ``I - open(I)`` and the black top-hat ``close(I) - I``
    (grey opening/closing with a ``size x size`` square), the largest over the channels;
    in the image's own units. A step edge or a smooth ramp gives 0 (the opening and the
    closing keep them), so an edge that is rightly sharp is not counted."""
    from scipy import ndimage

    x = _rgb(img)
    out = np.zeros(x.shape[:2])
    for c in range(x.shape[2]):
        ch = x[..., c]
        out = np.maximum(out, ch - ndimage.grey_opening(ch, (size, size), mode="nearest"))
        out = np.maximum(out, ndimage.grey_closing(ch, (size, size), mode="nearest") - ch)
    return out


def sharp_remnants(output, reference, disparity, blur_parameter: float,
                   focus_disparity: float, blur_px: float = REMNANT_BLUR_PX,
                   smooth: float = REMNANT_SMOOTH, keep: float = REMNANT_KEEP):
    """Sharp remnants of a refocused image: ``(remnants, must_blur)``, boolean ``(H, W)``.

    ``must_blur``: pixels whose whole 5x5 window ``disparity`` blurs by more than
    ``blur_px``: ``min_5x5 A |d - d_f| > blur_px`` (px). ``disparity`` may be a tuple of
    maps: then every one of them must blur the window (the input and the refined map of
    a photograph: a line drawn into a region that both say is blurred). ``remnants``: those of them
    where :func:`thin_structure` of ``reference`` is below ``smooth`` and that of
    ``output`` above ``keep``, a line or dot one or two pixels wide that a blur of that
    radius cannot leave. ``output`` and ``reference`` are display-encoded images in
    [0, 1] (thresholds in those units; :data:`REMNANT_BLUR_PX` for the reasoning);
    the reference is a render that must be smooth there (the exact depth's, or the
    unrefined one's for a photograph), ``disparity`` the map that says where the blur
    is (the input's for a photograph)."""
    must = must_blur(disparity, blur_parameter, focus_disparity, blur_px)
    rem = must & (thin_structure(reference) < smooth) & (thin_structure(output) > keep)
    return rem, must


def must_blur(disparity, blur_parameter: float, focus_disparity: float,
              blur_px: float = REMNANT_BLUR_PX) -> np.ndarray:
    """Boolean ``(H, W)``: pixels whose whole 5x5 window ``disparity`` (or every map of a
    tuple of them) blurs by more than ``blur_px``, ``min_5x5 A |d - d_f| > blur_px``."""
    from scipy import ndimage

    maps = disparity if isinstance(disparity, (tuple, list)) else (disparity,)
    must = np.ones(np.shape(maps[0]), bool)
    for d in maps:
        r = blur_parameter * np.abs(np.asarray(d, np.float64) - focus_disparity)
        must &= ndimage.minimum_filter(r, 5, mode="nearest") > blur_px
    return must


#: :func:`step_edges`: a pixel is on a step when its central-difference gradient is
#: above this share of the range of its 5x5 window (linear values, per channel). A step
#: (or one anti-aliased over a pixel) gives 1/2; a profile that is smooth over 5 px, as a
#: disk blur of radius 6 px or more leaves (its slope varies by 6 % across 5 px), gives
#: about 1/4 along an axis and less along a diagonal; a blurred ramp from black seen
#: through the sRGB curve stays below 0.37.
EDGE_RATIO = 0.4


def step_edges(img: np.ndarray, floor: float = REMNANT_KEEP) -> np.ndarray:
    """Boolean ``(H, W)``: pixels of a display-encoded (sRGB, [0, 1]) image that lie on
    a step: ``|grad c| > EDGE_RATIO (max_5x5 c - min_5x5 c)`` in the linear values ``c``
    of some channel, where that channel's 5x5 range of display values is above
    ``floor`` (below it, 8-bit levels and noise)."""
    from scipy import ndimage

    from mpib_validate.runtime.io.colour import srgb_to_linear

    v = _rgb(img)
    c = srgb_to_linear(np.clip(v, 0.0, 1.0))
    gy, gx = np.gradient(c, axis=(0, 1))
    grad = np.hypot(gx, gy)
    size = (5, 5, 1)
    span = ndimage.maximum_filter(c, size) - ndimage.minimum_filter(c, size)
    span_d = ndimage.maximum_filter(v, size) - ndimage.minimum_filter(v, size)
    return ((grad > EDGE_RATIO * span) & (span_d > floor)).any(axis=-1)


def sharp_edges(output, reference, disparity, blur_parameter: float,
                focus_disparity: float, blur_px: float = REMNANT_BLUR_PX):
    """Sharp edges inside the blur: ``(edges, must_blur)``, boolean ``(H, W)``. A lens
    blurs every edge in a region that :func:`must_blur` holds by more than ``blur_px``,
    so a step there (:func:`step_edges`) is wrong unless ``reference`` has one within a
    pixel (its own quantisation, noise or a misplaced blur of the same kind). The step
    edges that :func:`sharp_remnants`' top-hat does not count: a strip of background
    kept on a near side, or a hidden layer cut in two at different depths, seen through a
    blurred occluder. Arguments as for :func:`sharp_remnants`."""
    from scipy import ndimage

    must = must_blur(disparity, blur_parameter, focus_disparity, blur_px)
    theirs = ndimage.binary_dilation(step_edges(reference), np.ones((3, 3), bool))
    return must & step_edges(output) & ~theirs, must


# --------------------------------------------------------------------------------------
# The degraded-depth targets' scope (issue #28)

#: A highlight: an all-in-focus pixel brighter than 1 in some channel, grown by this many
#: pixels (its anti-aliased rim, whose colour is still the light's). The photos suite's
#: loss decomposition uses the same region (``bench.photos.oracle_disparities``).
HIGHLIGHT_GROW_PX = 2
#: Structures narrower than this (px) are out of scope: what a 3x3 grey opening or
#: closing removes, a wire or strand 1-2 px wide. After the degradation's 2 px blur and
#: 4x4 averaging such a structure keeps about a tenth of its jump, so no predicted map
#: holds its depth (the loss decomposition of the degraded Blender scenes and cards).
SCOPE_THIN_PX = 3
#: A thin structure has at least this many pixels (8-connected): a wire, a strand, a
#: leg. The opening also takes the 1-2 px tip where a digitised outline leaves the pixel
#: grid, which is part of an outline, not a structure under 3 px: the corners of rotated
#: cards and of the horses' outlines (0 to 20 px per 192x192 card scene of the photos
#: suite) and the limbs of round objects (the quick Blender scenes: 7 tips on the
#: spheres, 4 on Suzanne, 1 on the ground, each 1-2 px).
SCOPE_MIN_PIXELS = 3


def thin_disparity(disparity: np.ndarray, threshold: float, size: int = SCOPE_THIN_PX,
                   min_pixels: int = SCOPE_MIN_PIXELS) -> np.ndarray:
    """``(H, W)`` bool: pixels of structures narrower than ``size`` px in a disparity map,
    where ``d - open(d)`` (a near wire) or ``close(d) - d`` (a slit onto the far side)
    exceeds ``threshold`` (grey opening/closing with a ``size x size`` square, in the
    map's units), in 8-connected groups of at least ``min_pixels``. A step edge, a ramp,
    a structure ``size`` px wide or more, and an outline's 1-2 px tip give 0."""
    from scipy import ndimage

    thin = thin_structure(np.asarray(disparity, np.float64), size) > threshold
    if min_pixels > 1 and thin.any():
        lab, n = ndimage.label(thin, structure=np.ones((3, 3), bool))
        big = np.bincount(lab.ravel(), minlength=n + 1) >= min_pixels
        big[0] = False
        thin = big[lab]
    return thin


def degraded_scope_exclusion(all_in_focus, disparity, blur_parameter: float,
                             focus_disparity: float, threshold: float | None = None,
                             window: int = 9) -> np.ndarray:
    """``(H, W)`` bool: the pixels the re-scoped degraded-depth targets leave out, those
    whose error comes from depth that no predicted map can hold.

    Seeds: (a) HDR highlights, ``max_c L_c > 1`` in the linear all-in-focus radiance
    ``all_in_focus``, grown by :data:`HIGHLIGHT_GROW_PX`; (b) structures under
    :data:`SCOPE_THIN_PX` px wide in the *exact* ``disparity``
    (:func:`thin_disparity`), by more than ``threshold`` (default ``1 / A``: 1 px of
    blur radius ``A |d - d_f|``, the jump the boundary masks count). Each seed is then
    grown to the pixels its blur reaches, a disk whose radius is the largest blur radius
    ``A |d - d_f|`` (px) in its ``window x window`` neighbourhood
    (:func:`occlusion_mask`): that covers both the structure's own footprint and the one
    a predicted map gives it (the degraded map's value at a 1-3 px structure is a mean of
    its surroundings within a few pixels)."""
    from scipy import ndimage

    A = float(blur_parameter)
    d = np.asarray(disparity, np.float64)
    thr = 1.0 / A if threshold is None else float(threshold)
    lights = np.asarray(all_in_focus, np.float64)[..., :3].max(axis=-1) > 1.0
    if lights.any():
        lights = ndimage.binary_dilation(lights, iterations=HIGHLIGHT_GROW_PX)
    seeds = lights | thin_disparity(d, thr)
    return occlusion_mask(seeds, d, A, focus_disparity, window)
