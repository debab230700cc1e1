"""Degrading an exact disparity map the way a monocular depth estimator errs (seeded).

A network (DPT, MiDaS, Depth Anything) predicts disparity at a fraction of the image's
resolution and upsamples it: its map is smooth across object edges, misaligned with
the colour edges by a pixel or two, and wrong by a few per cent, smoothly over the
image. :func:`degrade_disparity` imitates that on a card scene's exact disparity, so
the layer construction can be scored against the ray tracer with an input that is as
unreliable at the boundaries as a predicted one (``mpib bench --suite photos``).
"""

from __future__ import annotations

import math

import numpy as np


def degrade_disparity(disparity: np.ndarray, seed: int, blur_px: float = 2.0, down: int = 4,
                      shift_px: float = 1.5, noise: float = 0.02) -> np.ndarray:
    """A predicted-looking version of ``disparity`` (same units, 1/scene-unit; same shape).

    The steps, in order (each one's parameter, 0 or 1 turns it off):

    1. Gaussian blur of standard deviation ``blur_px`` pixels (edges spread over about
       ``4 blur_px`` pixels); borders replicated.
    2. Down by ``down`` (the mean over each ``down x down`` block; the map is padded by
       edge replication to a multiple of ``down``): the estimator's resolution.
    3. Multiplicative noise at that resolution: ``d_low * (1 + noise * n)``, ``n`` standard
       normal, one value per block, so after step 4 it varies smoothly over ``down``
       pixels as a network's error does (not pixel to pixel). ``d >= 0`` is kept:
       ``n`` is clipped to ``|n| <= 3`` and ``noise <= 1/3`` is required.
    4. Bilinear up to the full resolution, pixel centres aligned:
       full-resolution pixel ``y`` samples the low-resolution grid at ``(y + 1/2) / down - 1/2``.
    5. A shift by ``shift_px`` pixels in a direction drawn from ``seed`` (bilinear, borders
       replicated): the map is misregistered with the colour.

    The same ``seed`` (and parameters) gives the same map, bit for bit.
    """
    from scipy import ndimage

    D = np.asarray(disparity, np.float64)
    if D.ndim != 2:
        raise ValueError(f"disparity must be (H, W), got {D.shape}")
    if not 0 <= noise <= 1 / 3:
        raise ValueError(f"noise must be in [0, 1/3], got {noise}")
    if int(down) != down or down < 1:
        raise ValueError(f"down must be a positive integer, got {down}")
    down = int(down)
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2.0 * math.pi)
    H, W = D.shape
    out = ndimage.gaussian_filter(D, blur_px, mode="nearest") if blur_px > 0 else D.copy()
    if down > 1:
        ph, pw = -H % down, -W % down
        padded = np.pad(out, ((0, ph), (0, pw)), mode="edge")
        low = padded.reshape(padded.shape[0] // down, down, padded.shape[1] // down, down).mean(
            axis=(1, 3))
    else:
        low = out
    n = np.clip(rng.standard_normal(low.shape), -3.0, 3.0)
    low = low * (1.0 + noise * n)
    if down > 1:
        yy = (np.arange(H) + 0.5) / down - 0.5
        xx = (np.arange(W) + 0.5) / down - 0.5
        gy, gx = np.meshgrid(yy, xx, indexing="ij")
        out = ndimage.map_coordinates(low, [gy, gx], order=1, mode="nearest")
    else:
        out = low
    if shift_px > 0:
        out = ndimage.shift(out, (shift_px * math.sin(angle), shift_px * math.cos(angle)),
                            order=1, mode="nearest")
    return np.maximum(out, 0.0)
