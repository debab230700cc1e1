"""Defocus kernels for MPI layers, and the convolution paths that apply them.

Kernel model (the canonical pixel model of ``shared/REFERENCE.md``). A fronto-parallel
layer at disparity ``d`` seen through aperture point ``(mu, nu)`` is shifted by
``rho (mu, nu)`` pixels, ``rho = A (d - d_f)`` (signed). With nearest-texel lookups and
samples spread over the pixel area, a sub-pixel shift ``delta`` reaches texel
``q`` with probability ``tent(q_x - delta_x) tent(q_y - delta_y)``
(``tent(t) = max(0, 1 - |t|)``). Averaging over the aperture, the exact discrete
kernel is the *bilinear splat* of the shift distribution::

    K[q] = E_(mu, nu) [ tent2(q - rho (mu, nu)) ]        (correlation: out(p) = sum_q K[q] L(p + q))

i.e. the disk of radius ``|rho|`` convolved with the pixel box twice, sampled at
integer offsets. Its support is ``ceil(|rho|) + 1`` taps from the centre, no more: no
kernel larger than the blur. Each kernel here is computed by splatting a stratified
(concentric-map) point set of the disk, or of a part of it for the sub-aperture
("middle") renderer, and sums to one.

The official MPIB kernel, a soft disk ``0.5 + 0.5 tanh(0.25 (r^2 - x^2 - y^2) + 0.5)``
at integer radius ``round(r)``, is available as :func:`soft_disk` for comparison.

Convolution paths (all compute the same correlation on a padded array, "valid" mode):

- ``direct``: scipy.ndimage.correlate, O(taps) per pixel;
- ``fft``: scipy.fft in float64, O(log n) per pixel; rounding noise below
  ``FFT_FLOOR`` times the input's largest value is cleared, alpha is clamped to [0, 1]
  and colour to >= 0 (no ringing, no negative values);
- ``auto``: whichever the cost model says is cheaper.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from .samples import concentric_disk

#: Relative level under which FFT output is rounding noise. The FFT runs in float64
#: (eps 2.2e-16; its error grows like eps * log2(n), ~5e-15 at n = 2^21 values), so
#: values below this fraction of the input's largest value are set to zero: far below
#: any float32 result, and it removes ringing and sign noise where nothing is.
FFT_FLOOR = 1e-12


def disk_points(radius: float, cell: tuple[int, int, int] | None = None) -> np.ndarray:
    """Stratified points covering the disk of ``radius`` pixels, shape ``(P, 2)`` as (x, y).

    The unit square is split into an ``m x m`` grid (``m`` grows with the radius so that
    there are >= ~16 points per square pixel), mapped onto the disk by the concentric
    map (area preserving, so the points are equally weighted). ``cell=(i, j, k)`` keeps
    only the points of sub-aperture ``(i, j)`` of a ``k x k`` partition of the square:
    ``k^2`` equal-area parts of the aperture.
    """
    m = int(np.clip(math.ceil(8.0 * abs(radius)), 32, 512))
    if cell is not None:
        k = cell[2]
        m = max(m // k, 8) * k
    t = (np.arange(m) + 0.5) / m
    u, v = np.meshgrid(t, t, indexing="xy")
    if cell is not None:
        i, j, k = cell
        sel = (np.floor(u * k) == i) & (np.floor(v * k) == j)
        u, v = u[sel], v[sel]
    mu, nu = concentric_disk(u.ravel(), v.ravel())
    return np.stack([mu * radius, nu * radius], axis=1)


def splat(points: np.ndarray) -> np.ndarray:
    """Bilinear (tent) splat of equally weighted points onto integer taps.

    Returns a ``(2R+1, 2R+1)`` float64 kernel, centre at ``[R, R]``, summing to one,
    with ``R = ceil(max |coordinate|)`` (the tent adds at most one tap per side).
    """
    if len(points) == 0:
        raise ValueError("cannot make a kernel from no points")
    R = int(math.ceil(float(np.abs(points).max()) - 1e-9)) if np.abs(points).max() > 0 else 0
    n = 2 * R + 1
    x = points[:, 0] + R
    y = points[:, 1] + R
    x0 = np.clip(np.floor(x), 0, n - 1)
    y0 = np.clip(np.floor(y), 0, n - 1)
    fx, fy = x - x0, y - y0
    k = np.zeros(n * n + 2 * n + 2)
    w = 1.0 / len(points)
    ix0, iy0 = x0.astype(np.int64), y0.astype(np.int64)
    for dx, dy, wt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                       (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        ix = np.minimum(ix0 + dx, n - 1)
        iy = np.minimum(iy0 + dy, n - 1)
        k += np.bincount(iy * n + ix, weights=wt * w, minlength=k.size)
    return k[:n * n].reshape(n, n)


@functools.lru_cache(maxsize=512)
def _disk_cached(radius_q: int, cell) -> np.ndarray:
    r = abs(radius_q) / 1024.0
    if r == 0.0:
        return np.ones((1, 1))
    k = splat(disk_points(math.copysign(r, radius_q), cell))
    if cell is None:
        k = _exact_interior(k, r)
    return k


def _exact_interior(k: np.ndarray, r: float) -> np.ndarray:
    """Set the taps whose tent support ``[q - 1, q + 1]^2`` lies inside the disk to their
    exact value ``1 / (pi r^2)``, and rescale the others so that the kernel sums to one.

    The splat estimates those taps to ~1e-4; the exact plateau also lets a row of the
    kernel be written as a few nested boxes (see :func:`row_boxes`).
    """
    R = kernel_radius(k)
    q = np.arange(-R, R + 1, dtype=np.float64)
    far = np.maximum(np.abs(q)[None, :] + 1.0, 0.0) ** 2 + (np.abs(q)[:, None] + 1.0) ** 2
    inside = far <= r * r
    if not inside.any():
        return k
    plateau = 1.0 / (math.pi * r * r)
    out = k.copy()
    out[inside] = plateau
    rest = 1.0 - plateau * inside.sum()
    edge = k[~inside].sum()
    out[~inside] *= rest / edge
    return out


def row_boxes(kernel: np.ndarray, rel_tol: float = 1e-7) -> list[tuple[int, int, int, float]]:
    """Write a kernel as a sum of row boxes ``(dy, a, b, h)``: weight ``h`` on taps
    ``dx in [a, b]`` of row ``dy`` (offsets from the centre).

    Each row's profile is decomposed into nested intervals (a "staircase": one box per
    rise). Values within ``rel_tol`` of the kernel's peak of each other are merged
    first, an error far below float32 resolution; a disk row with an exact plateau
    becomes ~3 boxes. Used by the gather-based (Dr.Jit) convolution with row prefix sums.
    """
    R = kernel_radius(kernel)
    quantum = rel_tol * float(np.abs(kernel).max())
    q = np.round(kernel / quantum) * quantum if quantum > 0 else kernel
    boxes = []
    for iy in range(kernel.shape[0]):
        row = q[iy]
        stack = []  # open boxes: [start, height]
        prev = 0.0
        for ix in range(row.size + 1):
            v = row[ix] if ix < row.size else 0.0
            if v > prev:
                stack.append([ix, v - prev])
            elif v < prev:
                drop = prev - v
                while drop > 1e-300 and stack:
                    start, h = stack[-1]
                    if h <= drop + 1e-300:
                        stack.pop()
                        boxes.append((iy - R, start - R, ix - 1 - R, h))
                        drop -= h
                    else:
                        stack[-1][1] = h - drop
                        boxes.append((iy - R, start - R, ix - 1 - R, drop))
                        drop = 0.0
            prev = v
    return boxes


def disk_kernel(rho: float, cell: tuple[int, int, int] | None = None) -> np.ndarray:
    """Canonical kernel of a layer with signed blur radius ``rho = A (d - d_f)`` pixels.

    The radius is quantised to 1/1024 px for caching (a radius error far below any
    measured effect). ``cell`` selects a sub-aperture (see :func:`disk_points`); the
    sign of ``rho`` matters only then (the shift is ``rho (mu, nu)``).
    Returns a read-only float64 correlation kernel that sums to one.
    """
    q = int(round(rho * 1024.0))
    if cell is None:
        q = abs(q)
    k = _disk_cached(q, cell)
    k.setflags(write=False)
    return k


def soft_disk(radius: float) -> np.ndarray:
    """The official MPIB kernel: integer radius ``r = round(radius)`` and
    ``0.5 + 0.5 tanh(0.25 (r^2 - x^2 - y^2) + 0.5)`` on the ``(2r+1)^2`` grid, normalised."""
    r = int(round(abs(radius)))
    if r == 0:
        return np.ones((1, 1))
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    k = 0.5 + 0.5 * np.tanh(0.25 * (r * r - x * x - y * y) + 0.5)
    return k / k.sum()


def kernel_radius(k: np.ndarray) -> int:
    return (k.shape[0] - 1) // 2


# --------------------------------------------------------------------------------------
# Convolution paths. Input: (h + 2R, w + 2R, C) float32, already padded by the kernel
# radius R; output: (h, w, C) float32 ("valid" correlation).


def correlate_direct(padded: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Direct correlation. scipy.ndimage is the fastest but computes the whole padded
    area (and runs out of memory on 401x401 kernels); when the valid part is small,
    scipy.signal computes only that part."""
    from scipy import ndimage, signal

    R = kernel_radius(kernel)
    h, w = padded.shape[0] - 2 * R, padded.shape[1] - 2 * R
    out = np.empty((h, w, padded.shape[2]), np.float32)
    valid_only = h * w < 0.25 * padded.shape[0] * padded.shape[1]
    k = kernel.astype(np.float64 if valid_only else np.float32)
    for c in range(padded.shape[2]):
        if valid_only:
            out[..., c] = signal.correlate(padded[..., c].astype(np.float64), k, mode="valid",
                                           method="direct")
        else:
            out[..., c] = ndimage.correlate(padded[..., c], k, mode="constant",
                                            cval=0.0)[R:R + h, R:R + w]
    return out


