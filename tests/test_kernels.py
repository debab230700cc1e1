"""Canonical disk kernels at any radius, against an independent quadrature of their
definition (the disk, or a quarter of it, convolved with the pixel box twice)."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from mpib_validate.runtime.compositor import kernels as K


def _tent_cdf(t):
    t = np.asarray(t, np.float64)
    return np.where(t <= -1, 0.0, np.where(t <= 0, 0.5 * (t + 1) ** 2,
                                           np.where(t <= 1, 1 - 0.5 * (1 - t) ** 2, 1.0)))


@functools.lru_cache(maxsize=4)
def _gauss(nodes: int):
    return np.polynomial.legendre.leggauss(nodes)


def exact_tap(qx: int, qy: int, r: float, quadrant=None, nodes: int = 200) -> float:
    """``K[q] = (1 / area) * integral of tent(qx - x) tent(qy - y)`` over the disk of radius
    ``r`` (or its quadrant ``(sx, sy)``: ``sx x >= 0`` and ``sy y >= 0``).

    The y integral is closed-form (the tent's CDF); the x integral is Gauss-Legendre on
    the pieces between the kinks (the tent's, the rim's, the axis), to ~1e-9."""
    cuts = sorted({qx - 1.0, float(qx), qx + 1.0,
                   *(c for c in (-r, r, 0.0) if qx - 1 < c < qx + 1)})
    g, w = _gauss(nodes)
    total = 0.0
    for a, b in zip(cuts[:-1], cuts[1:]):
        x = 0.5 * (b - a) * g + 0.5 * (a + b)
        h = np.sqrt(np.maximum(r * r - x * x, 0.0))
        lo, hi, keep = -h, h, 1.0
        if quadrant is not None:
            sx, sy = quadrant
            keep = (sx * x >= 0).astype(np.float64)
            lo, hi = (np.zeros_like(h), h) if sy > 0 else (-h, np.zeros_like(h))
        inner = _tent_cdf(hi - qy) - _tent_cdf(lo - qy)
        total += float(np.sum(0.5 * (b - a) * w * (1 - np.abs(x - qx)) * inner * keep))
    return total / (math.pi * r * r / (4 if quadrant else 1))


def _rim_and_axis_taps(r: float, quadrant=None):
    """Taps on and next to the rim (and, for a quadrant, along its two straight edges):
    the only ones that are not on the exact plateau."""
    sx, sy = quadrant or (1, 1)
    span = (0, math.pi / 2) if quadrant else (0, 2 * math.pi)
    taps = []
    for t in np.linspace(*span, 40):
        for dr in (-2, -1, 0, 1):
            taps.append((sx * round((r + dr) * math.cos(t)), sy * round((r + dr) * math.sin(t))))
    if quadrant:
        for s in np.linspace(0, r - 1, 20):
            for off in (-1, 0, 1, 2):
                taps += [(sx * round(s), sy * off), (sx * off, sy * round(s))]
    return taps


# The rim taps are a ~20-points-per-square-pixel stratified estimate: measured at r = 7.3,
# 30 and 64 px (the radii the tracer tests pin, see test_composite), its largest error is
# 0.80 % of the plateau value 1/(pi r^2); the same estimator must hold at every radius.
RIM_TOLERANCE = 0.01


@pytest.mark.parametrize("r", [30.0, 300.0, 1388.0, 2500.3])
def test_disk_kernel_is_exact_at_any_radius(r):
    """Up to 1,387 px the grid of splat points was capped at 512 x 512, so a large disk
    had under one point per square pixel (a noisy rim at 300 px) and from 1,388 px its
    rim taps got none: 0/0, a NaN kernel and an all-NaN image."""
    k = K.disk_kernel(r)
    R = K.kernel_radius(k)
    assert R == math.ceil(r)
    assert np.isfinite(k).all() and (k >= 0).all()
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    plateau = 1.0 / (math.pi * r * r)
    assert k[R, R] == pytest.approx(plateau, rel=1e-12)  # inside taps are exact
    for qx, qy in _rim_and_axis_taps(r):
        if max(abs(qx), abs(qy)) > R:
            continue
        assert abs(k[qy + R, qx + R] - exact_tap(qx, qy, r)) < RIM_TOLERANCE * plateau, (qx, qy)
    # second moment: the disk's r^2/2 plus twice the tent's 1/6 per axis; the grid's
    # midpoint rule misses it by 2.3e-5 at 30 px, 1.1e-8 at 1388 px (about 0.02 / r^2),
    # and float64 sums over 25 million taps add ~1e-7
    q = np.arange(-R, R + 1)
    m2 = float((k * (q[None, :] ** 2 + q[:, None] ** 2)).sum())
    assert m2 == pytest.approx(r * r / 2 + 1 / 3, rel=max(0.03 / r ** 2, 1e-6))


@pytest.mark.parametrize("r, cell, quadrant", [
    (9.2, (0, 0, 2), (-1, -1)),
    (700.0, (0, 0, 2), (-1, -1)),
    (-700.0, (0, 0, 2), (1, 1)),  # a negative radius mirrors the sub-aperture
    (700.0, (1, 0, 2), (1, -1)),
])
def test_subaperture_kernel_is_exact_at_any_radius(r, cell, quadrant):
    """The 2 x 2 sub-apertures of the concentric map are the disk's quadrants. With the
    capped grid a 700 px quadrant was a lattice of spots 2.7 px apart, not a disk."""
    k = K.disk_kernel(r, cell)
    R = K.kernel_radius(k)
    a = abs(r)
    plateau = 4.0 / (math.pi * a * a)
    assert np.isfinite(k).all() and (k >= 0).all()
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    for qx, qy in _rim_and_axis_taps(a, quadrant):
        if max(abs(qx), abs(qy)) <= R:
            want = exact_tap(qx, qy, a, quadrant)
            assert abs(k[qy + R, qx + R] - want) < RIM_TOLERANCE * plateau, (qx, qy)
    # every tap at least 3 px inside the quadrant is on the plateau (no holes); where the
    # radius is too small for an exact plateau, the splat estimates it to ~1e-4
    q = np.arange(-R, R + 1)
    X, Y = np.meshgrid(q, q)
    deep = ((quadrant[0] * X >= 3) & (quadrant[1] * Y >= 3) & (np.hypot(X, Y) <= a - 3))
    assert np.abs(k[deep] / plateau - 1).max() < 1e-3
    # centroid of a quarter disk: 4 r / (3 pi) along each axis
    c = 4 * a / (3 * math.pi)
    assert (k * X).sum() == pytest.approx(quadrant[0] * c, rel=1e-4)
    assert (k * Y).sum() == pytest.approx(quadrant[1] * c, rel=1e-4)


def test_the_sub_apertures_add_up_to_the_disk():
    """The k x k cells partition the aperture, so their kernels average to the disk's
    (to the rim estimate's error) at a radius beyond the old cap."""
    r = 800.0
    disk = K.disk_kernel(r)
    R = K.kernel_radius(disk)
    total = np.zeros_like(disk)
    for i in range(2):
        for j in range(2):
            part = K.disk_kernel(r, (i, j, 2))
            Rp = K.kernel_radius(part)
            total[R - Rp:R + Rp + 1, R - Rp:R + Rp + 1] += part / 4
    assert np.abs(total - disk).max() < 2 * RIM_TOLERANCE / (math.pi * r * r)


def test_kernel_cache_is_bounded_in_bytes(monkeypatch):
    """Every plane of a large blur has its own radius; the cache keeps at most
    KERNEL_CACHE_BYTES of them (it kept 512 kernels of up to 60 MB each)."""
    monkeypatch.setattr(K, "KERNEL_CACHE_BYTES", 20 << 20)
    for r in np.arange(200.0, 600.0, 50.0):
        K.disk_kernel(r)
    assert sum(v.nbytes for v in K._cache.values()) <= 20 << 20
    assert not K.disk_kernel(650.0).flags.writeable


@pytest.mark.parametrize("r", [0.1, 0.3, 0.7, 1.0, 1.6, 2.5, 3.4, 6.0, 12.5, 30.0])
def test_continuous_radius_gives_the_disks_second_moment(r):
    """A continuous scene's blur, seen through its pixel-filtered samples, has the disk's
    second moment r^2/4 per axis and no more; the canonical kernel adds its bilinear
    splat's E[f (1 - f)] (1/6 above ~1.5 px). At the continuous radius the canonical
    kernel's per-axis moment is r^2/4 up to the splat term's estimate (4096 disk points
    against the kernel's own taps): measured within 0.014 px^2 from 0.05 to 40 px, a
    0.1 % radius error at 3 px; we allow 0.02 px^2. The canonical kernel itself misses
    by 0.04 to 0.18 px^2 over this range, so the check can fail."""
    def axis_moment(k):
        R = K.kernel_radius(k)
        x = np.arange(-R, R + 1)
        return float((k.sum(axis=0) * x * x).sum())

    rc = K.continuous_radius(r)
    assert 0.0 <= rc < r
    assert K.continuous_radius(-r) == -rc  # the sign (a side of the focus) is kept
    assert axis_moment(K.disk_kernel(rc)) == pytest.approx(r * r / 4, abs=0.02)
    assert axis_moment(K.disk_kernel(r)) - r * r / 4 > 0.035
