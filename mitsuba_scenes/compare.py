"""A noise-aware comparison of two Monte Carlo renders of one scene (numpy only).

For each pixel and channel, a two-sample z-score (Welch, with the sample variances of
both renders)::

    z = (m_test - m_ref) / sqrt(s2_test / n_test + s2_ref / n_ref + floor^2)

``m`` are the pixel means, ``s2`` the per-sample variances, ``n`` the sample counts.
Both renderers integrate the same function, so an unbiased pair gives z with mean 0
and variance about 1 (less where the floor dominates).

The floor: a sample variance can miss rare events. A pixel where a few per cent of the
aperture sees a different card (sub-pixel blur at an edge, an HDR highlight seen
through a small part of the lens) can have all of its ``n`` samples equal: its sample
variance is 0 while its mean is off by ``p * delta``. Every sample value lies in
``[0, B]``, with ``B`` the pixel's value bound (:func:`value_bound`: the brightest
straight colour of any card within the pixel's reach; a composite ``sum T_i a_i c_i``
never exceeds its brightest ``c_i``). A mean of ``n`` samples cannot resolve an event
finer than one sample, ``B / n``; the floor is ``4 B / n`` per render. With it, an
unobserved event (``k = 0`` hits) reaches ``|z| > 4`` only if its expected hit count
``n p`` exceeds 16, which happens with probability ``e^-16``, and the lower Poisson tail
of few-hit pixels (``z ~ (k - n p) / sqrt(k + 16)``) is no heavier than a normal one.
The floor also covers float32 rounding: a film pixel summed in float32 from ``n``
samples is off by at most ``n u B`` (``u = 2^-24``), far below ``4 B / n`` for
``n < 2^11``.

Decision (:class:`Agreement`): a pixel is an outlier if any channel has ``|z| > 4``.
Under agreement a channel is an outlier with probability at most
``p4 = 2 * 2 Phi(-4) = 1.3e-4`` (the normal tail, doubled for the residual skew of
few-hit pixels), i.e. at most ``4 p4`` per pixel over four channels (union bound); the
outlier count is then at most Poisson with mean ``mu = 4 p4 N_pixels``, and the test
allows the count whose Poisson upper tail is below ``1e-6``. The mean z must also
stay within ``4 / sqrt(N_pixels)`` of 0 (each pixel's z has variance <= 1; channels of
one pixel may be fully correlated, so only pixels count as independent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mpib_validate.cards.scene import Scene

#: |z| above this marks an outlier.
Z_OUTLIER = 4.0
#: Per-channel outlier probability allowed for under agreement (see module docstring).
P_CHANNEL = 2.0 * math.erfc(Z_OUTLIER / math.sqrt(2.0))
#: Tail probability that sets the allowed outlier count.
FALSE_ALARM = 1e-6
#: Floor: a mean of n samples resolves nothing finer than FLOOR_SAMPLES * B / n.
FLOOR_SAMPLES = 4.0


def _window_max(a: np.ndarray, w: int, axis: int) -> np.ndarray:
    """Max over ``w`` consecutive entries along ``axis``: output ``n - w + 1`` long.

    Doubling: after each step, entry i holds the max over ``[i, i + span)``; a last
    overlapping step completes the window. O(n log w).
    """
    def part(x, start, stop):
        idx = [slice(None)] * x.ndim
        idx[axis] = slice(start, stop)
        return x[tuple(idx)]

    out, span = a, 1
    while 2 * span <= w:
        n = out.shape[axis]
        out = np.maximum(part(out, 0, n - span), part(out, span, n))
        span *= 2
    if span < w:
        n = out.shape[axis]
        out = np.maximum(part(out, 0, n - (w - span)), part(out, w - span, n))
    return out


def poisson_isf(tail: float, mu: float) -> int:
    """Smallest integer c with P(X > c) <= tail for X ~ Poisson(mu)."""
    if mu <= 0:
        return 0
    c, cdf = 0, math.exp(-mu)
    while 1.0 - cdf > tail:
        c += 1
        cdf += math.exp(c * math.log(mu) - mu - math.lgamma(c + 1))  # log space: no underflow
    return c


def value_bound(scene: Scene) -> np.ndarray:
    """Per-pixel upper bound ``B`` (``(H, W, 4)`` float64) on any sample value.

    A ray from pixel ``(i, j)`` meets card ``k`` within ``max_shift_k`` pixels of the pixel
    (Eq. 15's largest displacement over the frame and the aperture), plus one pixel for
    the pixel's and the texel's own extent. Its composited colour is at most the
    brightest straight colour of the texels (alpha > 0) it can meet, per channel; its
    coverage at most 1 if it can meet any such texel (else both are 0).
    """
    cam = scene.camera
    W, H = cam.width, cam.height
    out = np.zeros((H, W, 4), np.float64)
    for card in scene.cards:
        shift = card.plane.max_shift(cam.blur_parameter, cam.focus_disparity,
                                     -0.5 * W, 0.5 * W, -0.5 * H, 0.5 * H)
        reach = int(math.ceil(min(shift, 4.0 * max(W, H)))) + 2
        rgba = np.asarray(card.rgba, np.float64)
        val = np.where(rgba[..., 3:4] > 0, np.concatenate(
            [rgba[..., :3], np.ones_like(rgba[..., :1])], axis=-1), 0.0)
        # the card's texels on a canvas covering the frame plus the reach
        canvas = np.zeros((H + 2 * reach, W + 2 * reach, 4))
        ox, oy = card.offset
        h, w = card.size[1], card.size[0]
        r0, c0 = oy + reach, ox + reach
        rs, re = max(r0, 0), min(r0 + h, canvas.shape[0])
        cs, ce = max(c0, 0), min(c0 + w, canvas.shape[1])
        if rs < re and cs < ce:
            canvas[rs:re, cs:ce] = val[rs - r0:re - r0, cs - c0:ce - c0]
        # max over the (2 reach + 1)^2 window centred on each frame pixel
        grown = _window_max(_window_max(canvas, 2 * reach + 1, 0), 2 * reach + 1, 1)
        out = np.maximum(out, grown)
    return out


@dataclass
class Agreement:
    """Result of :func:`agreement`. ``passed`` is the decision; the rest explains it.

    Attributes:
        z: ``(H, W, C)`` z-scores.
        outlier_pixels: pixels with any channel ``|z| > 4``.
        allowed_outliers: the most outlier pixels an agreeing pair shows (tail 1e-6).
        mean_z: mean z over all pixels and channels; mean_z_bound: ``4 / sqrt(N_pixels)``.
        rms_z: root mean square of z (about 1, or below where the floor dominates).
        max_abs_z: largest ``|z|``.
    """

    z: np.ndarray
    outlier_pixels: int
    allowed_outliers: int
    mean_z: float
    mean_z_bound: float
    rms_z: float
    max_abs_z: float

    @property
    def pixels(self) -> int:
        return int(self.z.shape[0] * self.z.shape[1])

    @property
    def outlier_fraction(self) -> float:
        return self.outlier_pixels / self.pixels

    @property
    def passed(self) -> bool:
        return (self.outlier_pixels <= self.allowed_outliers
                and abs(self.mean_z) <= self.mean_z_bound)

    def summary(self) -> str:
        return (f"{'agree' if self.passed else 'DISAGREE'}: {self.outlier_pixels}/{self.pixels} "
                f"pixels with |z| > {Z_OUTLIER:g} (allowed {self.allowed_outliers}), "
                f"mean z {self.mean_z:+.3f} (bound {self.mean_z_bound:.3f}), "
                f"rms z {self.rms_z:.3f}, max |z| {self.max_abs_z:.3g}")


def allowed_outliers(pixels: int, channels: int = 4) -> int:
    """Largest outlier-pixel count with Poisson upper tail >= 1e-6 under agreement."""
    return poisson_isf(FALSE_ALARM, channels * P_CHANNEL * pixels)


def zscores(test: np.ndarray, test_var: np.ndarray, test_n: int, ref: np.ndarray,
            ref_var: np.ndarray, ref_n: int, bound: np.ndarray) -> np.ndarray:
    """Per-pixel, per-channel z of ``test - ref`` (see the module docstring).

    ``*_var`` are per-sample variances, ``*_n`` the samples per pixel, ``bound`` the
    per-pixel value bound. Where the denominator is 0 (no card in reach), z is 0 if the
    two agree exactly and infinite otherwise.
    """
    test = np.asarray(test, np.float64)
    ref = np.asarray(ref, np.float64)
    den2 = (np.asarray(test_var, np.float64) / test_n + np.asarray(ref_var, np.float64) / ref_n
            + (FLOOR_SAMPLES * bound / test_n) ** 2 + (FLOOR_SAMPLES * bound / ref_n) ** 2)
    diff = test - ref
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(den2 > 0, diff / np.sqrt(den2), np.where(diff == 0, 0.0, np.inf))
    return z


def agreement(test: np.ndarray, test_var: np.ndarray, test_n: int, ref: np.ndarray,
              ref_var: np.ndarray, ref_n: int, bound: np.ndarray) -> Agreement:
    """Decide whether two renders agree to Monte Carlo noise (module docstring).

    Args:
        test, ref: ``(H, W, C)`` pixel means.
        test_var, ref_var: ``(H, W, C)`` per-sample variances (for a quasi-Monte Carlo
            reference, an upper bound such as the test's own: see the tests).
        test_n, ref_n: samples per pixel behind each mean.
        bound: ``(H, W, C)`` value bound, :func:`value_bound`.
    """
    z = zscores(test, test_var, test_n, ref, ref_var, ref_n, bound)
    a = np.abs(z)
    outliers = int((a > Z_OUTLIER).any(axis=-1).sum())
    pixels = z.shape[0] * z.shape[1]
    finite = np.isfinite(z)
    mean_z = float(z[finite].mean()) if finite.all() else math.inf
    return Agreement(z, outliers, allowed_outliers(pixels, z.shape[-1]), mean_z,
                     Z_OUTLIER / math.sqrt(pixels),
                     float(np.sqrt(np.mean(z ** 2))), float(a.max()))
