"""Rendering an MPI: Eq. 1 (MPIB), the exact aperture-sampled renderer, and between them.

Eq. 1 of the supplement, with layers ``i = 1..N`` far to near, premultiplied colour
``c_i alpha_i`` and kernels ``K_i`` of radius ``A |d_i - d_f|``::

    B = sum_i (c_i alpha_i * K_i) prod_{j>i} (1 - alpha_j * K_j)
        / sum_i (alpha_i * K_i) prod_{j>i} (1 - alpha_j * K_j)

computed far to near as ``acc <- acc (1 - alpha_i * K_i) + (c_i alpha_i, alpha_i) * K_i``
over premultiplied colour and a normaliser channel. The division is safe: where the
normaliser is zero the colour is zero, and elsewhere the ratio, a weighted average of
blurred layer colours, is clamped to ``[0, max layer colour]`` (it can leave that range
only through rounding). No NaN or Inf is possible, and no epsilon biases the result.

The output is ``(H, W, 4)`` float32: normalised linear colour and, in the fourth
channel, the composited alpha ``1 - prod (1 - alpha_i * K_i)`` (the coverage).

Eq. 1 replaces the aperture average of a product (visibility times colour) by a
product of averages, so it is not exact even with perfect layers. :func:`mpib_validate.cards.mpi.render_exact`
renders the MPI through every aperture sample instead (exact for fronto-parallel
layers); :func:`render_subapertures` sits between the two: it splits the aperture into
``k x k`` equal-area parts, composites each with Eq. 1 using that part's own kernels,
and averages them (``k = 1`` is Eq. 1, large ``k`` tends to the exact renderer).
For an MPI of additive groups built from passes (its layers together cover every
pixel), ``CompositeSettings.chain_px`` lays the slabs of one surface with the disjoint
"over" and each such chain on the renormalised farther composite (:class:`_Chain`),
which removes Eq. 1's cracks between slabs and its halos where the fill leaves a hole.

Fast paths, all optional and each checked against the plain path in the tests:

- ``conv="fft"`` (or ``"auto"``): FFT convolution instead of direct;
- ``crop=True``: each layer is blurred only over its content box grown by its kernel
  radius (empty planes are never stored, see :mod:`mpib_validate.runtime.layers.mpi`);
- ``reduce_above=R``: a layer whose radius exceeds ``R`` px is blurred at
  ``1/s`` resolution (``s = ceil(r / R)``, area-averaged down over the canvas's grid
  of ``s x s`` cells, bilinear up), with the disk shrunk so that the blur's second
  moment is preserved; like the full-resolution blur, only on the output tiles that
  its content reaches (the same result as over the whole box, up to rounding).

Image borders: a layer whose content reaches the canvas edge is continued past it by
replication (the official padding); content beyond the canvas is otherwise zero.
Layers taken from card scenes carry a margin of real content instead, so the ray
tracer (with cards larger than the frame) is the ground truth at the borders.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from mpib_validate.runtime.compositor import kernels as _k
from mpib_validate.runtime.cores import available_cores as _cores
from mpib_validate.runtime.layers import mpi as _M
from mpib_validate.runtime.layers.mpi import MPI, Layer
from mpib_validate.runtime.resample import bilinear_separable


@dataclass(frozen=True)
class CompositeSettings:
    """How to run Eq. 1.

    Attributes:
        kernel: ``canonical`` (exact for the ray tracer's pixel model: nearest-texel
            card textures), ``continuous`` (the canonical kernel at
            :func:`~mpib_validate.runtime.compositor.kernels.continuous_radius`: a render of
            continuous geometry or a photograph) or ``soft`` (official soft disk at
            integer radius).
        conv: ``direct``, ``fft`` or ``auto``.
        crop: blur each layer only over its content box plus kernel radius.
        reduce_above: radius (px) above which a layer is blurred at reduced
            resolution; ``None`` = never.
        backend: ``numpy`` (scipy direct/FFT), or ``llvm`` / ``cuda`` for the Dr.Jit
            gather-based blur (:mod:`mpib_validate.runtime.compositor.blur_drjit`; ``conv`` is then
            ignored). A Dr.Jit backend that cannot run falls back to numpy with a notice.
        slab_px: for an MPI of additive groups (:attr:`mpi.Layer.group`): consecutive
            groups whose blur radii span at most this many pixels are summed as one
            slab before "over" (``None``: each group alone). Fewer seams where one
            continuous surface crosses groups; two surfaces closer than this are then
            side by side rather than one in front (an error within a band of that
            many pixels).
        tiles: with ``crop`` and the numpy backend, blur each layer only on the output
            tiles whose window holds its content, where that costs less
            (:func:`_tile_plan`); the same result up to rounding.
        chain_px: for an MPI of additive groups whose layers together cover every
            pixel (one built from passes): consecutive slabs whose disparity ranges lie
            within this many pixels of blur radius of each other are taken as one
            surface (a *chain*) and combined with the disjoint "over" before the chain
            is laid with "over" on the farther composite, renormalised
            (:class:`_Chain`); ``None``: every slab with "over" (Eq. 1). The
            output's fourth channel is then not Eq. 1's coverage (the colour is
            unchanged by the renormalisation; only a zero coverage stays zero).
        aperture: the lens's shape (:class:`mpib_validate.runtime.camera.Aperture`:
            blades, rotation, ratio); ``None``, a disk. Every kernel is that shape's
            (:func:`~mpib_validate.runtime.compositor.kernels.aperture_kernel`), and a
            layer's blur reaches ``extent |rho|`` px (``extent = max(1, 1/ratio)``).
    """

    kernel: str = "canonical"
    conv: str = "auto"
    crop: bool = True
    reduce_above: float | None = None
    backend: str = "numpy"
    slab_px: float | None = None
    tiles: bool = True
    chain_px: float | None = None
    aperture: object = None


PLAIN = CompositeSettings(kernel="canonical", conv="direct", crop=False, reduce_above=None)


def _shaped(settings: CompositeSettings) -> bool:
    """Whether the settings' aperture is other than a disk."""
    return settings.aperture is not None and not settings.aperture.is_disk


def _layer_kernel(rho: float, settings: CompositeSettings, cell=None) -> np.ndarray:
    if _shaped(settings):
        ap = settings.aperture
        if settings.kernel == "canonical":
            return _k.aperture_kernel(rho, ap, cell)
        if settings.kernel == "continuous":
            return _k.aperture_kernel(rho, ap, cell, _k.continuous_axes(rho, ap))
        if settings.kernel == "soft":
            raise ValueError("the soft-disk kernel has no polygon or anamorphic form")
    if settings.kernel == "canonical":
        return _k.disk_kernel(rho, cell)
    if settings.kernel == "continuous":
        return _k.disk_kernel(_k.continuous_radius(rho), cell)
    if settings.kernel == "soft":
        if cell is not None:
            raise ValueError("the soft-disk kernel has no sub-aperture form")
        return _k.soft_disk(rho)
    raise ValueError(f"kernel must be 'canonical', 'continuous' or 'soft', got {settings.kernel!r}")


def _padded_region(layer: Layer, canvas: tuple[int, int], box: tuple[int, int, int, int],
                   R: int, out: np.ndarray | None = None) -> np.ndarray:
    """Layer content over ``box`` (canvas coordinates) grown by ``R`` on every side.

    Zero where the layer has no content; past the canvas edge the content is continued
    by replication where the layer's box touches that edge (the official padding).
    ``out``: a zeroed float32 array of that shape to write into (else a new one)."""
    y0, y1, x0, x1 = box
    hc, wc = canvas
    if out is None:
        out = np.zeros((y1 - y0 + 2 * R, x1 - x0 + 2 * R, layer.shape[2]), np.float32)
    ly0, ly1, lx0, lx1 = layer.box
    layer.read(out, y0 - R, x0 - R)
    # replication past the canvas edge, where the content touches it
    top, left = -(y0 - R), -(x0 - R)  # rows/cols of `out` before the canvas starts
    bottom = (y1 + R) - hc
    right = (x1 + R) - wc
    if top > 0 and ly0 == 0:
        out[:top] = out[top:top + 1]
    if bottom > 0 and ly1 == hc:
        out[out.shape[0] - bottom:] = out[out.shape[0] - bottom - 1:out.shape[0] - bottom]
    if left > 0 and lx0 == 0:
        out[:, :left] = out[:, left:left + 1]
    if right > 0 and lx1 == wc:
        out[:, out.shape[1] - right:] = out[:, out.shape[1] - right - 1:out.shape[1] - right]
    return out