def _channel_peaks(a: np.ndarray) -> np.ndarray:
    """Largest magnitude of each channel of ``(H, W, C)`` (a scalar reduction per
    channel: numpy reduces a strided channel several times faster than ``axis=(0, 1)``)."""
    return np.array([max(float(a[..., c].max()), -float(a[..., c].min()))
                     for c in range(a.shape[-1])])


def correlate_fft(padded: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    from scipy import fft

    R = kernel_radius(kernel)
    H, W = padded.shape[:2]
    sh = (fft.next_fast_len(H, real=True), fft.next_fast_len(W, real=True))
    spec = fft.rfft2(padded.astype(np.float64), s=sh, axes=(0, 1), workers=-1)
    # correlation = convolution with the flipped kernel; the kernel's [0, 0] tap lands
    # at the output offset 2R, which is where the "valid" region starts.
    kf = fft.rfft2(kernel[::-1, ::-1], s=sh, workers=-1)
    spec *= kf[..., None]
    full = fft.irfft2(spec, s=sh, axes=(0, 1), workers=-1)
    out = np.ascontiguousarray(full[2 * R:H, 2 * R:W], dtype=np.float32)
    # clear rounding noise relative to each channel's largest input magnitude
    peak = _channel_peaks(padded)
    out[np.abs(out) < FFT_FLOOR * peak] = 0.0
    np.maximum(out, 0.0, out=out)
    return out


def fft_is_cheaper(h: int, w: int, kernel: np.ndarray) -> bool:
    """Cost model: direct costs ~taps per pixel; the FFT ~ 9 transforms of the padded
    size at ~2.5 log2(n) operations per value (measured on this project's machines,
    the crossover is near 7x7 kernels)."""
    taps = kernel.size
    n = (h + kernel.shape[0]) * (w + kernel.shape[1])
    return taps > 2.5 * math.log2(max(n, 2)) * 9 / 4 / 2


def correlate(padded: np.ndarray, kernel: np.ndarray, method: str = "auto") -> np.ndarray:
    """Valid-mode correlation of a padded ``(H, W, C)`` array with ``kernel``."""
    if kernel.shape == (1, 1):
        return np.array(padded * np.float32(kernel[0, 0]), dtype=np.float32)
    if method == "auto":
        h, w = padded.shape[0] - kernel.shape[0] + 1, padded.shape[1] - kernel.shape[1] + 1
        method = "fft" if fft_is_cheaper(h, w, kernel) else "direct"
    if method == "fft":
        return correlate_fft(padded, kernel)
    if method == "direct":
        return correlate_direct(padded, kernel)
    raise ValueError(f"unknown convolution method {method!r}; use auto, direct or fft")
