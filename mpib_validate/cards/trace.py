"""The paper's image-space thin-lens ray tracer (supplement Eq. 6-15), exact for card scenes.

For a sensor point ``(x, y)`` (pixels from the image centre) and an aperture point
``(mu, nu)`` in the unit disk, the ray meets card ``n`` where its pinhole projection is
(Eq. 15)::

    s   = (1 - a x - b y - c d_f) / (a A mu + b A nu + c)
    x_n = x + s A mu,      y_n = y + s A nu

and the hit's disparity is the plane's own ``d_n = (1 - a x_n - b y_n) / c``. Each ray
sorts its hits by depth (largest disparity first) and composites them front to back
with "over" on premultiplied colour::

    C += T * alpha_n * c_n,      T *= 1 - alpha_n

A pixel is the average of ``C`` over its samples (linear radiance; nothing behind the
last card, i.e. black), and its alpha is the average coverage ``1 - T``.

The canonical pixel model (``docs/camera.md``) is the default: nearest-texel
lookups and samples spread over the pixel area (see :mod:`mpib_validate.runtime.samples`).
The official generator's bilinear lookups at the pixel centre and its fixed
object order are options, for comparison only: the fixed order is wrong wherever
cards interleave in depth.

Two backends run the *same* per-sample code (:func:`_shade`): numpy, and Dr.Jit
(LLVM on the CPU, CUDA on a GPU), which compiles it into one kernel that loops over the
samples per pixel, so memory stays O(pixels) whatever the sample count. All arithmetic
is float32 in the same order in both, with float64 accumulation.

Work is skipped where it is not needed: a card is looked up only where the ray lands
inside its texture, and a ray stops looking up cards once it is opaque.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mpib_validate.runtime.compositor import backend as _backend
from mpib_validate.runtime import samples as _samples
from mpib_validate.cards.scene import Scene

LOOKUPS = ("nearest", "bilinear")
ORDERS = ("depth", "fixed")


@dataclass(frozen=True)
class _Flat:
    """A scene flattened for the kernels; every number pre-rounded to float32."""

    width: int
    height: int
    A: float
    d_f: float
    planes: np.ndarray  # (N, 3) float32: a, b, c
    offset: np.ndarray  # (N, 2) int32: frame pixel of texel (0, 0)
    size: np.ndarray  # (N, 2) int32: W_t, H_t
    base: np.ndarray  # (N,) int32: first texel of each card in `texels`
    texels: np.ndarray  # (T, 4) float32, premultiplied
    fixed_order: tuple  # official order: nearest card (at its centre) first
    depth_groups: tuple  # cards whose disparity ranges overlap; groups nearest first

    @property
    def n(self) -> int:
        return int(self.planes.shape[0])


def _flatten(scene: Scene) -> _Flat:
    cam = scene.camera
    planes, offset, size, base, tex = [], [], [], [], []
    start = 0
    centre_d = []
    for card in scene.cards:
        planes.append((card.plane.a, card.plane.b, card.plane.c))
        x0, x1, y0, y1 = card.extent(cam)
        offset.append(card.offset)
        size.append(card.size)
        base.append(start)
        start += card.size[0] * card.size[1]
        tex.append(card.premultiplied().reshape(-1, 4))
        centre_d.append(float(card.plane.disparity(0.5 * (x0 + x1), 0.5 * (y0 + y1))))
    if start >= 2 ** 31:
        raise ValueError(f"scene textures hold {start} texels; at most 2^31 are supported")
    fixed = tuple(int(i) for i in np.argsort(-np.asarray(centre_d), kind="stable"))
    return _Flat(
        cam.width, cam.height,
        float(np.float32(cam.blur_parameter)), float(np.float32(cam.focus_disparity)),
        np.asarray(planes, np.float32), np.asarray(offset, np.int32),
        np.asarray(size, np.int32), np.asarray(base, np.int32),
        np.ascontiguousarray(np.concatenate(tex), dtype=np.float32), fixed,
        depth_groups(scene))


def depth_groups(scene: Scene) -> tuple:
    """Partition the cards into groups whose disparity ranges overlap, nearest group first.

    Any hit on a card of an earlier group is nearer than any hit on a later group, so a
    ray needs to sort its hits only within a group: all fronto-parallel cards at distinct
    disparities need no per-ray sort at all. Within a group cards keep index order, so
    ties break exactly as in a full stable sort. Touching ranges count as overlapping.
    """
    ranges = [c.disparity_range(scene.camera) for c in scene.cards]
    by_near = sorted(range(len(ranges)), key=lambda i: (-ranges[i][1], i))
    groups, current, low = [], [], None
    for i in by_near:
        lo, hi = ranges[i]
        if current and hi < low:
            groups.append(tuple(sorted(current)))
            current, low = [], None
        current.append(i)
        low = lo if low is None else min(low, lo)
    groups.append(tuple(sorted(current)))
    return tuple(groups)


# --------------------------------------------------------------------------------------
# One per-sample shading routine, written once against a tiny array interface.


class _NumpyOps:
    def const(self, v):
        return np.float32(v)

    def floor(self, v):
        return np.floor(v)

    def select(self, m, a, b):
        return np.where(m, a, b)

    def to_int(self, v):
        return v.astype(np.int32)

    def to_float(self, v):
        return v.astype(np.float32)

    def int_const(self, v):
        return np.int32(v)

    def gather4(self, texels, idx, mask):
        rgba = texels[np.where(mask, idx, 0)]
        zero = np.float32(0)
        return [np.where(mask, rgba[:, k], zero) for k in range(4)]


class _DrjitOps:
    def __init__(self, dr, m):
        self.dr, self.m = dr, m

    def const(self, v):
        return float(np.float32(v))

    def floor(self, v):
        return self.dr.floor(v)

    def select(self, m, a, b):
        return self.dr.select(m, a, b)

    def to_int(self, v):
        return self.m.Int32(v)

    def to_float(self, v):
        return self.m.Float(v)

    def int_const(self, v):
        return int(v)

    def gather4(self, texels, idx, mask):
        v = self.dr.gather(self.m.Array4f, texels, self.m.UInt32(idx), mask)
        return [v.x, v.y, v.z, v.w]


def _card_hit(ops, flat: _Flat, k: int, px, py, x, y, sx, sy, Amu, Anu):
    """Eq. 15 for card k: the ray's displacement (dx, dy), the hit's disparity, and the
    texture coordinate split into an exact integer part and a fraction.

    The texel column is ``(px - ox) + floor(sx + dx)``: the pixel index enters as an
    integer, so for a fronto-parallel card (``dx`` the same for every pixel) each
    sample maps pixels one-to-one onto texels and energy is conserved exactly.
    """
    a, b, c = (ops.const(v) for v in flat.planes[k])
    one = ops.const(1.0)
    num = ((one - a * x) - b * y) - c * ops.const(flat.d_f)
    den = (a * Amu + b * Anu) + c
    t = num / den
    dx = t * Amu
    dy = t * Anu
    d = ((one - a * (x + dx)) - b * (y + dy)) / c
    return d, px - ops.int_const(flat.offset[k, 0]), py - ops.int_const(flat.offset[k, 1]), \
        sx + dx, sy + dy


def _floor_int(ops, v):
    """floor(v) as int32; |v| is clamped to 2^24 first (far outside any texture)."""
    big = ops.const(16777216.0)
    return ops.to_int(ops.floor(ops.select(v > big, big, ops.select(v < -big, -big, v))))


def _inside(ops, flat, k, col, row):
    zero = ops.int_const(0)
    return ((col >= zero) & (col < ops.int_const(flat.size[k, 0]))
            & (row >= zero) & (row < ops.int_const(flat.size[k, 1])))


def _texel_index(ops, flat, k, col, row, ok):
    zero = ops.int_const(0)
    return (ops.int_const(flat.base[k]) + ops.select(ok, row, zero)
            * ops.int_const(flat.size[k, 0]) + ops.select(ok, col, zero))


def _bilinear(ops, flat, k, icol, irow, fu, fv, texels):
    """Bilinear lookup of the premultiplied texture at texel centres; zero outside."""
    half = ops.const(0.5)
    fu, fv = fu - half, fv - half
    fcu, fcv = ops.floor(fu), ops.floor(fv)
    wx, wy = fu - fcu, fv - fcv
    c0 = icol + _floor_int(ops, fcu)
    r0 = irow + _floor_int(ops, fcv)
    zero, one = ops.const(0.0), ops.const(1.0)
    near = _inside(ops, flat, k, c0, r0)
    out = [zero, zero, zero, zero]
    for dc, dr_, wgt in ((0, 0, (one - wx) * (one - wy)), (1, 0, wx * (one - wy)),
                         (0, 1, (one - wx) * wy), (1, 1, wx * wy)):
        cc, rr = c0 + ops.int_const(dc), r0 + ops.int_const(dr_)
        ok = _inside(ops, flat, k, cc, rr)
        near = near | ok
        tap = ops.gather4(texels, _texel_index(ops, flat, k, cc, rr, ok), ok)
        out = [o + wgt * t for o, t in zip(out, tap)]
    return near, out


def _rank_by_depth(ops, hits, lookup):
    """Selection sort of one group's hits by disparity, nearest first, per lane.

    Ties go to the lower card index, like a stable sort. ``hits`` holds
    ``(valid, disparity, payload)`` per card; returns them ranked.
    """
    if len(hits) == 1:
        return hits
    zero = ops.const(0.0)
    n = len(hits)
    ranked = []
    used = [None] * n
    for _ in range(n):
        for k, (valid, d, payload) in enumerate(hits):
            cand = valid if used[k] is None else valid & ~used[k]
            if k == 0:
                best_valid, best_d, best_p, onehot = cand, ops.select(cand, d, zero), payload, [cand]
                continue
            take = cand & (~best_valid | (d > best_d))
            best_valid = best_valid | cand
            best_d = ops.select(take, d, best_d)
            best_p = (ops.select(take, payload, best_p) if lookup == "nearest"
                      else [ops.select(take, p, q) for p, q in zip(payload, best_p)])
            onehot = [o & ~take for o in onehot] + [take]
        used = [o if u is None else u | o for u, o in zip(used, onehot)]
        ranked.append((best_valid, best_d, best_p))
    return ranked


def _shade(ops, flat: _Flat, texels, px, py, sx, sy, Amu, Anu, lookup: str, order: str):
    """Radiance and coverage of one sample per lane: returns (R, G, B, 1 - T).

    ``px, py`` are int32 pixel indices, ``sx, sy`` the sub-pixel position in [0, 1),
    ``Amu, Anu`` the aperture point scaled by A (pixels per unit disparity).
    """
    zero, one = ops.const(0.0), ops.const(1.0)
    x = (ops.to_float(px) - ops.const(0.5 * flat.width)) + sx
    y = (ops.to_float(py) - ops.const(0.5 * flat.height)) + sy
    n = flat.n
    hits = []  # per card: (valid, disparity, payload)
    for k in range(n):
        d, icol, irow, fu, fv = _card_hit(ops, flat, k, px, py, x, y, sx, sy, Amu, Anu)
        if lookup == "nearest":
            col = icol + _floor_int(ops, fu)
            row = irow + _floor_int(ops, fv)
            inside = _inside(ops, flat, k, col, row)
            hits.append((inside, d, _texel_index(ops, flat, k, col, row, inside)))
        else:
            near, rgba = _bilinear(ops, flat, k, icol, irow, fu, fv, texels)
            hits.append((near, d, rgba))

    if order == "fixed":
        ranked = [hits[k] for k in flat.fixed_order]
    else:
        ranked = []
        for group in flat.depth_groups:
            ranked += _rank_by_depth(ops, [hits[k] for k in group], lookup)

    T = one + zero * x  # lane-shaped ones
    C = [zero, zero, zero]
    for valid, _d, payload in ranked:
        if lookup == "nearest":
            active = valid & (T > zero)  # stop a ray once it is opaque
            r, g, b, a = ops.gather4(texels, payload, active)
        else:
            r, g, b, a = (ops.select(valid, p, zero) for p in payload)
        C = [C[0] + T * r, C[1] + T * g, C[2] + T * b]
        T = T * (one - a)
    return C[0], C[1], C[2], one - T


# --------------------------------------------------------------------------------------
# Backends


def _trace_numpy(flat: _Flat, smp: _samples.LensSamples, lookup, order, progress,
                 tile_pixels: int = 1 << 18) -> np.ndarray:
    ops = _NumpyOps()
    W, H = flat.width, flat.height
    out = np.zeros((H * W, 4), np.float64)
    f = np.float32
    A = f(flat.A)
    mu, nu = smp.mu.astype(f), smp.nu.astype(f)
    sx, sy = smp.sx.astype(f), smp.sy.astype(f)
    rows_per_tile = max(1, tile_pixels // W)
    tiles = [(r, min(H, r + rows_per_tile)) for r in range(0, H, rows_per_tile)]
    bar = _progress(progress, len(tiles) * len(smp), "trace numpy")
    for r0, r1 in tiles:
        px = np.tile(np.arange(W, dtype=np.int32), r1 - r0)
        py = np.repeat(np.arange(r0, r1, dtype=np.int32), W)
        acc = np.zeros((px.size, 4), np.float64)
        for s in range(len(smp)):
            rgbc = _shade(ops, flat, flat.texels, px, py, sx[s], sy[s], A * mu[s], A * nu[s],
                          lookup, order)
            for c in range(4):
                acc[:, c] += rgbc[c]
            if bar is not None:
                bar.update(1)
        out[r0 * W:r1 * W] = acc
    if bar is not None:
        bar.close()
    return (out / len(smp)).astype(np.float32).reshape(H, W, 4)


def _trace_drjit(flat: _Flat, smp: _samples.LensSamples, lookup, order, progress,
                 device: str, chunk: int = 256) -> np.ndarray:
    dr = _backend.import_drjit()
    if device == "cuda":
        import drjit.cuda as m
    else:
        import drjit.llvm as m
    ops = _DrjitOps(dr, m)
    W, H = flat.width, flat.height
    P = W * H
    texels = m.Float(flat.texels.ravel())
    A = ops.const(flat.A)
    idx = dr.arange(m.Int32, P)
    px = idx % W
    py = idx // W
    acc = [dr.zeros(m.Float64, P) for _ in range(4)]
    bar = _progress(progress, len(smp), f"trace drjit-{device}")
    for part in smp.chunks(chunk):
        mu, nu = m.Float(part.mu.astype(np.float32)), m.Float(part.nu.astype(np.float32))
        sx, sy = m.Float(part.sx.astype(np.float32)), m.Float(part.sy.astype(np.float32))
        n = dr.opaque(m.UInt32, len(part))

        def cond(s, *_):
            return s < n

        def body(s, r, g, b, c):
            Amu = A * dr.gather(m.Float, mu, s)
            Anu = A * dr.gather(m.Float, nu, s)
            rgbc = _shade(ops, flat, texels, px, py, dr.gather(m.Float, sx, s),
                          dr.gather(m.Float, sy, s), Amu, Anu, lookup, order)
            return (s + 1, r + m.Float64(rgbc[0]), g + m.Float64(rgbc[1]),
                    b + m.Float64(rgbc[2]), c + m.Float64(rgbc[3]))

        state = dr.while_loop((dr.zeros(m.UInt32, P), *acc), cond, body)
        acc = list(state[1:])
        dr.eval(*acc)
        if bar is not None:
            bar.update(len(part))
    if bar is not None:
        bar.close()
    out = np.stack([a.numpy() for a in acc], axis=-1) / len(smp)
    return out.astype(np.float32).reshape(H, W, 4)


def _progress(enabled: bool, total: int, desc: str):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit="spl", leave=False, disable=None)


# --------------------------------------------------------------------------------------
# Public API


@dataclass
class TraceResult:
    """Outputs of :func:`render`.

    Attributes:
        bokeh: ``(H, W, 4)`` float32: radiance averaged over pixel and aperture
            (premultiplied; black where no card), alpha = coverage.
        all_in_focus: same with a pinhole (``A = 0``), pixel box averaged.
        disparity: ``(H, W)`` float32, disparity (1/scene-unit) of the front-most card
            with alpha >= 0.5 at the pixel centre; 0 where there is none.
        depth: ``1/disparity`` (scene units), 1e10 where there is no card (as Cycles).
        layer: ``(H, W)`` int32 index of that card, -1 where there is none.
        card_alpha: ``(N, H, W)`` float32 alpha of each card at the pixel centre
            (pinhole, occluded or not): the per-pixel hit layers.
        card_disparity: ``(N, H, W)`` float32 disparity of each card's plane there.
        meta: settings, backend and timings.
    """

    bokeh: np.ndarray
    all_in_focus: np.ndarray
    disparity: np.ndarray
    depth: np.ndarray
    layer: np.ndarray
    card_alpha: np.ndarray
    card_disparity: np.ndarray
    meta: dict = field(default_factory=dict)


def trace(scene: Scene, samples: _samples.LensSamples | None = None, *, backend: str = "auto",
          lookup: str = "nearest", order: str = "depth", progress: bool = False,
          notices: bool = True) -> tuple[np.ndarray, dict]:
    """Render the defocused image of ``scene`` (Eq. 15, front-to-back "over").

    Args:
        samples: joint aperture/pixel samples of the camera's aperture (refused
            otherwise); default a 1,024-point scrambled Sobol set with pixel box
            averaging over ``scene.camera.aperture``.
        backend: ``auto`` (CUDA, then LLVM, then numpy), ``numpy``, ``llvm`` or ``cuda``.
        lookup: ``nearest`` (canonical) or ``bilinear`` (the official generator).
        order: ``depth`` (per-ray sort) or ``fixed`` (the official order; wrong where
            cards interleave in depth).

    Returns:
        ``(image, meta)``: ``(H, W, 4)`` float32 premultiplied radiance + coverage,
        and a dict with the backend that ran, the sample set and the time in seconds.
    """
    if lookup not in LOOKUPS:
        raise ValueError(f"lookup must be one of {LOOKUPS}, got {lookup!r}")
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    scene.validate()
    aperture = scene.camera.aperture
    smp = samples if samples is not None else _samples.stratified(1024, aperture=aperture)
    if not smp.covers(aperture):
        raise ValueError(f"the samples ({smp.kind}) are not of the camera's aperture "
                         f"({aperture.describe()}): make them with "
                         f"samples.stratified(n, aperture=camera.aperture)")
    be = _backend.resolve(backend)
    if notices:
        _backend.notify(be)
    flat = _flatten(scene)
    t0 = time.perf_counter()
    if be.name == "numpy":
        img = _trace_numpy(flat, smp, lookup, order, progress)
    else:
        img = _trace_drjit(flat, smp, lookup, order, progress, be.name)
    seconds = time.perf_counter() - t0
    meta = {"engine": "trace", "backend": be.name, "backend_notice": be.notice,
            "samples": smp.kind, "sample_count": len(smp), "lookup": lookup,
            "order": order, "seconds": seconds}
    return img, meta


def pinhole_maps(scene: Scene) -> dict:
    """Per-pixel maps at pixel centres with a pinhole: ``disparity``, ``depth``, ``layer``,
    ``card_alpha``, ``card_disparity`` (see :class:`TraceResult`) and ``card_rgb``
    (each card's straight colour there)."""
    cam = scene.camera
    xs, ys = cam.pixel_centres()
    x, y = np.meshgrid(xs, ys)
    n = len(scene.cards)
    alpha = np.zeros((n, cam.height, cam.width), np.float32)
    rgb = np.zeros((n, cam.height, cam.width, 3), np.float32)
    disp = np.zeros((n, cam.height, cam.width), np.float32)
    for k, card in enumerate(scene.cards):
        x0, _, y0, _ = card.extent(cam)
        col = np.floor(x - x0).astype(np.int64)
        row = np.floor(y - y0).astype(np.int64)
        w, h = card.size
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        alpha[k][ok] = card.rgba[row[ok], col[ok], 3]
        rgb[k][ok] = card.rgba[row[ok], col[ok], :3]
        disp[k] = card.plane.disparity(x, y)
    # front-most card with alpha >= 0.5 (Cycles' pass_alpha_threshold)
    solid = alpha >= 0.5
    key = np.where(solid, disp, -np.inf)
    layer = np.argmax(key, axis=0).astype(np.int32)
    has = solid.any(axis=0)
    layer[~has] = -1
    d = np.where(has, np.take_along_axis(disp, np.maximum(layer, 0)[None], 0)[0], 0.0)
    depth = np.where(has, 1.0 / np.where(has, d, 1.0), 1e10)
    return {"disparity": d.astype(np.float32), "depth": depth.astype(np.float32),
            "layer": layer, "card_alpha": alpha, "card_disparity": disp, "card_rgb": rgb}


def render(scene: Scene, samples: _samples.LensSamples | None = None, *, backend: str = "auto",
           lookup: str = "nearest", order: str = "depth", progress: bool = False,
           notices: bool = True) -> TraceResult:
    """:func:`trace` plus the all-in-focus image and the per-pixel maps."""
    bokeh, meta = trace(scene, samples, backend=backend, lookup=lookup, order=order,
                        progress=progress, notices=notices)
    # Pinhole samples (mu = nu = 0) see every card at its projection: the all-in-focus view.
    aif, _ = trace(scene, _samples.pinhole(4), backend=meta["backend"], lookup=lookup,
                   order=order, notices=False)
    maps = pinhole_maps(scene)
    return TraceResult(bokeh, aif, maps["disparity"], maps["depth"], maps["layer"],
                       maps["card_alpha"], maps["card_disparity"], meta)