def _reduced_kernel(rho: float, s: int, settings, cell):
    """Coarse kernel for blurring at 1/s resolution. Area-averaging down and bilinear
    interpolation up add ``s^2/12 + s^2/6`` of variance per axis, against the canonical
    kernel's ``1/6``; a disk of radius r has ``r^2/4``. The coarse disk is shrunk so that
    the overall second moment equals the full-resolution kernel's."""
    extra = s * s / 12.0 + s * s / 6.0 - 1.0 / 6.0
    if _shaped(settings):  # per axis: the fine kernel's second moment a^2 V rho^2 less the extra
        ap = settings.aperture
        axes = (_k.continuous_axes(rho, ap) if settings.kernel == "continuous"
                else (1.0, 1.0))
        V = _k.shape_moments(ap)
        axes = tuple(math.sqrt(max(a * a - extra / (v * rho * rho), 0.0))
                     for a, v in zip(axes, V))
        return _k.aperture_kernel(rho / s, ap, cell, axes)
    if settings.kernel == "continuous":  # the fine target is the disk's r^2/4 alone
        rho = _k.continuous_radius(rho)
        settings = replace(settings, kernel="canonical")
    r2 = max(rho * rho - 4.0 * extra, 0.0)
    return _layer_kernel(math.copysign(math.sqrt(r2), rho) / s, settings, cell)


def _correlate(padded: np.ndarray, kernel: np.ndarray, settings: CompositeSettings,
               peak=None) -> np.ndarray:
    if settings.backend != "numpy" and kernel.shape != (1, 1):
        from mpib_validate.runtime.compositor.backend import notify, resolve

        be = resolve(settings.backend)
        if be.name != "numpy":
            from mpib_validate.runtime.compositor.blur_drjit import correlate_drjit

            # the Dr.Jit kernel takes up to 4 channels: extras go in a second call
            parts = [correlate_drjit(padded[..., c:c + 4], kernel, be.name)
                     for c in range(0, padded.shape[2], 4)]
            return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=2)
        if be.notice and not getattr(_correlate, "_told", False):
            notify(be)
            _correlate._told = True
    return _k.correlate(padded, kernel, settings.conv, peak)


