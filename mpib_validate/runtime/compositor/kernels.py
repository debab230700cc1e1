"""Defocus kernels for MPI layers, and the convolution paths that apply them.

Kernel model (the canonical pixel model of ``docs/camera.md``). A fronto-parallel
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

A polygonal or anamorphic aperture (:class:`mpib_validate.runtime.camera.Aperture`, the
conventions of Cycles) has the same model with ``(mu, nu)`` uniform over its shape:
:func:`aperture_kernel` splats the points of an area-preserving map of the square onto
it (:func:`mpib_validate.runtime.samples.aperture_map`), ``rho`` signed (a point in
front of the focus sees the shape turned 180 degrees). A disk goes to
:func:`disk_kernel`, unchanged.

The official MPIB kernel, a soft disk ``0.5 + 0.5 tanh(0.25 (r^2 - x^2 - y^2) + 0.5)``
at integer radius ``round(r)``, is available as :func:`soft_disk` for comparison.

Convolution paths (all compute the same correlation on a padded array, "valid" mode):

- ``direct``: scipy.ndimage.correlate, O(taps) per pixel;
- ``fft``: scipy.fft in float32 (the layers' own precision), O(log n) per pixel;
  rounding noise below ``FFT_FLOOR`` times the input's largest value is cleared, alpha
  is clamped to [0, 1] and colour to >= 0 (no ringing, no negative values);
- ``auto``: whichever the cost model says is cheaper.
"""

from __future__ import annotations

import collections
import functools
import math
import threading

import numpy as np

from mpib_validate.runtime.samples import aperture_map, concentric_disk

#: Precision of the FFT path: float32, the layers' and the output's own precision, at
#: about half the time and memory of float64. Its rounding error grows like
#: ``eps log2(n)`` in the worst case (eps 1.2e-7: 2.5e-6 at n = 2^21 values); measured
#: on disk kernels of 1.5 to 60 px over windows up to 632^2 holding an HDR dot 1000x the
#: mean, it stays below 3e-8 of the window's largest value (and within 7e-7 of the
#: peak after Eq. 1's accumulation, against float64 FFTs on the 1080p bench MPI and the
#: Blender suite's passes).
FFT_DTYPE = np.float32

#: Relative level under which FFT output is rounding noise: values below this fraction
#: of the input's largest value (per channel) are set to zero. 30x above the measured
#: float32 noise (3e-8, see ``FFT_DTYPE``); it removes ringing and sign noise where
#: nothing is. What it can clear of real content is below 1e-6 of the peak: under
#: 1/4 of an 8-bit step at display white even next to a 1000x HDR highlight.
FFT_FLOOR = 1e-6


#: Stratified points per unit of ``8 x radius`` along each side of the unit square: the
#: grid is ``m x m`` with ``m = max(32, ceil(8 |r|))`` (``64 / pi``, about 20 points per
#: square pixel of the disk at any radius; at least 32 per side for small disks).
POINTS_PER_RADIUS = 8.0

#: Largest ``|d(u, v)|`` per unit ``|d(x, y)|`` of the inverse concentric map (in the
#: max-norm over ``(u, v)``): ``sqrt(1 + 16 / pi^2) / 2`` (the angular stretch along the
#: wedge diagonals). Bounds how far a tap's tent support reaches in the unit square.
_INVERSE_LIPSCHITZ = math.sqrt(1.0 + 16.0 / math.pi ** 2) / 2.0

#: Points splatted per batch (bounds the splat's working memory to ~100 MB).
_SPLAT_BATCH = 1 << 20