def _coarse_grid(y0: int, h: int, s: int, Rc: int) -> tuple[int, int]:
    """``(c0, n)``: the first canvas row and the number of the coarse cells that the
    reduced blur of output rows ``[y0, y0 + h)`` reads. The cells lie on the canvas grid
    (cell ``k`` covers canvas rows ``[k s, (k + 1) s)``), so every output pixel gets the
    same value whatever box or tile it is computed in; they reach ``Rc + 1`` cells beyond
    the output (the coarse kernel and the bilinear interpolation)."""
    first = y0 // s - (Rc + 1)
    last = -(-(y0 + h) // s) + Rc + 1  # exclusive
    return first * s, last - first


def _downsample(fine: np.ndarray, s: int) -> np.ndarray:
    """Area average of ``(h s, w s, C)`` over ``s x s`` cells: float32 ``(h, w, C)``."""
    hc, wc, C = fine.shape[0] // s, fine.shape[1] // s, fine.shape[2]
    # sum the s rows of each cell (contiguous adds), then its s columns
    rows = fine.reshape(hc, s, wc * s, C).sum(axis=1, dtype=np.float64)
    return (rows.reshape(hc, wc, s, C).sum(axis=2) / (s * s)).astype(np.float32)


def _upsample_axis(y0: int, h: int, s: int, Rc: int) -> np.ndarray:
    """Positions of output rows ``[y0, y0 + h)`` (pixel centres) in units of the
    blurred coarse cells (centres at integers; blurred cell 0 is coarse cell ``Rc``)."""
    c0, _ = _coarse_grid(y0, h, s, Rc)
    return (np.arange(y0, y0 + h) + 0.5 - c0) / s - 0.5 - Rc


def _blur_reduced(layer: Layer, canvas, rects, s: int, kc, settings: CompositeSettings,
                  peak=None):
    """Blur at 1/s resolution over equally sized canvas rectangles: area-average down on
    the canvas-aligned coarse grid (:func:`_coarse_grid`), correlate with ``kc`` (all
    rectangles in one batch), bilinear up. Yields ``(rect, blurred)``; each output pixel
    is the same whichever rectangle holds it (up to the FFT's rounding)."""
    Rc = _k.kernel_radius(kc)
    h, w = rects[0][1] - rects[0][0], rects[0][3] - rects[0][2]
    # a rectangle's cell count depends on its phase on the grid: take the largest
    nh, nw = -(-h // s) + 2 * Rc + 3, -(-w // s) + 2 * Rc + 3
    C = layer.shape[2]
    coarse = np.zeros((len(rects), nh, nw, C), np.float32)
    for j, (y0, y1, x0, x1) in enumerate(rects):
        cy, _ = _coarse_grid(y0, h, s, Rc)
        cx, _ = _coarse_grid(x0, w, s, Rc)
        fine = _padded_region(layer, canvas, (cy, cy + nh * s, cx, cx + nw * s), 0)
        coarse[j] = _downsample(fine, s)
    if settings.backend != "numpy" or len(rects) == 1:
        blurred = [_correlate(c, kc, settings, peak) for c in coarse]
    else:
        blurred = _k.correlate_batch(coarse, kc, settings.conv, peak)
    for (y0, y1, x0, x1), b in zip(rects, blurred):
        ty, tx = _upsample_axis(y0, h, s, Rc), _upsample_axis(x0, w, s, Rc)
        yield (y0, y1, x0, x1), bilinear_separable(b, ty, tx)


def _reduction(rho: float, settings: CompositeSettings) -> int:
    """The reduced path's factor ``s = ceil(|rho| / reduce_above)`` (1: full resolution)."""
    if settings.reduce_above is None or not abs(rho) > settings.reduce_above:
        return 1
    return int(math.ceil(abs(rho) / settings.reduce_above))


def _reach(rho: float, settings: CompositeSettings) -> int:
    """How far (px) a layer's blur reaches beyond its content: the kernel radius
    ``ceil(extent |rho|) + 1`` (extent 1 for a disk or a polygon, ``1/ratio`` for a
    ratio below 1), plus ``2 s`` for the reduced path's down/up sampling."""
    s = _reduction(rho, settings)
    if _shaped(settings):
        rho = rho * settings.aperture.extent
    return int(math.ceil(abs(rho))) + 1 + (2 * s if s > 1 else 0)


def _blur_layer(layer: Layer, box, canvas, kernel: np.ndarray, settings: CompositeSettings):
    """The layer blurred at full resolution with ``kernel`` over ``box`` (one window)."""
    return _correlate(_padded_region(layer, canvas, box, _k.kernel_radius(kernel)), kernel,
                      settings)


#: Side (px) of the canvas tiles on which the compositor records where a group was
#: written (the layers' storage tiles, :data:`mpib_validate.runtime.layers.mpi.TILE_PX`).
_TILE = _M.TILE_PX


def _window_cost(h: int, w: int, taps: int) -> float:
    """Relative cost of correlating one padded window of ``h x w`` pixels: per pixel
    the taps (direct) or the FFT's (:func:`mpib_validate.runtime.compositor.kernels.fft_cost`),
    whichever is less."""
    n = h * w
    return n * min(taps, _k.fft_cost(n))


#: Output tile sides (px, multiples of the storage tile) the compositor chooses from.
_TILE_SIDES = (64, 128, 256, 512)
#: Side (px) of the cells on which a layer's content is located for the tile plan (a
#: divisor of the storage tile): the kept tiles are those within the kernel radius,
#: rounded up to this, of content.
_FINE = 16


def _tile_plan(layer: Layer, R: int, taps: int, box, canvas):
    """``(T, ty, tx)``: the output tile side and the tiles (canvas tile indices) of
    ``box`` whose input window (the tile grown by ``R``) may hold content of the
    layer, for the side that costs least (:func:`_window_cost` summed over the
    tiles); ``None`` when one window over the whole box costs less."""
    by0, by1, bx0, bx1 = box
    best = _window_cost(by1 - by0 + 2 * R, bx1 - bx0 + 2 * R, taps), None
    occ = layer.occupancy(canvas, _FINE)
    e = -(-R // _FINE)  # fine cells a window reaches beyond its tile
    if e:
        from scipy import ndimage

        occ = ndimage.binary_dilation(occ, np.ones((2 * e + 1, 2 * e + 1), bool))
    for T in _TILE_SIDES:
        f = T // _FINE
        ny, nx = -(-occ.shape[0] // f), -(-occ.shape[1] // f)
        grid = np.zeros((ny * f, nx * f), bool)
        grid[:occ.shape[0], :occ.shape[1]] = occ
        occT = grid.reshape(ny, f, nx, f).any(axis=(1, 3))
        sub = occT[by0 // T:-(-by1 // T), bx0 // T:-(-bx1 // T)]
        cost = int(sub.sum()) * _window_cost(T + 2 * R, T + 2 * R, taps)
        if cost < best[0]:
            ty, tx = np.nonzero(sub)
            best = cost, (T, ty + by0 // T, tx + bx0 // T)
    return best[1]


def _clamp(blurred: np.ndarray) -> np.ndarray:
    """Blurred alpha clipped to [0, 1], colour and extra channels to >= 0 (in place):
    rounding cannot then leave the range of a blur of valid content."""
    np.maximum(blurred, 0.0, out=blurred)  # every channel at once (contiguous: 3x faster)
    alpha = blurred[..., 3]
    np.minimum(alpha, 1.0, out=alpha)
    return blurred


def _layer_peaks(layer: Layer) -> np.ndarray:
    """Largest magnitude of each channel of the layer (the FFT noise floor's scale),
    kept with the layer: it does not depend on the focus."""
    peak = layer._memo.get("peaks")
    if peak is None:
        peak = layer._memo["peaks"] = _k._channel_peaks(
            layer.tiles[1] if layer.tiles is not None else layer.rgba)
    return peak


def _straight_max(layer: Layer) -> np.ndarray:
    """Largest straight (un-premultiplied) value of each colour and extra channel of the
    layer, for the safe division; kept with the layer."""
    out = layer._memo.get("straight max")
    if out is None:
        rgba = layer.tiles[1] if layer.tiles is not None else layer.rgba
        a = rgba[..., 3]
        inv = np.divide(1.0, a, out=np.zeros_like(a), where=a > 0)
        out = np.array([float((rgba[..., c] * inv).max()) if a.size else 0.0
                        for c in range(rgba.shape[-1]) if c != 3], np.float32)
        layer._memo["straight max"] = out
    return out


def _blur_parts(layer: Layer, rho: float, box, canvas, settings: CompositeSettings, cell=None):
    """The blurred layer over ``box`` as ``(rect, blurred)`` parts, canvas rectangles
    (y0, y1, x0, x1) inside ``box``; the layer's blur is zero elsewhere: the parts of
    :func:`_blur_jobs`, run one after another."""
    for job in _blur_jobs(layer, rho, box, canvas, settings, cell):
        yield from job()


def _blur_jobs(layer: Layer, rho: float, box, canvas, settings: CompositeSettings, cell=None):
    """The blur of the layer over ``box`` as independent jobs: callables, each returning
    a list of ``(rect, blurred)`` parts (canvas rectangles inside ``box``, disjoint);
    any thread may run them, in any order.

    With ``crop`` and the numpy backend at full resolution, the box may be cut into
    square output tiles (:func:`_tile_plan`: the side that costs least, or none); a tile
    whose input window (the tile grown by the kernel radius) holds no content of the
    layer is skipped, and the kept windows are blurred in batches
    (:func:`mpib_validate.runtime.compositor.kernels.correlate_batch`), one job each. Each
    output pixel is the same correlation of the same window as untiled, with the same
    FFT noise floor (the layer's channel peaks): only rounding differs (an FFT of
    another size). Otherwise the box is one job of one part."""
    if _reduction(rho, settings) > 1:
        yield from _blur_jobs_reduced(layer, rho, box, canvas, settings, cell)
        return
    k = _layer_kernel(rho, settings, cell)  # here, on the one thread that draws the jobs
    if not settings.crop or settings.backend != "numpy":
        yield lambda: [(box, _clamp(_blur_layer(layer, box, canvas, k, settings)))]
        return
    R = _k.kernel_radius(k)
    plan = _kept_plan(layer, R, k.size, box, canvas) if k.size > 1 and settings.tiles else None
    peak = _layer_peaks(layer)
    if plan is None:
        yield lambda: [(box, _clamp(_correlate(_padded_region(layer, canvas, box, R), k,
                                               settings, peak)))]
        return
    T = plan[0]
    Hw = T + 2 * R  # a window: the tile grown by the kernel radius
    method = settings.conv
    if method == "auto":
        method = "fft" if _k.fft_is_cheaper(T, T, k) else "direct"
    # FFT windows are written straight into arrays of the transform's size (zero past
    # the window), which the transform would otherwise pad with a copy
    side = _k.fft_size(Hw) if method == "fft" else Hw

    def batch(rects):
        windows = np.zeros((len(rects), side, side, layer.shape[2]), np.float32)
        for j, r in enumerate(rects):
            _padded_region(layer, canvas, r, R, windows[j, :Hw, :Hw])
        blurred = _clamp(_k.correlate_batch(windows, k, method, peak, window=(Hw, Hw)))
        return list(_clipped(zip(rects, blurred), box))

    for rects in _tile_batches(plan, side, layer.shape[2]):
        yield functools.partial(batch, rects)


def _kept_plan(layer: Layer, reach: int, taps: int, box, canvas, s: int = 1):
    """:func:`_tile_plan`, kept with the layer: the k x k sub-aperture passes and a focus
    pull ask again for the same layer, reach and box."""
    key = ("tile plan", reach, taps, tuple(box), tuple(canvas), s)
    if key not in layer._memo:
        layer._memo[key] = _tile_plan(layer, reach, taps, box, canvas)
    return layer._memo[key]


def _tile_batches(plan, side: int, channels: int):
    """The plan's output tiles as canvas rectangles, in batches whose windows (``side``
    px square) fill at most :data:`kernels.BATCH_BYTES`."""
    T, ty, tx = plan
    per = max(1, _k.BATCH_BYTES // (4 * side * side * channels))
    for a in range(0, ty.size, per):
        yield [(y * T, y * T + T, x * T, x * T + T)
               for y, x in zip(ty[a:a + per], tx[a:a + per])]


def _clipped(parts, box):
    """``(rect, blurred)`` parts cut to ``box`` (those that overlap it)."""
    by0, by1, bx0, bx1 = box
    for (y0, y1, x0, x1), b in parts:
        c = (max(y0, by0), min(y1, by1), max(x0, bx0), min(x1, bx1))
        if c[0] < c[1] and c[2] < c[3]:
            yield c, b[c[0] - y0:c[1] - y0, c[2] - x0:c[3] - x0]


def _blur_jobs_reduced(layer: Layer, rho: float, box, canvas, settings: CompositeSettings,
                       cell=None):
    """:func:`_blur_jobs` for a layer blurred at reduced resolution
    (:func:`_blur_reduced`): with ``crop``, ``tiles`` and the numpy backend, on the output
    tiles whose window holds content (:func:`_tile_plan`, costed at full resolution: the
    reduction divides every alternative's cost alike), a job per batch; else the box.
    The coarse grid is the canvas's, so tiled and untiled agree up to rounding."""
    s = _reduction(rho, settings)
    kc = _reduced_kernel(rho, s, settings, cell)
    Rc = _k.kernel_radius(kc)
    plan = None
    if settings.crop and settings.tiles and settings.backend == "numpy" and kc.size > 1:
        # (Rc + 2) s: how far (fine px) a tile's coarse window reads beyond it
        plan = _kept_plan(layer, (Rc + 2) * s, kc.size, box, canvas, s)
    if plan is None:
        yield lambda: [(rect, _clamp(blurred)) for rect, blurred in
                       _blur_reduced(layer, canvas, [tuple(box)], s, kc, settings)]
        return
    peak = _layer_peaks(layer)
    side = _k.fft_size(-(-plan[0] // s) + 2 * Rc + 3)

    def batch(rects):
        return [(c, _clamp(b)) for c, b in
                _clipped(_blur_reduced(layer, canvas, rects, s, kc, settings, peak), box)]

    for rects in _tile_batches(plan, side, layer.shape[2]):
        yield functools.partial(batch, rects)


def composite(mpi: MPI, blur_parameter: float, focus_disparity: float,
              settings: CompositeSettings = CompositeSettings(), cell=None,
              progress=None) -> np.ndarray:
    """Eq. 1: blur every layer with its disk and composite far to near, normalised.

    Args:
        mpi: the layers (far to near).
        blur_parameter: ``A`` in pixels per unit disparity.
        focus_disparity: ``d_f`` in 1/scene-unit.
        settings: kernel, convolution path and fast paths.
        cell: ``(i, j, k)`` to use the kernels of one sub-aperture (see
            :func:`render_subapertures`).
        progress: optional ``progress(fraction)``, called after each layer; raising
            from it stops the composite (how a caller cancels).

    Returns:
        ``(H, W, 4)`` float32: normalised colour and composited alpha.
    """
    return _normalise(*_accumulate(mpi, blur_parameter, focus_disparity, settings, cell,
                                   progress))


def _accumulate(mpi: MPI, blur_parameter: float, focus_disparity: float,
                settings: CompositeSettings, cell, progress):
    """Eq. 1 before the division: ``(acc, cmax)``, the composited premultiplied colour
    with the normaliser in channel 3 (``(H, W, C)`` float32), and the colour bound.

    The layers' blurs (:func:`_layer_parts`: independent jobs) run on
    :func:`blur_threads` worker threads (one with a Dr.Jit backend), at most :data:`HELD_JOBS` finished jobs ahead
    of the "over" steps on the caller's thread (scipy's FFTs and numpy's array
    operations release the GIL, so they overlap on the cores; the result is the same
    to the bit, laid in the same order)."""
    if not blur_parameter > 0 or not math.isfinite(blur_parameter):
        raise ValueError(f"blur parameter A must be finite and > 0, got {blur_parameter}")
    H, W, m = mpi.height, mpi.width, mpi.margin
    canvas = mpi.canvas_shape
    C = mpi.channels
    acc = np.zeros((H, W, C), np.float32)  # premultiplied colour + normaliser (+ extras)
    cmax = np.zeros(C - 1, np.float32)
    frame = (m, m + H, m, m + W)
    ny, nx = -(-canvas[0] // _TILE), -(-canvas[1] // _TILE)
    group_sum, group_tiles, group_id = None, None, None  # the additive slab being summed
    layers, slab_of = _slab_layers(mpi, (settings.slab_px or 0.0) / blur_parameter)
    chain = None if settings.chain_px is None else _Chain(
        layers, slab_of, settings.chain_px / blur_parameter, (ny, nx), m, frame,
        [_reach(blur_parameter * (l.disparity - focus_disparity), settings) for l in layers],
        canvas)
    jobs = _layer_parts(layers, blur_parameter, focus_disparity, settings, cell, canvas,
                        frame, mpi.colour_max is None)

    def lay_slab():  # the summed slab onto acc: "over", or into the chain of its surface
        if chain is None:
            _over_tiles(acc, group_sum, group_tiles, m, frame)
        else:
            chain.push(acc, group_sum, group_tiles, group_id)

    # the Dr.Jit backends run their kernels from one thread
    threads = blur_threads() if settings.backend == "numpy" else 1
    with _OrderedPool(jobs, threads, HELD_JOBS) as items:
        for kind, i, result in items:
            if kind == "layer":  # far to near
                if progress is not None:
                    progress(i / max(len(layers), 1))
                if result is not None:
                    cmax = np.maximum(cmax, result)
                layer = layers[i]
                if layer.group is not None:
                    if group_tiles is not None and slab_of[i] != group_id:
                        lay_slab()
                        group_tiles = None
                    if group_sum is None:
                        group_sum = np.zeros_like(acc)
                    if group_tiles is None:
                        group_tiles = np.zeros((ny, nx), bool)
                    group_id = slab_of[i]
                continue
            for (y0, y1, x0, x1), blurred in result:
                if layer.group is None:
                    _over(acc[y0 - m:y1 - m, x0 - m:x1 - m], blurred)
                    continue
                # an additive group: sum its blurred shares, then lay the sum over acc
                group_sum[y0 - m:y1 - m, x0 - m:x1 - m] += blurred
                group_tiles[y0 // _TILE:-(-y1 // _TILE), x0 // _TILE:-(-x1 // _TILE)] = True
    if group_tiles is not None:
        lay_slab()
    if chain is not None:
        chain.flush(acc)
    if progress is not None:
        progress(1.0)
    return acc, (cmax if mpi.colour_max is None else mpi.colour_max)


def blur_threads() -> int:
    """Threads that blur layers during a composite: one per core available to the
    process, at most :data:`MAX_BLUR_THREADS`."""
    return max(1, min(_cores(), MAX_BLUR_THREADS))


#: Most threads blurring at once (each holds one job's working set,
#: :data:`mpib_validate.runtime.budget.TILED_BLUR_BYTES`).
MAX_BLUR_THREADS = 4
#: Jobs done ahead of the "over" steps, beyond those running: their blurred parts are
#: the memory the overlap costs besides the running jobs' working sets.
HELD_JOBS = 1


def _layer_parts(layers, blur_parameter, focus_disparity, settings, cell, canvas, frame,
                 need_cmax: bool):
    """For each layer far to near: ``("layer", i, job)``, whose job returns the largest
    straight colour of the layer (for the safe division) or None, then its blur's jobs
    ``("parts", None, job)`` (:func:`_blur_jobs`); a layer whose output box is empty
    outside the frame has none."""
    m = frame[0]
    H, W = frame[1] - m, frame[3] - m
    for i, layer in enumerate(layers):
        rho = blur_parameter * (layer.disparity - focus_disparity)
        if settings.crop:
            R = _reach(rho, settings)
            ly0, ly1, lx0, lx1 = layer.box
            # output box: content grown by R, inside the frame; content touching the
            # canvas edge is replicated outward, so the box reaches the frame edge there
            y0 = m if ly0 == 0 else max(m, ly0 - R)
            x0 = m if lx0 == 0 else max(m, lx0 - R)
            y1 = m + H if ly1 == canvas[0] else min(m + H, ly1 + R)
            x1 = m + W if lx1 == canvas[1] else min(m + W, lx1 + R)
            if y0 >= y1 or x0 >= x1:
                continue
            box = (y0, y1, x0, x1)
        else:
            box = frame
        yield "layer", i, (functools.partial(_straight_max, layer) if need_cmax
                           else _no_value)
        for job in _blur_jobs(layer, rho, box, canvas, settings, cell):
            yield "parts", None, job


def _no_value():
    return None


class _OrderedPool:
    """Run the jobs of a sequence of ``(kind, key, job)`` on ``threads`` worker threads
    and give ``(kind, key, result)`` in the sequence's order, at most ``threads +
    held`` jobs ahead of the consumer; an exception in a job is raised in the consumer
    at its place. The sequence itself (the kernels and tile plans) is drawn on one
    more thread (:class:`_Prefetch`), which submits the jobs. Leaving the ``with`` block
    early (an exception in the consumer, e.g. a cancelling ``progress``) stops that
    thread, drops the jobs not started and waits for the running ones, so no thread
    outlives it. Each worker runs its FFTs on ``max(1, cores // threads)`` threads
    (:func:`mpib_validate.runtime.compositor.kernels.set_fft_workers`)."""

    def __init__(self, items, threads: int, held: int):
        from concurrent.futures import ThreadPoolExecutor

        self._items = items
        self._pool = ThreadPoolExecutor(
            threads, thread_name_prefix="mpib-blur", initializer=_k.set_fft_workers,
            initargs=(max(1, _cores() // threads),))
        # a job is submitted before the producer waits to queue it: one more is running
        self._ahead = _Prefetch(((kind, key, self._pool.submit(job)) for kind, key, job
                                 in items), max(1, threads + held - 1))

    def __enter__(self):
        return ((kind, key, future.result()) for kind, key, future in self._ahead.__enter__())

    def __exit__(self, *exc):
        self._ahead.__exit__(*exc)
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._items.close()
        return False


class _Prefetch:
    """Run a generator on a thread of its own, at most ``depth`` items ahead of the
    consumer; items come out in order, and an exception in the generator is raised in
    the consumer at its place. Leaving the ``with`` block early (an exception in the
    consumer, e.g. a cancelling ``progress``) stops the worker before returning."""

    def __init__(self, gen, depth: int):
        import queue
        import threading

        self._gen, self._queue = gen, queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mpib-blur-plan", daemon=True)

    def _run(self):
        try:
            for item in self._gen:
                if not self._put(("item", item)):
                    return
            self._put(("done", None))
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            self._put(("error", exc))

    def _put(self, msg) -> bool:
        import queue

        while not self._stop.is_set():
            try:
                self._queue.put(msg, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def __enter__(self):
        self._thread.start()
        return self._items()

    def _items(self):
        while True:
            kind, value = self._queue.get()
            if kind == "item":
                yield value
            elif kind == "done":
                return
            else:
                raise value

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._gen.close()
        return False


def _slab_layers(mpi: MPI, span: float):
    """:func:`_merge_within_slabs` of the MPI's layers for a slab span (1/scene-unit),
    kept with the MPI: it depends on ``A`` (through the span), not on the focus, so a
    focus pull merges once. The key holds the layers' identities, so a changed layer
    list is merged afresh; only the latest span is kept."""
    key = (span, tuple(id(l) for l in mpi.layers))
    hit = mpi._derived.get("slabs")
    if hit is not None and hit[0] == key:
        return hit[1]
    merged = _merge_within_slabs(mpi.layers, _slabs(mpi.layers, span))
    mpi._derived["slabs"] = (key, merged, list(mpi.layers))  # the list keeps the ids alive
    return merged


def _disparity_ranges(layers, keys) -> tuple[dict, dict]:
    """``(lo, hi)``: the smallest and largest layer disparity per key (``keys[i]`` of
    ``layers[i]``; None keys are left out)."""
    lo, hi = {}, {}
    for layer, k in zip(layers, keys):
        if k is not None:
            lo[k] = min(lo.get(k, math.inf), layer.disparity)
            hi[k] = max(hi.get(k, -math.inf), layer.disparity)
    return lo, hi


def _slabs(layers, span: float) -> list:
    """Slab id of each layer: consecutive additive groups merged while the slab's
    disparity span stays within ``span`` (0: one slab per group); None for ungrouped
    layers."""
    lo, hi = _disparity_ranges(layers, [l.group for l in layers])
    out, slab, start, last = [], -1, 0.0, None
    for l in layers:
        if l.group is None:
            out.append(None)
            continue
        if l.group != last and (last is None or span <= 0 or hi[l.group] - start > span):
            slab, start = slab + 1, lo[l.group]
        last = l.group
        out.append(slab)
    return out


def _merge_within_slabs(layers, slab_of):
    """Layers of one slab on the same plane summed into one (box union): a slab is
    summed after blurring anyway, and the blur is linear, so each plane of a slab is
    blurred once. Returns the layers and their slab ids, in slab order (ungrouped
    layers pass through)."""
    if all(s is None for s in slab_of):
        return layers, slab_of
    merged: dict = {}
    order = []
    for layer, slab in zip(layers, slab_of):
        key = (slab, layer.disparity) if slab is not None else (id(layer),)
        if key not in merged:
            merged[key] = [layer]
            order.append(key)
        else:
            merged[key].append(layer)
    out, slabs = [], []
    for key in order:
        group = merged[key]
        first = group[0]
        if len(group) == 1:
            out.append(first)
        else:
            y0 = min(l.y0 for l in group)
            x0 = min(l.x0 for l in group)
            y1 = max(l.box[1] for l in group)
            x1 = max(l.box[3] for l in group)
            rgba = np.zeros((y1 - y0, x1 - x0, first.rgba.shape[2]), np.float32)
            for l in group:
                ly0, ly1, lx0, lx1 = l.box
                rgba[ly0 - y0:ly1 - y0, lx0 - x0:lx1 - x0] += l.rgba
            out.append(Layer(first.disparity, rgba, y0, x0, first.group))
        slabs.append(key[0] if len(key) == 2 else None)
    return out, slabs


def _over(region: np.ndarray, blurred: np.ndarray) -> None:
    """``region <- region (1 - a_blur) + blurred`` in place (premultiplied colour and the
    normaliser: Eq. 1's "over"). A strided region (a tile of the frame) is updated as a
    contiguous copy: numpy broadcasts the ``(..., 1)`` factor over one about twice as
    slowly, more than the two copies cost. Either way the same operations in the same
    order, so the same result to the bit."""
    work = region if region.flags.c_contiguous else region.copy()
    work *= 1.0 - blurred[..., 3:4]
    work += blurred
    if work is not region:
        region[...] = work


def _over_group(acc, group_sum, box, m):
    """``acc <- acc (1 - a_G) + G`` over ``box`` for the summed group ``G`` (its alpha
    clipped to 1), then clear ``G`` there."""
    y0, y1, x0, x1 = box
    g = group_sum[y0 - m:y1 - m, x0 - m:x1 - m]
    region = acc[y0 - m:y1 - m, x0 - m:x1 - m]
    region *= 1.0 - np.minimum(g[..., 3:4], 1.0)
    region += g
    g[...] = 0.0


def _over_tiles(acc, group_sum, tiles, m, frame):
    """:func:`_over_group` on each row run of the marked canvas tiles (side
    ``_TILE``) within the frame: where the group was written, and nowhere twice."""
    for rect in _runs(tiles, _TILE, frame):
        _over_group(acc, group_sum, rect, m)


def _runs(tiles: np.ndarray, T: int, clip):
    """Rectangles (y0, y1, x0, x1), canvas pixels clipped to ``clip``, of the runs of
    consecutive True tiles of each row of the tile map ``tiles`` (side ``T``)."""
    cy0, cy1, cx0, cx1 = clip
    for ty in np.flatnonzero(tiles.any(axis=1)):
        row = np.concatenate([[False], tiles[ty], [False]])
        edges = np.flatnonzero(row[1:] != row[:-1])
        y0, y1 = max(ty * T, cy0), min(ty * T + T, cy1)
        if y0 >= y1:
            continue
        for a, b in zip(edges[::2], edges[1::2]):
            x0, x1 = max(a * T, cx0), min(b * T, cx1)
            if x0 < x1:
                yield y0, y1, x0, x1


#: The farther composite is renormalised by ``1 / max(n, _RENORM_FLOOR)`` (``n`` its
#: normaliser): raised to full strength where it holds at least a quarter of its
#: rays, in proportion below. Next to an occluder's silhouette, the hole that the
#: renormalisation fills, the farther blur holds the far side's half-plane and the fill
#: (``n`` about 1/2 and more; 0.3 where the occluder's own blur ends on the box before
#: the sky of ``tests/test_chain.py``). Inside a surface cut into planes of different
#: radii the chain's own coverage falls short by up to 10 % where its disparity crosses
#: planes (the shares of a pixel are blurred with different kernels), which is no hole;
#: there the farther composite is only the tail of a distant blur, and raising a tail of
#: 1/200 of its rays to full strength laid patches of the far colour, cut off sharply
#: where the tail ends, inside the blurred surface (``tests/test_chain.py``). FFT noise
#: is cleared below ``kernels.FFT_FLOOR`` (1e-6 of the channel peaks), far below.
_RENORM_FLOOR = 0.25


class _Chain:
    """Slabs of one surface combined before they are laid on what lies behind them.

    Eq. 1 lays each slab with "over": ``acc <- G + (1 - a_G) acc``. Two failures of
    that on an MPI built from passes (every pixel is covered by some layer, so the
    composite of all layers is opaque; a coverage below 1 is a hole, not a view):

    - *cracks*: where two slabs of one continuous surface meet, their blurred edges
      are complementary (``a_1 + a_2 = 1``) but "over" leaves ``(1 - a_1)(1 - a_2)``
      of what lies behind showing through (up to 1/4). The *disjoint over* of
      Porter and Duff, ``C <- G_2 + min(1, (1 - a_2) / a_1) G_1``, sums the two where
      their coverages add up to at most 1 (disjoint, as at a seam) and lets the
      nearer one hide the farther where they overlap (``a_1 = 1``: it is "over");
    - *holes*: the fill behind an occluder reaches only ``A (d_near - d_far)``, so a
      farther layer's blur is partly empty next to the occluder's silhouette (its
      normaliser ``n < 1``), and Eq. 1's final division gives the missing share to
      every layer, the occluder's colour too (a halo of it). The rays that miss the
      occluder see the farther surface: the farther composite is renormalised,
      ``acc <- acc / n``, before a chain is laid on it.

    A chain also holds what lies behind a surface: the hidden background filled behind
    a silhouette, at the far side's disparity, when the disparities in between are
    held elsewhere in the picture (a photograph's map is continuous). Where a surface
    crosses two slabs, the disjoint over of the nearer on everything before it shrank
    the farther slab and that fill alike, and the fill showed through the surface
    (light patches inside blurred hair, up to a quarter of the colour). Where the new
    slab and the last one are one surface (:meth:`_weights`), the two are combined
    first and what lay before them fills only what they leave, and nothing deep inside
    their opaque footprint (:func:`_disjoint_over_last`).

    Consecutive slabs are one chain while the disparity gap between them is within
    ``gap`` (the planes of one continuous surface are a plane step apart, a gap in
    the content more); the disjoint over inside a chain, renormalisation and "over"
    between chains (not inside one: a chain's own partial coverage at a crack is what
    the disjoint over closes). Each step works on the canvas tiles (side ``_TILE``)
    that the slab wrote, as :func:`_over_tiles` does.
    """

    def __init__(self, layers, slab_of, gap: float, tiles_shape, margin: int, frame,
                 reach, canvas):
        self.lo, self.hi = _disparity_ranges(layers, slab_of)
        self.gap, self.m, self.frame = gap, margin, frame
        self.shape = tiles_shape
        self.sum = None  # the chain's combined premultiplied colour and normaliser
        self.tiles = None
        self.last = None
        self.canvas = canvas
        self.members = set()  # the slabs of the current chain
        self.cover = None  # the sum of the chain's slabs' footprint alphas (canvas)
        self.cover_reach = None  # the same sum, each alpha times its slab's blur reach
        self.last_sum = None  # the last slab as laid (frame-sized), on last_tiles
        self.last_tiles = None
        self.last_foot = None  # the last slab's _footprint
        self.by_slab: dict = {}  # slab -> [(layer, reach)]
        for layer, s, r in zip(layers, slab_of, reach):
            self.by_slab.setdefault(s, []).append((layer, r))

    def _footprint(self, slab) -> tuple:
        """Where the slab's layers hold content: ``(alpha, cells, box)``, the sum of
        their alphas (unblurred; canvas float32, padded to whole storage tiles), on
        :data:`_ONE_CELL` px cells where it is above 0, and the layers' union box
        ``(y0, y1, x0, x1)`` (None without layers)."""
        f = _ONE_CELL
        H, W = self.canvas
        hc, wc = -(-H // f), -(-W // f)
        T = _M.TILE_PX  # a multiple of f: the storage tiles' grid is the cells' grid
        alpha = np.zeros((-(-H // T) * T, -(-W // T) * T), np.float32)
        cells = np.zeros((hc, wc), bool)
        layers = [layer for layer, _ in self.by_slab.get(slab, [])]
        for layer in layers:
            layer.add_channel(alpha, 3)
        if not layers:
            return alpha, cells, None
        box = (min(l.box[0] for l in layers), max(l.box[1] for l in layers),
               min(l.box[2] for l in layers), max(l.box[3] for l in layers))
        cy0, cx0, cy1, cx1 = box[0] // f, box[2] // f, -(-box[1] // f), -(-box[3] // f)
        cells[cy0:cy1, cx0:cx1] = _cells(alpha[cy0 * f:cy1 * f, cx0 * f:cx1 * f] > 0)
        return alpha, cells, box

    def _weights(self, slab, foot, tiles):
        """``(same, (cy0, cx0), deep)``, the two weights of :func:`_disjoint_over_last`
        for the slab on the last one over the box of ``tiles`` and around it (from canvas
        pixel ``(4 cy0, 4 cx0)``):

        - *same*, on :data:`_ONE_CELL` px cells (from cell ``(cy0, cx0)``;
          :func:`_cell_weights` reads it at pixels), how far the two are one surface: 1
          where either holds content, but 0 within the slab's blur reach of a place
          where both do. Visible content never overlaps itself, so content of the last
          slab under this one is hidden background filled behind it: the two meet at a
          depth jump, and what lies behind both may show between them;
        - *deep*, per pixel (a number where it is the same everywhere), how far the
          pixel lies inside the two's opaque footprint: :func:`_depth_ramp` of its
          distance to the nearest pixel they do not cover opaquely
          (:func:`_deep_inside`), 0 within ``R`` px (``R`` the larger of their blur
          reaches), rising linearly to 1 at ``R + 1``. A thin lens sees only them
          there, so nothing behind fills their shortfall.

        Beyond the canvas the compositor continues the content: there it counts as
        opaque."""
        from scipy import ndimage

        f = _ONE_CELL
        H, W = self.canvas
        rows = np.flatnonzero(tiles.any(axis=1))
        cols = np.flatnonzero(tiles.any(axis=0))
        y0, y1 = rows[0] * _TILE, min((rows[-1] + 1) * _TILE, H)
        x0, x1 = cols[0] * _TILE, min((cols[-1] + 1) * _TILE, W)
        reach = max(self._slab_reach(slab), self._slab_reach(self.last))
        R = int(math.ceil(reach))
        grow = int(math.ceil((R + 1) / f)) + 2  # cells: the filters' reach, and one
        cy0, cy1 = max(0, y0 // f - grow), min(foot[1].shape[0], -(-y1 // f) + grow)
        cx0, cx1 = max(0, x0 // f - grow), min(foot[1].shape[1], -(-x1 // f) + grow)
        py, px = slice(cy0 * f, cy1 * f), slice(cx0 * f, cx1 * f)
        here, last = foot[1][cy0:cy1, cx0:cx1], self.last_foot[1][cy0:cy1, cx0:cx1]
        same = (here | last).astype(np.float32)
        if (here & last).any():  # cells where both may hold content: at one pixel?
            jump = _cells((foot[0][py, px] > 0) & (self.last_foot[0][py, px] > 0))
            if jump.any():
                n = 2 * int(math.ceil(R / f)) + 3
                same[ndimage.maximum_filter(jump, size=n)] = 0.0
        solid = (foot[0][py, px] + self.last_foot[0][py, px]) >= np.float32(1.0 - 1e-3)
        solid[H - cy0 * f:, :] = True
        solid[:, W - cx0 * f:] = True
        return same, (cy0, cx0), _deep_inside(solid, R)

    def push(self, acc, group_sum, group_tiles, slab) -> None:
        """Add the summed slab ``group_sum`` (written on ``group_tiles``; cleared here)."""
        if self.sum is None:
            self.sum = np.zeros_like(acc)
        if self.tiles is not None and self.lo[slab] - self.hi[self.last] > self.gap:
            self.flush(acc)
        fresh = self.tiles is None  # the chain's sum is zero: the slab is copied in
        if fresh:
            self.tiles = np.zeros(self.shape, bool)
        if self.last_sum is None:
            self.last_sum = np.zeros_like(acc)
        m = self.m
        foot = self._footprint(slab)
        if fresh:
            self.cover = np.zeros_like(foot[0])
            self.cover_reach = np.zeros_like(foot[0])
        if foot[2] is not None:
            y0, y1, x0, x1 = foot[2]
            a = foot[0][y0:y1, x0:x1]
            self.cover[y0:y1, x0:x1] += a
            self.cover_reach[y0:y1, x0:x1] += np.float32(self._slab_reach(slab)) * a
        if not fresh:
            same, origin, deep = self._weights(slab, foot, group_tiles)
            oy, ox = origin[0] * _ONE_CELL, origin[1] * _ONE_CELL
        if self.last_tiles is not None:  # the last slab is zero where this one is not
            for y0, y1, x0, x1 in _runs(self.last_tiles & ~group_tiles, _TILE, self.frame):
                self.last_sum[y0 - m:y1 - m, x0 - m:x1 - m] = 0.0
        for y0, y1, x0, x1 in _runs(group_tiles, _TILE, self.frame):
            g = group_sum[y0 - m:y1 - m, x0 - m:x1 - m]
            c = self.sum[y0 - m:y1 - m, x0 - m:x1 - m]
            last = self.last_sum[y0 - m:y1 - m, x0 - m:x1 - m]
            if fresh:
                c[...] = g
            else:
                d = deep if np.isscalar(deep) else deep[y0 - oy:y1 - oy, x0 - ox:x1 - ox]
                _disjoint_over_last(c, last, g, _cell_weights(same, origin, y0, y1, x0, x1), d)
            last[...] = g
            g[...] = 0.0
        self.last_tiles = group_tiles.copy()
        self.last_foot = foot
        self.tiles |= group_tiles
        self.last = slab
        self.members.add(slab)

    def flush(self, acc) -> None:
        """Lay the chain on ``acc`` (renormalised) with "over"; start a new chain."""
        if self.tiles is None:
            return
        m = self.m
        inside = self._inside()
        for y0, y1, x0, x1 in _runs(self.tiles, _TILE, self.frame):
            region = acc[y0 - m:y1 - m, x0 - m:x1 - m]
            # where n = 0 the colour is 0 too (up to FFT noise, raised to 1e-9 at most)
            gain = 1.0 / np.maximum(region[..., 3:4], np.float32(_RENORM_FLOOR))
            if inside is not None:
                w, (iy0, ix0) = inside
                gain = gain * (1.0 - w[y0 - iy0:y1 - iy0, x0 - ix0:x1 - ix0, None])
            region *= gain
        _over_tiles(acc, self.sum, self.tiles, m, self.frame)
        for y0, y1, x0, x1 in _runs(self.last_tiles, _TILE, self.frame):
            self.last_sum[y0 - m:y1 - m, x0 - m:x1 - m] = 0.0
        self.last_tiles = self.last_foot = self.cover = self.cover_reach = None
        self.tiles = None
        self.members = set()

    def _slab_reach(self, slab) -> float:
        """The largest blur reach (px) of the slab's layers (0 without layers)."""
        return max([r for _, r in self.by_slab.get(slab, [])] + [0])

    def _inside(self):
        """``(w, (y0, x0))``: over the box of the chain's tiles (canvas pixels from
        ``(y0, x0)``), how far each pixel lies inside the chain's opaque footprint:
        0 within the surface's own blur reach ``R`` at that pixel of a pixel that the
        chain does not cover opaquely, rising linearly to 1 at ``R + 1``; None when no
        pixel is that deep. ``R`` is the mean of the reaches of the chain's slabs at the
        pixel, weighted by their footprint alphas there (a pixel's shares between two
        planes): the radius of the cone that a thin lens sees the surface through from
        that pixel. A chain holds every slab of a continuous map between two gaps, so
        its largest reach can be that of another object, twice the surface's; a ramp
        at that reach would let the farther composite show through the surface's
        shortfall beyond the surface's own reach (a faint line of a light wall inside a
        blurred black helmet, 17 display levels; ``tests/test_chain.py``).

        There a thin lens sees only the chain's surface, and a coverage below 1 is not
        a hole but the shortfall of a surface cut into planes of different radii (the
        shares of a pixel between two planes are blurred with different kernels: up to
        10 % where a noisy disparity crosses planes). The farther composite is not laid
        under it there, so Eq. 1's division normalises the chain's own colour, as it
        does without chains; the ramp keeps the change continuous."""
        if not self.members:
            return None
        from scipy import ndimage

        rows = np.flatnonzero(self.tiles.any(axis=1))
        cols = np.flatnonzero(self.tiles.any(axis=0))
        y0, y1 = rows[0] * _TILE, min((rows[-1] + 1) * _TILE, self.canvas[0])
        x0, x1 = cols[0] * _TILE, min((cols[-1] + 1) * _TILE, self.canvas[1])
        if 2 * min(self._slab_reach(s) for s in self.members) >= min(y1 - y0, x1 - x0):
            return None
        cover = self.cover[y0:y1, x0:x1]
        solid = cover >= np.float32(1.0 - 1e-3)
        # the compositor continues content at the canvas edge outward: so does the mask
        pad = [(0 if y0 == 0 else 1, 0 if y1 == self.canvas[0] else 1),
               (0 if x0 == 0 else 1, 0 if x1 == self.canvas[1] else 1)]
        padded = np.pad(solid, pad, constant_values=False)
        if padded.all():
            return None
        dist = ndimage.distance_transform_edt(padded)[pad[0][0]:pad[0][0] + solid.shape[0],
                                                      pad[1][0]:pad[1][0] + solid.shape[1]]
        reach = self.cover_reach[y0:y1, x0:x1] / np.maximum(cover, np.float32(1e-6))
        w = _depth_ramp(dist, reach).astype(np.float32)
        return (w, (y0, x0)) if w.any() else None


def _depth_ramp(dist: np.ndarray, R) -> np.ndarray:
    """How far inside an opaque footprint a pixel lies, from its distance ``dist`` (px)
    to the nearest pixel the footprint does not cover: ``clip(dist - R, 0, 1)``, 0
    within the blur reach ``R`` (px; a number, or one per pixel) of the footprint's
    edge, where a lens still sees past it, 1 from ``R + 1`` on
    (:meth:`_Chain._weights`, :meth:`_Chain._inside`).

    Deeper than ``R`` a thin lens sees nothing behind the footprint, and what lies
    behind would show only through the few percent by which a surface cut into planes
    of different radii falls short of full coverage: a pattern of that shortfall's
    grain, which in a dark region is tens of display levels (a visor's black rim before
    a light wall: 20 to 30). A ramp wider than a pixel kept that pattern over its width,
    with an end that a blur of ``R`` cannot make; one pixel keeps the rule continuous
    enough."""
    return np.clip(dist - R, 0.0, 1.0)


#: Side (px) of the cells on which a chain decides where a slab and the last one are
#: one surface (:meth:`_Chain._weights`; bilinear between cell centres, so that the
#: rule changes continuously), and which bound how deep inside their footprint a pixel
#: lies (:func:`_deep_inside`).
_ONE_CELL = 4  # :func:`_cells` reads 4 bools as one word


def _cells(mask: np.ndarray, every: bool = False) -> np.ndarray:
    """``mask`` (bool, sides multiples of :data:`_ONE_CELL` = 4) on 4 px cells: True where
    any pixel of the cell is (``every``: all are). A row of 4 bools is read as one
    32-bit word (1 byte per bool, so all four set is 0x01010101 in either byte order)."""
    h, w = mask.shape
    words = np.ascontiguousarray(mask).view(np.uint32).reshape(h // 4, 4, w // 4)
    return (words == 0x01010101).all(axis=1) if every else (words != 0).any(axis=1)


def _cell_weights(cells: np.ndarray, origin, y0: int, y1: int, x0: int, x1: int):
    """The weight *same* of :meth:`_Chain._weights` (on cells from cell ``origin``) at
    canvas pixels ``[y0, y1) x [x0, x1)``: bilinear between the cells' centres, so that
    it changes continuously; a number where the cells around are all alike."""
    f = _ONE_CELL
    cy0, cx0 = origin
    by0, bx0 = max(0, (y0 // f) - 1 - cy0), max(0, (x0 // f) - 1 - cx0)
    block = cells[by0:-(-y1 // f) + 1 - cy0, bx0:-(-x1 // f) + 1 - cx0]
    first = block[0, 0]
    if (block == first).all():
        return float(first)
    ty = (np.arange(y0, y1) + 0.5) / f - 0.5 - cy0 - by0
    tx = (np.arange(x0, x1) + 0.5) / f - 0.5 - cx0 - bx0
    return bilinear_separable(block, ty, tx)


def _deep_inside(solid: np.ndarray, R: int):
    """:func:`_depth_ramp` ``clip(d - R, 0, 1)`` of the Euclidean distance ``d`` (px)
    from each pixel of ``solid`` (bool, sides multiples of :data:`_ONE_CELL`) to the
    nearest False pixel of the array, as ``scipy.ndimage.distance_transform_edt`` gives
    it, computed only where the ramp is decided (float32; a number where it is 0 or 1
    everywhere).

    On 4 px cells the distance ``c`` (px) between the centre of a pixel's cell and that
    of the nearest cell not wholly solid bounds it, ``|d - c| <= 3 sqrt 2`` (each pixel
    lies within ``1.5 sqrt 2`` of its cell's centre): the ramp is 1 where
    ``c - 3 sqrt 2 >= R + 1``, 0 in cells wholly not solid and where
    ``c + 3 sqrt 2 <= R``. In the cells left, a ring about 10 px wide at ``R`` from the
    edge, ``d`` is exact and clipped at ``R + 1``: the distance ``g`` to the nearest
    False pixel in the pixel's column (running extremes of row indices), then
    ``d^2 = min_{|k| <= R + 1} k^2 + g(x + k)^2`` along the row (Felzenszwalb and
    Huttenlocher's separable form, on the ring's pixels only)."""
    from scipy import ndimage

    f = _ONE_CELL
    H, W = solid.shape
    whole = _cells(solid, every=True)
    if whole.all():
        return 1.0
    part = _cells(solid)
    if not part.any():
        return 0.0
    c = f * ndimage.distance_transform_edt(whole)
    slack = 3.0 * math.sqrt(2.0) + 1e-3
    r1 = R + 1
    deep = np.empty((H, W), np.float32)
    deep.reshape(H // f, f, W // f, f)[...] = (c - slack >= r1)[:, None, :, None]
    ring = (c - slack < r1) & (c + slack > R) & part
    if not ring.any():
        return deep
    # the ring's box, and every pixel within R + 1 of it
    rows, cols = np.flatnonzero(ring.any(axis=1)), np.flatnonzero(ring.any(axis=0))
    Y0, Y1 = max(0, rows[0] * f - r1), min(H, (rows[-1] + 1) * f + r1)
    X0, X1 = max(0, cols[0] * f - r1), min(W, (cols[-1] + 1) * f + r1)
    free = ~solid[Y0:Y1, X0:X1]
    h, w = free.shape
    kind = np.int16 if h < 2 ** 14 else np.int32
    far = kind(np.iinfo(kind).max // 2)
    ys = np.arange(h, dtype=kind)[:, None]
    above = np.where(free, ys, -far)  # the last free row at or above, per column
    np.maximum.accumulate(above, axis=0, out=above)
    np.subtract(ys, above, out=above)
    below = np.where(free, ys, far)[::-1]  # the first at or below
    np.minimum.accumulate(below, axis=0, out=below)
    below = below[::-1]
    below -= ys
    g = np.full((h, w + 2 * r1), r1, np.float32)  # padded by R + 1 columns (none free)
    np.minimum(np.minimum(above, below), r1, out=g[:, r1:r1 + w], casting="unsafe")
    g = g.ravel()
    flat = deep.reshape(-1)
    dy, dx = np.repeat(np.arange(f), f), np.tile(np.arange(f), f)  # a cell's pixels
    offsets = dy * (w + 2 * r1) + dx
    cells = np.flatnonzero(ring)
    # the ring's pixels as flat indices into g (and deep), a bounded number at a time
    for chunk in np.array_split(cells, -(-cells.size // _RING_CELLS_AT_ONCE)):
        cy, cx = np.divmod(chunk, ring.shape[1])
        at = (((f * cy - Y0) * (w + 2 * r1) + (f * cx - X0) + r1)[:, None] + offsets).ravel()
        d2 = g[at] ** 2
        for k in range(1, r1 + 1):
            gk = np.minimum(g[at - k], g[at + k])
            np.minimum(d2, gk * gk + np.float32(k * k), out=d2)
        out = ((f * cy * W + f * cx)[:, None] + (dy * W + dx)).ravel()
        flat[out] = _depth_ramp(np.sqrt(d2), np.float32(R))
    return deep


#: Cells of :func:`_deep_inside`'s ring computed at once (16 pixels each; about 40
#: bytes per pixel while they are).
_RING_CELLS_AT_ONCE = 1 << 14


def _disjoint_over_last(chain: np.ndarray, last: np.ndarray, g: np.ndarray,
                        same: np.ndarray, deep: np.ndarray) -> None:
    """``chain <- g + k_P P + k_O O`` in place: ``g`` the new slab, ``P = last`` the
    chain's last slab (as laid) and ``O = chain - P`` what the chain held behind it;
    normalisers ``a`` clipped to 1, weights ``same`` and ``deep`` in [0, 1] (2-D, or
    numbers; :meth:`_Chain._weights`).

    - ``same = 0``: Porter and Duff's disjoint over of ``g`` on ``P + O``,
      ``k_P = k_O = min(1, (1 - a_g) / a_{P+O})``: the sum where the two coverages add
      up to at most 1, the nearer ``g`` in front where they overlap;
    - ``same = 1`` (``g`` and ``P`` are one surface): the disjoint over of ``g`` on ``P``,
      then of both on ``O``: ``k_P = min(1, (1 - a_g) / a_P)``, ``k_O = (1 - deep)
      min(1, (1 - a_g - k_P a_P) / min(a_O, 1 - a_P))``. ``O`` fills only what the
      surface leaves (its shortfall where it crosses planes), and nothing deep inside
      it, where the plain disjoint over shrank ``P`` and ``O`` alike and let ``O`` show
      through the surface by up to ``a_O (1 - a_g)``;
    - linear in ``same`` between. ``g = 0`` and ``deep = 0`` leave the chain as it is."""
    one, zero, tiny = np.float32(1.0), np.float32(0.0), np.float32(1e-30)
    free = one - np.minimum(g[..., 3], one)
    a_c = chain[..., 3]
    k_all = free / np.clip(np.maximum(a_c, free), tiny, one)
    if not np.any(same):
        chain *= k_all[..., None]
        chain += g
        return
    # chain <- k_O chain + (k_P - k_O) P + g
    a_l = last[..., 3]
    a_p = np.minimum(a_l, one)
    k_p = free / np.clip(np.maximum(a_p, free), tiny, one)
    free -= k_p * a_p  # what g and P leave for O
    np.maximum(free, zero, out=free)
    room = np.minimum(np.maximum(a_c - a_l, zero), one - a_p)
    k_o = free / np.clip(np.maximum(room, free), tiny, one)
    if np.any(deep):
        k_o *= 1.0 - deep
    k_p -= k_o
    if not np.all(same == 1.0):
        k_p *= same
        k_o -= k_all
        k_o *= same
        k_o += k_all
    chain *= k_o[..., None]
    chain += k_p[..., None] * last
    chain += g


def _normalise(acc: np.ndarray, cmax: np.ndarray) -> np.ndarray:
    """Colour channels (all but channel 3) divided by the normaliser (channel 3) and
    clamped to ``[0, cmax]``; channel 3 becomes the coverage, clipped to [0, 1]."""
    norm = acc[..., 3:4]
    # divide every channel at once (contiguous); where the normaliser is not positive
    # the colour is zero up to the FFT floor, and is divided by 1
    out = acc / np.where(norm > 0.0, norm, np.float32(1.0))
    bound = np.concatenate([cmax[:3], [np.inf], cmax[3:]]).astype(np.float32)
    np.minimum(out, bound, out=out)
    np.maximum(out, 0.0, out=out)
    out[..., 3] = np.clip(acc[..., 3], 0.0, 1.0)
    return out


def render_subapertures(mpi: MPI, blur_parameter: float, focus_disparity: float, k: int,
                        settings: CompositeSettings = CompositeSettings(),
                        progress=None) -> np.ndarray:
    """The middle setting: ``k x k`` equal-area sub-apertures, each composited with Eq. 1
    using its own partial-disk kernels, averaged. ``k = 1`` is plain Eq. 1.

    The average is taken of the parts' premultiplied colour and normaliser before Eq.
    1's division, as the aperture average is; then normalised once. ``progress`` is as in
    :func:`composite`, over all ``k * k`` parts.
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    if k == 1:
        return composite(mpi, blur_parameter, focus_disparity, settings, progress=progress)
    if not blur_parameter > 0 or not math.isfinite(blur_parameter):
        raise ValueError(f"blur parameter A must be finite and > 0, got {blur_parameter}")
    total = np.zeros((mpi.height, mpi.width, mpi.channels), np.float64)
    for i in range(k):
        for j in range(k):
            part_progress = None
            if progress is not None:
                done = i * k + j
                part_progress = lambda f, done=done: progress((done + f) / (k * k))  # noqa: E731
            acc, cmax = _accumulate(mpi, blur_parameter, focus_disparity, settings, (i, j, k),
                                    part_progress)
            total += acc  # premultiplied colour and normaliser: the aperture average
    return _normalise((total / (k * k)).astype(np.float32), cmax)


def timed(fn, *args, **kwargs):
    """``(result, seconds)`` of one call."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0