def _grid_side(radius: float, k: int = 1) -> int:
    """Side ``m`` of the stratified grid over the unit square for a disk of ``radius``
    px (divisible by ``k`` for ``k x k`` sub-apertures)."""
    m = max(32, int(math.ceil(POINTS_PER_RADIUS * abs(radius))))
    return m if k == 1 else max(m // k, 8) * k


def _grid_to_disk(iu: np.ndarray, iv: np.ndarray, m: int, radius: float) -> np.ndarray:
    """Points ``(P, 2)`` (x, y) of grid cells ``(iu, iv)`` of the ``m x m`` grid, mapped
    onto the disk of ``radius`` by the concentric map."""
    mu, nu = concentric_disk((iu + 0.5) / m, (iv + 0.5) / m)
    return np.stack([mu * radius, nu * radius], axis=1)


def disk_points(radius: float, cell: tuple[int, int, int] | None = None) -> np.ndarray:
    """Stratified points covering the disk of ``radius`` pixels, shape ``(P, 2)`` as (x, y).

    The unit square is split into an ``m x m`` grid (:func:`_grid_side`: ~20 points per
    square pixel at any radius), mapped onto the disk by the concentric map (area
    preserving, so the points are equally weighted). ``cell=(i, j, k)`` keeps only the
    points of sub-aperture ``(i, j)`` of a ``k x k`` partition of the square: ``k^2``
    equal-area parts of the aperture. All ``m^2`` points: the kernels use only those
    near the edges (:func:`_edge_points`).
    """
    i, j, k = cell if cell is not None else (0, 0, 1)
    m = _grid_side(radius, k)
    n = m // k
    iu, iv = np.meshgrid(np.arange(i * n, (i + 1) * n), np.arange(j * n, (j + 1) * n),
                         indexing="xy")
    return _grid_to_disk(iu.ravel(), iv.ravel(), m, radius)


def _edge_indices(lo: int, n: int, t: int):
    """Grid indices ``lo .. lo + n - 1`` split into the ``t`` nearest each end (the
    frame) and the rest."""
    idx = np.arange(lo, lo + n)
    near = (idx < lo + t) | (idx >= lo + n - t)
    return idx[near], idx[~near]


def _edge_points(radius: float, cell, width_uv: float):
    """The grid points of ``cell`` (whole disk if ``None``) that lie within ``width_uv``
    (unit-square units) of the cell's edges, as batches of ``(P, 2)`` points; and the
    weight of one point, ``1 / (points in the cell)``.

    Only these points reach taps that are not on the kernel's exact plateau (see
    :func:`_disk_cached`), so the work grows with the rim, not the area.
    """
    return _edge_points_m(_grid_side(radius, 1 if cell is None else cell[2]), cell, width_uv)


def _edge_points_m(m: int, cell, width_uv: float):
    """:func:`_edge_points` on the ``m x m`` grid."""
    i, j, k = cell if cell is not None else (0, 0, 1)
    n = m // k
    t = min(n, int(math.ceil(width_uv * m)) + 1)
    u_near, u_mid = _edge_indices(i * n, n, t)
    v_near, _ = _edge_indices(j * n, n, t)
    v_all = np.arange(j * n, (j + 1) * n)
    # rows near a u-edge (all of their columns), then the other rows' columns near a v-edge
    blocks = [(u_near, v_all), (u_mid, v_near)]
    batches = []
    for us, vs in blocks:
        if us.size == 0 or vs.size == 0:
            continue
        per = max(1, _SPLAT_BATCH // vs.size)
        for s in range(0, us.size, per):
            iu, iv = np.meshgrid(us[s:s + per], vs, indexing="ij")
            batches.append((iu.ravel(), iv.ravel()))
    return m, batches, 1.0 / (n * n)


def splat(points: np.ndarray) -> np.ndarray:
    """Bilinear (tent) splat of equally weighted points onto integer taps.

    Returns a ``(2R+1, 2R+1)`` float64 kernel, centre at ``[R, R]``, summing to one,
    with ``R = ceil(max |coordinate|)`` (the tent adds at most one tap per side).
    """
    if len(points) == 0:
        raise ValueError("cannot make a kernel from no points")
    R = _support_radius(points)
    k = np.zeros((2 * R + 1, 2 * R + 1))
    _splat_into(k, points, 1.0 / len(points))
    return k


def _support_radius(points: np.ndarray) -> int:
    top = float(np.abs(points).max()) if len(points) else 0.0
    return int(math.ceil(top - 1e-9)) if top > 0 else 0


def _splat_into(k: np.ndarray, points: np.ndarray, weight: float) -> None:
    """Add the tent splat of ``points`` (each of ``weight``) to the kernel ``k`` in place."""
    n = k.shape[0]
    R = (n - 1) // 2
    x = points[:, 0] + R
    y = points[:, 1] + R
    x0 = np.clip(np.floor(x), 0, n - 1)
    y0 = np.clip(np.floor(y), 0, n - 1)
    fx, fy = x - x0, y - y0
    ix0, iy0 = x0.astype(np.int64), y0.astype(np.int64)
    flat = k.reshape(-1)
    for dx, dy, wt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                       (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        ix = np.minimum(ix0 + dx, n - 1)
        iy = np.minimum(iy0 + dy, n - 1)
        np.add.at(flat, iy * n + ix, wt * weight)


#: Kernels kept for reuse, at most this many bytes in all (least recently used first
#: out); a kernel larger than this is computed each time it is asked for.
KERNEL_CACHE_BYTES = 256 << 20
_cache: "collections.OrderedDict" = collections.OrderedDict()


_cache_lock = threading.Lock()  # callers may be on several threads


def _cached(key, make) -> np.ndarray:
    """The kernel of ``key`` from the LRU cache, else ``make()`` (read-only), kept while
    the cache stays within :data:`KERNEL_CACHE_BYTES`."""
    with _cache_lock:
        k = _cache.get(key)
        if k is not None:
            _cache.move_to_end(key)
            return k
    k = make()
    k.setflags(write=False)
    if k.nbytes <= KERNEL_CACHE_BYTES:
        with _cache_lock:
            _cache[key] = k
            total = sum(v.nbytes for v in _cache.values())
            while total > KERNEL_CACHE_BYTES:
                _, old = _cache.popitem(last=False)
                total -= old.nbytes
    return k


def _disk_cached(radius_q: int, cell) -> np.ndarray:
    key = (radius_q, cell)
    return _cached(key, lambda: _disk_kernel(math.copysign(abs(radius_q) / 1024.0, radius_q),
                                             cell))


def _disk_kernel(rho: float, cell) -> np.ndarray:
    """The canonical kernel of signed radius ``rho`` (see :func:`disk_kernel`).

    Taps whose whole tent support ``[q - 1, q + 1]^2`` lies inside the disk (or inside
    the sub-aperture's part of it) have the exact value ``k^2 / (pi r^2)`` (the point
    density; ``k = 1`` for the whole disk). Only the other taps are estimated, by the
    tent splat of the grid points that can reach them: those within the tent's reach
    of the region's edges (:func:`_edge_points`). The estimate is then rescaled so that
    the kernel sums to one. The cost grows with the rim length, and the point density
    (~20 per square pixel) is the same at every radius.
    """
    r = abs(rho)
    if r == 0.0:
        return np.ones((1, 1))
    k = 1 if cell is None else cell[2]
    if cell is None:
        # a tap is inside when its support's far corner is: (|q| + 1)^2 summed <= r^2.
        # Points further than 2 sqrt(2) px inside the rim reach inside taps only.
        width = (2.0 * math.sqrt(2.0) + 0.01) / (2.0 * r)
    else:
        # in unit-square units, a point moves at most lambda / r per pixel: a support
        # (half-diagonal sqrt 2) spans +-delta, two supports +-2 delta
        delta = math.sqrt(2.0) * _INVERSE_LIPSCHITZ / r * (1.0 + 1e-9)
        width = 2.0 * delta
    m, batches, weight = _edge_points(rho, cell, width)
    pts = [_grid_to_disk(iu, iv, m, rho) for iu, iv in batches]
    R = max(_support_radius(p) for p in pts)
    out = np.zeros((2 * R + 1, 2 * R + 1))
    for p in pts:
        _splat_into(out, p, weight)
    inside = _inside_disk(R, r) if cell is None else _inside_cell(R, rho, cell, delta)
    n_inside = int(inside.sum())
    if n_inside == 0:
        return out
    plateau = k * k / (math.pi * r * r)
    out[inside] = 0.0
    edge = out.sum()
    out *= (1.0 - plateau * n_inside) / edge
    out[inside] = plateau
    return out


def _inside_disk(R: int, r: float) -> np.ndarray:
    """Taps whose tent support lies inside the disk of radius ``r``."""
    q = np.abs(np.arange(-R, R + 1, dtype=np.float64)) + 1.0
    return (q[None, :] ** 2 + q[:, None] ** 2) <= r * r


def _concentric_inverse(x: np.ndarray, y: np.ndarray):
    """Inverse of :func:`mpib_validate.runtime.samples.concentric_disk`: unit-disk points to the
    unit square (extended beyond the disk by the same formulas)."""
    s = np.hypot(x, y)
    th = np.arctan2(y, x)
    q = math.pi / 4.0
    right = np.abs(th) <= q
    left = np.abs(th) >= 3 * q
    top = ~right & ~left & (th > 0)
    a = np.where(right, s, np.where(left, -s, np.where(top, s * (2 * q - th) / q,
                                                       s * (2 * q + th) / q)))
    phi_left = np.where(th > 0, th - math.pi, th + math.pi)
    b = np.where(right, s * th / q, np.where(left, -s * phi_left / q,
                                             np.where(top, s, -s)))
    return 0.5 * (a + 1.0), 0.5 * (b + 1.0)


def _inside_cell(R: int, rho: float, cell, delta: float) -> np.ndarray:
    """Taps whose tent support maps wholly into sub-aperture ``cell``: the tap centre's
    unit-square position is at least ``delta`` inside the cell (the support's reach)."""
    i, j, k = cell
    q = np.arange(-R, R + 1, dtype=np.float64) / rho
    inside = np.zeros((2 * R + 1, 2 * R + 1), bool)
    rows = max(1, (1 << 22) // (2 * R + 1))
    for y0 in range(0, 2 * R + 1, rows):
        u, v = _concentric_inverse(q[None, :], q[y0:y0 + rows, None])
        inside[y0:y0 + rows] = ((u - delta >= i / k) & (u + delta <= (i + 1) / k)
                                & (v - delta >= j / k) & (v + delta <= (j + 1) / k))
    return inside


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
    return _disk_cached(q, cell)


def continuous_radius(rho: float) -> float:
    """The signed radius whose canonical kernel has the second moment of a *continuous*
    scene's blur: ``r^2 / 4`` per axis for a disk of radius ``r = |rho|`` px.

    The canonical kernel is exact for the ray tracer's pixel model (nearest-texel
    textures: each pixel a constant patch). A render of continuous geometry (Cycles) or
    a photograph is the scene filtered by the pixel box, sampled; its depth of field is
    that same filtered scene blurred by the disk alone, so from its samples the blur has
    the disk's second moment ``r^2/4`` per axis and no more (the band-limited
    reconstruction adds none). The canonical kernel's bilinear splat adds
    ``E[f (1 - f)]`` (``f`` the fractional part of the shift ``r mu``; 1/6 for ``r``
    above ~1.5 px, ``~0.4 r`` below), which on Cycles scenes made small bokeh 3 to 4 %
    too wide at 3.4 px and in-focus detail softer than Cycles'. This radius is the
    solution of ``r'^2/4 + E[f(1 - f)](r') = r^2 / 4`` (bisection; the splat term from a
    stratified set of 4096 disk points; cached per 1/1024 px)."""
    q = int(round(abs(rho) * 1024.0))
    return math.copysign(_continuous_radius_q(q), rho)


@functools.lru_cache(maxsize=8192)
def _continuous_radius_q(q: int) -> float:
    r = q / 1024.0
    if r == 0.0:
        return 0.0
    target = r * r / 4.0
    if r >= 16.0:  # the splat term is 1/6 to within the point set's accuracy
        return math.sqrt(r * r - 4.0 / 6.0)
    lo, hi = 0.0, r
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        x = mid * _axis_points()
        f = x - np.floor(x)
        if mid * mid / 4.0 + float(np.mean(f * (1.0 - f))) < target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@functools.lru_cache(maxsize=1)
def _axis_points() -> np.ndarray:
    """x coordinates of a stratified 64 x 64 concentric point set of the unit disk."""
    g = (np.arange(64) + 0.5) / 64.0
    u, v = np.meshgrid(g, g)
    return concentric_disk(u.ravel(), v.ravel())[0]


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
    from scipy import ndimage

    R = kernel_radius(kernel)
    h, w = padded.shape[0] - 2 * R, padded.shape[1] - 2 * R
    out = np.empty((h, w, padded.shape[2]), np.float32)
    valid_only = h * w < 0.25 * padded.shape[0] * padded.shape[1]
    k = kernel.astype(np.float64 if valid_only else np.float32)
    for c in range(padded.shape[2]):
        if valid_only:
            from scipy import signal  # imported only here: it takes ~2 s to import

            out[..., c] = signal.correlate(padded[..., c].astype(np.float64), k, mode="valid",
                                           method="direct")
        else:
            out[..., c] = ndimage.correlate(padded[..., c], k, mode="constant",
                                            cval=0.0)[R:R + h, R:R + w]
    return out


_fft_threads = threading.local()


def fft_workers() -> int:
    """Threads one FFT of this module may use on the calling thread: all cores (-1) by
    default; :func:`set_fft_workers` lowers it on a thread that runs beside others (the
    compositor's blur threads, each running its own transforms). The result does not
    depend on it: the transforms split independent 1-D FFTs between threads."""
    return getattr(_fft_threads, "workers", -1)


def set_fft_workers(n: int) -> None:
    """Set :func:`fft_workers` for the calling thread (``n >= 1``, or -1 for all cores)."""
    _fft_threads.workers = int(n)


def _channel_peaks(a: np.ndarray) -> np.ndarray:
    """Largest magnitude of each channel of ``(H, W, C)`` (a scalar reduction per
    channel: numpy reduces a strided channel several times faster than ``axis=(0, 1)``)."""
    return np.array([max(float(a[..., c].max()), -float(a[..., c].min()))
                     for c in range(a.shape[-1])])


def correlate_fft(padded: np.ndarray, kernel: np.ndarray, peak=None) -> np.ndarray:
    """Valid-mode correlation by FFT (``FFT_DTYPE``). ``peak``: the per-channel largest
    magnitude that sets the noise floor cleared (default: that of ``padded``)."""
    from scipy import fft

    R = kernel_radius(kernel)
    H, W = padded.shape[:2]
    sh = (fft.next_fast_len(H, real=True), fft.next_fast_len(W, real=True))
    spec = fft.rfft2(padded.astype(FFT_DTYPE, copy=False), s=sh, axes=(0, 1), workers=fft_workers())
    # correlation = convolution with the flipped kernel; the kernel's [0, 0] tap lands
    # at the output offset 2R, which is where the "valid" region starts.
    kf = kernel_spectrum(kernel, sh)
    spec *= kf[..., None]
    full = fft.irfft2(spec, s=sh, axes=(0, 1), workers=fft_workers())
    out = np.ascontiguousarray(full[2 * R:H, 2 * R:W], dtype=np.float32)
    # clear rounding noise relative to each channel's largest input magnitude
    clear_below_floor(out, _channel_peaks(padded) if peak is None else peak)
    return out


def clear_below_floor(out: np.ndarray, peak) -> np.ndarray:
    """In place: every value of channel ``c`` below ``FFT_FLOOR * peak[c]`` (the FFT's
    rounding noise, and every negative value) becomes 0; the rest is kept."""
    floor = (FFT_FLOOR * np.asarray(peak, np.float64)).astype(np.float32)
    np.copyto(out, 0.0, where=out < floor)
    return out


def kernel_spectrum(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``rfft2`` of the flipped kernel at FFT size ``shape`` (complex, ``FFT_DTYPE``):
    correlation is convolution with the flipped kernel."""
    from scipy import fft

    return fft.rfft2(kernel[::-1, ::-1].astype(FFT_DTYPE), s=shape, workers=fft_workers())


#: Bytes of windows per batch of :func:`correlate_batch` (its spectrum takes
#: about as much again).
BATCH_BYTES = 32 << 20


def fft_size(n: int) -> int:
    """The transform length the FFT path uses for ``n`` samples along an axis."""
    from scipy import fft

    return fft.next_fast_len(n, real=True)


def correlate_batch(windows: np.ndarray, kernel: np.ndarray, method: str = "auto",
                    peak: np.ndarray | None = None,
                    window: tuple[int, int] | None = None) -> np.ndarray:
    """Valid-mode correlation of each of ``n`` equally sized padded windows
    ``(n, h + 2R, w + 2R, C)`` with one kernel: ``(n, h, w, C)`` float32, each window
    exactly as :func:`correlate` computes it, but in one call (one kernel spectrum for
    all). ``peak``: the per-channel largest magnitude that sets the FFT's noise floor
    (``FFT_FLOOR`` times it is cleared); default: that of the windows.
    ``window``: the windows' ``(h + 2R, w + 2R)`` when ``windows`` is larger, zero
    past them (e.g. already at the transform's size, :func:`fft_size`).

    Direct: ``scipy.ndimage.correlate`` with the kernel as a ``(1, k, k, 1)`` filter
    (the same taps in the same order as on one window). FFT: ``FFT_DTYPE`` ``rfft2``
    over the window axes."""
    from scipy import fft, ndimage

    n, Hw, Ww, C = windows.shape
    if window is not None:
        Hw, Ww = window
        if method != "fft" or kernel.shape == (1, 1):
            windows = windows[:, :Hw, :Ww]
    R = kernel_radius(kernel)
    h, w = Hw - 2 * R, Ww - 2 * R
    if kernel.shape == (1, 1):
        return np.array(windows * np.float32(kernel[0, 0]), dtype=np.float32)
    if method == "auto":
        method = "fft" if fft_is_cheaper(h, w, kernel) else "direct"
    if method == "direct":
        full = ndimage.correlate(windows, kernel.astype(np.float32)[None, :, :, None],
                                 mode="constant", cval=0.0)
        return np.ascontiguousarray(full[:, R:R + h, R:R + w])
    if method != "fft":
        raise ValueError(f"unknown convolution method {method!r}; use auto, direct or fft")
    if peak is None:
        peak = _channel_peaks(windows.reshape(-1, windows.shape[2], C))
    sh = (fft_size(Hw), fft_size(Ww))
    kf = kernel_spectrum(kernel, sh)[None, :, :, None]
    out = np.empty((n, h, w, C), np.float32)
    per = max(1, BATCH_BYTES // (np.dtype(FFT_DTYPE).itemsize * sh[0] * sh[1] * C))
    for a in range(0, n, per):
        spec = fft.rfft2(windows[a:a + per].astype(FFT_DTYPE, copy=False), s=sh,
                         axes=(1, 2), workers=fft_workers())
        spec *= kf
        full = fft.irfft2(spec, s=sh, axes=(1, 2), workers=fft_workers())
        out[a:a + per] = full[:, 2 * R:Hw, 2 * R:Ww]
    # |v| below the floor -> 0, then v >= 0: in one pass, v below the floor -> 0
    return clear_below_floor(out, peak)


#: Cost of the float32 FFT path per padded pixel, in units of one direct tap per
#: pixel, per ``log2`` of the window's pixel count. Measured with
#: :func:`correlate_batch` on 5-channel float32 windows (tiles of 64 to 1024 px, disk
#: radii 0.7 to 5 px, CPU time): direct costs ~10 ns per tap and pixel, the FFT
#: ~10.5 ns per pixel and ``log2 n``; the crossover fell between 9 and 25 taps.
FFT_TAPS_PER_LOG2 = 1.05


def fft_cost(n: int) -> float:
    """The FFT path's cost per pixel of an ``n``-pixel window, in direct taps."""
    return FFT_TAPS_PER_LOG2 * math.log2(max(n, 2))


def fft_is_cheaper(h: int, w: int, kernel: np.ndarray) -> bool:
    """Cost model: direct costs ~taps per pixel, the FFT :func:`fft_cost` of the
    padded window (crossover near 5x5 kernels for tiles of 64 px, 7x7 for 1024)."""
    return kernel.size > fft_cost((h + kernel.shape[0]) * (w + kernel.shape[1]))


def correlate(padded: np.ndarray, kernel: np.ndarray, method: str = "auto",
              peak=None) -> np.ndarray:
    """Valid-mode correlation of a padded ``(H, W, C)`` array with ``kernel``. ``peak``:
    the FFT's noise floor scale (:func:`correlate_fft`)."""
    if kernel.shape == (1, 1):
        return np.array(padded * np.float32(kernel[0, 0]), dtype=np.float32)
    if method == "auto":
        h, w = padded.shape[0] - kernel.shape[0] + 1, padded.shape[1] - kernel.shape[1] + 1
        method = "fft" if fft_is_cheaper(h, w, kernel) else "direct"
    if method == "fft":
        return correlate_fft(padded, kernel, peak)
    if method == "direct":
        return correlate_direct(padded, kernel)
    raise ValueError(f"unknown convolution method {method!r}; use auto, direct or fft")


# --------------------------------------------------------------------------------------
# Polygonal and anamorphic apertures

#: Grid density of the shape kernels, relative to the disk's (:data:`POINTS_PER_RADIUS`,
#: at the radius of the disk of the same area): 1.5 per side, about 45 points per
#: square pixel. At the disk's 20 the rim taps of a 1.5 ratio ellipse missed a 5000^2
#: point splat by up to 1.3 % of the plateau (3 to 31 px, 3 to 6 blades, ratios 0.7 to
#: 1.5); at 1.5 by 0.7 %, the disk's own level (0.8 %).
SHAPE_DENSITY = 1.5


def aperture_kernel(rho: float, aperture, cell: tuple[int, int, int] | None = None,
                    axes: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Canonical kernel of signed radius ``rho = A (d - d_f)`` pixels for an aperture
    (:class:`mpib_validate.runtime.camera.Aperture`): the splat of ``rho (ax mu, ay nu)``,
    ``(mu, nu)`` uniform over the unit aperture, ``(ax, ay) = axes`` per-axis scales (1:
    the canonical kernel; see :func:`continuous_axes`). A disk with unit axes is
    :func:`disk_kernel` itself (bit for bit). ``rho`` is quantised to 1/1024 px; its
    sign matters unless the shape is centrally symmetric (and for sub-apertures).
    Returns a read-only float64 correlation kernel that sums to one."""
    if aperture is None or (aperture.is_disk and axes == (1.0, 1.0)):
        return disk_kernel(rho, cell)
    q = int(round(rho * 1024.0))
    if cell is None and aperture.symmetric:
        q = abs(q)
    key = ("shape", q, aperture.blades, aperture.rotation, aperture.ratio,
           float(axes[0]), float(axes[1]), cell)
    return _cached(key, lambda: _shape_kernel(math.copysign(abs(q) / 1024.0, q), aperture,
                                              cell, axes))


def _shape_points(iu, iv, m: int, rho: float, aperture, axes) -> np.ndarray:
    """Points ``(P, 2)`` (x, y) of grid cells ``(iu, iv)`` of the ``m x m`` grid mapped
    onto the aperture scaled by ``rho (ax, ay)``."""
    mu, nu = aperture_map((iu + 0.5) / m, (iv + 0.5) / m, aperture)
    return np.stack([mu * (rho * axes[0]), nu * (rho * axes[1])], axis=1)


def _shape_kernel(rho: float, aperture, cell, axes) -> np.ndarray:
    """The kernel of :func:`aperture_kernel`.

    Whole aperture: as :func:`_disk_kernel`, the taps whose tent support
    ``[q - 1, q + 1]^2`` lies inside the (convex) shape (its four corners do) have the
    exact value ``1 / (area r^2)``; only the grid points that can reach the others are
    splatted: those within ``2 sqrt 2`` px of the rim. In the concentric parameter
    ``s`` (the unit square's frame is ``s = 1``) a point's distance to the rim is at
    least ``(1 - s) r a s_min`` (``a`` the apothem, ``s_min`` the smaller axis scale:
    the polygon map sends the circle of radius ``s`` onto the polygon scaled by ``s``),
    so they lie within ``2 sqrt 2 / (2 r a s_min)`` of the frame. The estimate is then
    rescaled so that the kernel sums to one.

    Sub-aperture ``(i, j, k)``: every point of the cell splatted, weight ``1 / n^2``
    (the part's share of the aperture is ``1 / k^2`` and its kernel sums to one). The
    cell's points number ``(m / k)^2``, about ``45 area r^2 / k^2``.
    """
    r = abs(rho)
    if r == 0.0:
        return np.ones((1, 1))
    sx, sy = axes[0] / aperture.ratio, axes[1]
    area = aperture.area * axes[0] * axes[1]
    k = 1 if cell is None else cell[2]
    m = _grid_side(SHAPE_DENSITY * r * math.sqrt(area / math.pi), k)
    if cell is not None:
        i, j, k = cell
        n = m // k
        iu, iv = np.meshgrid(np.arange(i * n, (i + 1) * n), np.arange(j * n, (j + 1) * n),
                             indexing="xy")
        iu, iv = iu.ravel(), iv.ravel()
        R = _support_radius(_shape_points(iu, iv, m, rho, aperture, axes))
        out = np.zeros((2 * R + 1, 2 * R + 1))
        for s0 in range(0, iu.size, _SPLAT_BATCH):
            _splat_into(out, _shape_points(iu[s0:s0 + _SPLAT_BATCH], iv[s0:s0 + _SPLAT_BATCH],
                                           m, rho, aperture, axes), 1.0 / (n * n))
        return out / out.sum()
    width = (2.0 * math.sqrt(2.0) + 0.01) / (2.0 * r * aperture.apothem * min(sx, sy))
    _, batches, weight = _edge_points_m(m, None, width)
    pts = [_shape_points(iu, iv, m, rho, aperture, axes) for iu, iv in batches]
    R = max(_support_radius(p) for p in pts)
    out = np.zeros((2 * R + 1, 2 * R + 1))
    for p in pts:
        _splat_into(out, p, weight)
    q = np.arange(-R, R + 1, dtype=np.float64)
    inside = np.ones((2 * R + 1, 2 * R + 1), bool)
    for cx in (-1.0, 1.0):
        for cy in (-1.0, 1.0):
            inside &= aperture.contains((q[None, :] + cx) / (rho * axes[0]),
                                        (q[:, None] + cy) / (rho * axes[1]))
    n_inside = int(inside.sum())
    if n_inside == 0:
        return out / out.sum()
    plateau = 1.0 / (area * r * r)
    out[inside] = 0.0
    edge = out.sum()
    out *= (1.0 - plateau * n_inside) / edge
    out[inside] = plateau
    return out


def shape_moments(aperture) -> tuple[float, float]:
    """Second moments ``(E[mu^2], E[nu^2])`` of the unit aperture (its centroid is the
    centre): ``1/4`` each for the disk; a regular polygon's are equal (``5/24`` for 6
    blades), the ratio divides the first by ``ratio^2``. From a 256^2 stratified grid
    (relative error below 1e-5)."""
    return _shape_moments(aperture.blades, aperture.rotation, aperture.ratio)


@functools.lru_cache(maxsize=64)
def _shape_moments(blades, rotation, ratio):
    from mpib_validate.runtime.camera import Aperture

    g = (np.arange(256) + 0.5) / 256.0
    u, v = np.meshgrid(g, g)
    mu, nu = aperture_map(u.ravel(), v.ravel(), Aperture(blades, rotation, ratio))
    return float(np.mean(mu * mu)), float(np.mean(nu * nu))


def continuous_axes(rho: float, aperture) -> tuple[float, float]:
    """Per-axis scales ``(ax, ay)`` whose :func:`aperture_kernel` has, along each image
    axis, the second moment of a *continuous* scene's blur, ``V rho^2`` (``V`` the unit
    aperture's :func:`shape_moments` along that axis): the solution of
    ``a^2 V r^2 + E[f (1 - f)](a r x) = V r^2`` for each axis, ``x`` the shape's
    coordinates along it (the splat's ``E[f(1 - f)]``, see :func:`continuous_radius`;
    a regular polygon's covariance is isotropic and the ratio keeps it axis-aligned, so
    two scales match it). For a disk this is the scale of :func:`continuous_radius`
    (which the compositor uses for disks: the same kernel up to the bisection's
    rounding). Cached per 1/1024 px."""
    q = int(round(abs(rho) * 1024.0))
    return _continuous_axes_q(q, aperture.blades, aperture.rotation, aperture.ratio)


@functools.lru_cache(maxsize=8192)
def _continuous_axes_q(q: int, blades: int, rotation: float, ratio: float):
    r = q / 1024.0
    if r == 0.0:
        return 1.0, 1.0
    xs = _shape_axis_points(blades, rotation, ratio)
    out = []
    for x in xs:
        V = float(np.mean(x * x))
        target = V * r * r
        if r * math.sqrt(V) * 2.0 >= 16.0:  # the splat term is 1/6 (as continuous_radius)
            out.append(math.sqrt(max(1.0 - 1.0 / (6.0 * target), 0.0)))
            continue
        lo, hi = 0.0, 1.0
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            p = mid * r * x
            f = p - np.floor(p)
            if mid * mid * target + float(np.mean(f * (1.0 - f))) < target:
                lo = mid
            else:
                hi = mid
        out.append(0.5 * (lo + hi))
    return out[0], out[1]


@functools.lru_cache(maxsize=64)
def _shape_axis_points(blades: int, rotation: float, ratio: float):
    """x and y coordinates of a stratified 64 x 64 point set of the unit aperture."""
    from mpib_validate.runtime.camera import Aperture

    g = (np.arange(64) + 0.5) / 64.0
    u, v = np.meshgrid(g, g)
    mu, nu = aperture_map(u.ravel(), v.ravel(), Aperture(blades, rotation, ratio))
    return mu, nu
