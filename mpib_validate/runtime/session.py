"""Refocus one picture many times: the MPI is built once, a new focus only re-composites.

What the MPI of rendered passes depends on (:func:`mpib_validate.runtime.layers.passes.layers_from_passes`):
the colour and depth, the preset's settings and the blur parameter ``A`` (pixels per
unit disparity), through the plane spacing ``2 tol / A``, the edge threshold
``jump_px / A``, the occlusion reach ``A (d_near - d_far)`` of the fill and the slab span
``slab_px / A``. It does **not** depend on the focus ``d_f``: the blur radius
``r = A |d_i - d_f|`` of each plane enters only in the compositor (Eq. 1). So:

- **New focus, same ``A``**: only Eq. 1 runs again, on the cached MPI. The result is
  the one :func:`mpib_validate.runtime.refocus.refocus` gives (the same function on the same
  layers: equal to the last bit).
- **New f-stop, ``A <= A_b``** (the ``A`` the cached MPI was built for) and
  ``A >= A_b * REUSE_DOWN_TO``: the cached MPI is reused. Its guarantees at ``A`` are
  those of the preset or better: the radius quantisation error of its plane spacing is
  ``tol * A / A_b <= tol`` px, its fill reaches ``A_b (d_near - d_far) >= A (d_near -
  d_far)`` px behind each edge (at least the shift the aperture can give), edge pixels
  whose blur radii differ by more than ``jump_px * A / A_b`` px (instead of ``jump_px``)
  are unmixed, and content within ``slab_px * A / A_b`` px of blur radius is summed as
  one slab. It is not bit-identical to a fresh build at ``A`` (the choices inside those
  bounds differ); ``mpib bench --suite refocus`` measures the difference.
- **Wider aperture (``A > A_b``), or much narrower**: the MPI is rebuilt for ``A``
  (``exact_aperture=True``: for any change of ``A``).

Preview (``scale = 1/s``, ``s`` an integer, 0.25 for a quarter of the resolution per
axis): the cached MPI area-averaged by ``s x s`` (:func:`downsample_mpi`, premultiplied
colour and alpha, so a layer's coverage and energy are kept) and composited with
``A / s``: the blur radius in the coarse pixels is ``A |d - d_f| / s``. The coarse MPI is
cached too (``1/s^2`` of the full one's memory). Before any MPI is built (the first
pull after a render), :meth:`RefocusSession.quick_preview` builds a small one from the
passes subsampled ``s x s`` instead, at ``1/s^2`` of the build's cost.

Memory: the session keeps the passes (the caller's), one MPI (``16 B`` per stored layer
pixel and channel group of four float32, see :attr:`RefocusSession.cache_bytes`;
:func:`mpib_validate.runtime.budget.refocus_estimate` estimates it before the build as its
``layers`` part) and its previews. An MPI larger than ``max_cache_bytes`` is not kept:
each render then rebuilds it (as :func:`refocus` does), and ``info["mpi"]`` says so.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
from dataclasses import dataclass

import numpy as np

from mpib_validate.runtime.layers.mpi import MPI, Layer
from mpib_validate.runtime.layers.passes import DEFAULT_FAR_LIMIT
from mpib_validate.runtime.layers.cache import passes_digest
from mpib_validate.runtime.refocus import (BuiltMPI, Passes, RefocusResult, build_mpi,
                                           render_built, result_info, split_progress)
from mpib_validate.runtime.request import RefocusRequest

#: A cached MPI built for ``A_b`` is reused down to ``A = REUSE_DOWN_TO * A_b``; below
#: that it holds more than twice the planes the narrower aperture needs (slower to
#: composite than a rebuild is worth once the artist stays there).
REUSE_DOWN_TO = 0.5

#: Default bound on the memory one session keeps (the MPI and its previews).
DEFAULT_MAX_CACHE_BYTES = 2 << 30


def preview_factor(scale: float) -> int:
    """The integer ``s`` with ``scale = 1/s`` (1 for full resolution); ValueError naming
    ``scale`` otherwise."""
    if not (scale > 0) or not math.isfinite(scale) or scale > 1:
        raise ValueError(f"scale must be 1/s for a whole number s >= 1 (1, 0.5, 0.25, ...), "
                         f"got {scale}")
    s = int(round(1.0 / scale))
    if abs(s * scale - 1.0) > 1e-6:
        raise ValueError(f"scale must be 1/s for a whole number s >= 1 (1, 0.5, 0.25, ...), "
                         f"got {scale}")
    return s


def _downsample_layer(layer: Layer, s: int, canvas: tuple[int, int]) -> Layer:
    """Area average of a layer over ``s x s`` blocks of the canvas; a block cut by the
    canvas edge averages the canvas pixels it holds (what replication padding gives)."""
    hc, wc = canvas
    y0, y1, x0, x1 = layer.box
    Y0, X0, Y1, X1 = y0 // s, x0 // s, -(-y1 // s), -(-x1 // s)
    C = layer.rgba.shape[2]
    buf = np.zeros(((Y1 - Y0) * s, (X1 - X0) * s, C), np.float32)
    buf[y0 - Y0 * s:y1 - Y0 * s, x0 - X0 * s:x1 - X0 * s] = layer.rgba
    sums = buf.reshape(Y1 - Y0, s, X1 - X0, s, C).sum(axis=3).sum(axis=1)
    rows = np.arange(Y0, Y1)
    cols = np.arange(X0, X1)
    ny = np.minimum((rows + 1) * s, hc) - rows * s
    nx = np.minimum((cols + 1) * s, wc) - cols * s
    avg = sums / (ny[:, None] * nx[None, :]).astype(np.float32)[..., None]
    return Layer(layer.disparity, np.ascontiguousarray(avg, np.float32), Y0, X0, layer.group)


def downsample_mpi(mpi: MPI, s: int) -> MPI:
    """The MPI at ``1/s`` resolution per axis: every layer area-averaged over ``s x s``
    blocks (premultiplied colour and alpha: block coverage and energy are kept; a
    weighted average of straight colours stays below :attr:`MPI.colour_max`, which is
    carried over). Frame ``ceil(H/s) x ceil(W/s)``; the margin must be a multiple of
    ``s`` (pictures have none) so that the frame stays on the block grid."""
    if s < 1:
        raise ValueError(f"the factor must be >= 1, got {s}")
    if s == 1:
        return mpi
    if mpi.margin % s:
        raise ValueError(f"the MPI's margin ({mpi.margin} px) is not a multiple of {s}")
    out = MPI(-(-mpi.height // s), -(-mpi.width // s), mpi.margin // s,
              colour_max=mpi.colour_max)
    out.layers = [_downsample_layer(l, s, mpi.canvas_shape) for l in mpi.layers]
    return out


def take_passes(passes: Passes, rows, cols) -> Passes:
    """The passes at the pixels ``rows x cols`` (index arrays into the frame, in order;
    repeats allowed): colour, depth, film alpha, disparity and every depth group alike."""
    from dataclasses import replace

    rows, cols = np.asarray(rows), np.asarray(cols)

    def pick(a):
        return None if a is None else np.ascontiguousarray(a[rows][:, cols])

    groups = None
    if passes.groups is not None:
        groups = [tuple(pick(a) for a in g) for g in passes.groups]
    return replace(passes, colour=pick(passes.colour), depth=pick(passes.depth),
                   alpha=pick(passes.alpha), groups=groups, notices=[],
                   disparity=pick(passes.disparity))


def subsample_passes(passes: Passes, s: int) -> Passes:
    """The passes at ``1/s`` resolution: the pixel at the centre of each ``s x s`` block
    (colour, depth and film alpha of one pixel each: averaging depth across an edge would
    invent surfaces in between), the frame first continued by edge replication to a
    multiple of ``s``, so the result is ``ceil(H/s) x ceil(W/s)`` as :func:`downsample_mpi`
    gives."""
    H, W = passes.depth.shape
    Hs, Ws = -(-H // s), -(-W // s)
    rows = np.minimum(np.arange(Hs) * s + s // 2, H - 1)
    cols = np.minimum(np.arange(Ws) * s + s // 2, W - 1)
    return take_passes(passes, rows, cols)


@dataclass(frozen=True)
class FrameFit:
    """How a render's pixels map onto the image the refocus works on, and back.

    ``region``: ``(x0, y0, x1, y1)``, the box of the frame that holds the render (an
    uncropped render region: nothing was rendered outside it), or None for the whole
    frame. ``stretch``: ``(mx, my)``, each column repeated ``mx`` times and each row
    ``my`` times so that non-square pixels (Blender's Pixel Aspect X:Y = mx:my) become
    square; the refocused image is averaged back over each ``mx x my`` block (the blur is
    linear, so this is the render's pixels blurred by the stretched, anisotropic
    kernel). ``linear_far``: an orthographic camera's ``far`` (its clip end): the
    refocus's disparity is then ``far - Z``, linear in depth (0 at ``far`` and beyond,
    and where nothing was rendered), as
    :func:`mpib_validate.runtime.camera.blender_orthographic_camera` blurs it."""

    region: tuple | None = None
    stretch: tuple = (1, 1)
    linear_far: float | None = None

    @property
    def identity(self) -> bool:
        return self.region is None and tuple(self.stretch) == (1, 1) and self.linear_far is None

    def passes(self, passes: Passes) -> Passes:
        """The passes the refocus works on: the region, the square pixels, and the linear
        depth of an orthographic camera."""
        from dataclasses import replace

        if self.identity:
            return passes
        H, W = passes.depth.shape
        x0, y0, x1, y1 = self.region or (0, 0, W, H)
        mx, my = self.stretch
        out = take_passes(passes, np.repeat(np.arange(y0, y1), my),
                          np.repeat(np.arange(x0, x1), mx))
        if self.linear_far is not None:
            z = np.asarray(out.depth, np.float64)
            far = float(self.linear_far)
            d = np.where(np.isfinite(z) & (z < far), far - z, 0.0)
            out = replace(out, disparity=np.maximum(d, 0.0))
        return out

    def pixel(self, x: int, y: int, shape) -> tuple[int, int]:
        """A pixel of the render (from the top left) on the refocus's image; raises
        ``ValueError`` naming the region when it lies outside it."""
        H, W = shape
        x0, y0, x1, y1 = self.region or (0, 0, W, H)
        if not (x0 <= x < x1 and y0 <= y < y1):
            raise ValueError(f"the focus pixel ({x}, {y}) lies outside the render region "
                             f"(columns {x0}-{x1 - 1}, rows {y0}-{y1 - 1})")
        mx, my = self.stretch
        return (x - x0) * mx + mx // 2, (y - y0) * my + my // 2

    def image(self, rgba: np.ndarray, shape) -> np.ndarray:
        """The refocused ``(h, w, 4)`` straight RGBA back on the render's ``shape`` ``(H,
        W)``: each ``mx x my`` block averaged (premultiplied), placed in the region; 0
        (transparent) outside it, as the render is there."""
        if self.identity:
            return rgba
        mx, my = self.stretch
        img = np.asarray(rgba, np.float32)
        if (mx, my) != (1, 1):
            h, w = img.shape[0] // my, img.shape[1] // mx
            pre = np.concatenate([img[..., :3] * img[..., 3:4], img[..., 3:4]], axis=-1)
            pre = pre.reshape(h, my, w, mx, 4).mean(axis=(1, 3))
            img = np.zeros_like(pre)
            a = pre[..., 3:4]
            np.divide(pre[..., :3], a, out=img[..., :3], where=a > 0)
            img[..., 3:4] = a
        if self.region is None:
            return img
        x0, y0, x1, y1 = self.region
        out = np.zeros((*shape, 4), np.float32)
        out[y0:y1, x0:x1] = img
        return out


def file_stamps(paths) -> tuple:
    """``(path, mtime_ns, size)`` of each existing input file: a change to any of them
    invalidates a session built from them (:meth:`RefocusSession.is_current`)."""
    out = []
    for p in paths:
        if p is None:
            continue
        st = os.stat(p)
        out.append((os.path.abspath(p), st.st_mtime_ns, st.st_size))
    return tuple(out)


def mpi_bytes(mpi: MPI | None) -> int:
    """Bytes the layers of an MPI hold."""
    return 0 if mpi is None else int(sum(l.nbytes for l in mpi.layers))


class RefocusSession:
    """One picture's passes with their MPI kept between renders (see the module
    docstring for what is reused and with which error bound): the memory cache of
    :func:`mpib_validate.runtime.refocus.refocus` (``refocus(request, cache=session)``
    for a request of this session's :meth:`request`), with previews.

    Args:
        passes: from :func:`mpib_validate.runtime.refocus.load_passes` (or the layered loader).
        preset, far_limit, background, refine: as for
            :class:`~mpib_validate.runtime.request.RefocusRequest` (the preset a
            :class:`~mpib_validate.runtime.presets.Preset` or its name, looked up once here).
        stamps: the input files' :func:`file_stamps`, so that :meth:`is_current` can
            tell when they changed (:meth:`from_files` fills it in).
        exact_aperture: rebuild the MPI whenever ``A`` changes (every result then
            equals :func:`refocus` to the last bit).
        max_cache_bytes: the most memory the kept MPI and its previews may hold.
    """

    def __init__(self, passes: Passes, preset="default",
                 far_limit: float = DEFAULT_FAR_LIMIT, background=None, stamps: tuple = (),
                 exact_aperture: bool = False,
                 max_cache_bytes: int = DEFAULT_MAX_CACHE_BYTES, refine: str | None = None):
        # the request this session serves, at a placeholder lens (A = 1, d_f = 0):
        # every render gives its own (:meth:`request`)
        self._template = RefocusRequest(passes, 1.0, 0.0, preset, far_limit, background,
                                        refine)
        self.stamps = tuple(stamps)
        self.exact_aperture = exact_aperture
        self.max_cache_bytes = int(max_cache_bytes)
        self._built: BuiltMPI | None = None
        self._previews: dict[int, BuiltMPI] = {}
        self._lock = threading.Lock()
        self.builds = 0  # MPI builds this session has run

    @property
    def passes(self) -> Passes:
        return self._template.passes

    @property
    def preset(self):
        """The resolved :class:`~mpib_validate.runtime.presets.Preset`."""
        return self._template.preset

    @property
    def far_limit(self) -> float:
        return self._template.far_limit

    def request(self, focus_disparity: float, blur_parameter: float,
                aperture=None) -> RefocusRequest:
        """The request of a render of this session's picture at ``d_f`` and ``A``, with
        the lens's ``aperture`` (None: a disk)."""
        request = self._template.with_lens(blur_parameter, focus_disparity)
        return request if aperture is None else dataclasses.replace(request, aperture=aperture)

    @classmethod
    def from_files(cls, path, depth_path=None, view_layer=None, **kwargs) -> "RefocusSession":
        """Load the passes (:func:`mpib_validate.runtime.refocus.load_passes`) and remember the
        files' stamps."""
        from mpib_validate.runtime.refocus import load_passes

        stamps = file_stamps([path, depth_path])
        return cls(load_passes(path, depth_path, view_layer=view_layer), stamps=stamps,
                   **kwargs)

    def is_current(self) -> bool:
        """False when an input file this session was built from changed (its
        modification time or size) or is gone."""
        try:
            return file_stamps([p for p, _, _ in self.stamps]) == self.stamps
        except OSError:
            return False

    @property
    def cache_bytes(self) -> int:
        """Memory the kept MPI and its previews hold now (bytes)."""
        built = [self._built] + list(self._previews.values())
        return sum(mpi_bytes(b.mpi) for b in built if b is not None)

    @property
    def built_for(self) -> float | None:
        """The ``A`` the kept MPI was built for (None: none kept)."""
        return None if self._built is None else self._built.blur_parameter

    def drop(self) -> None:
        """Forget the kept MPI and previews (e.g. a new render arrived)."""
        with self._lock:
            self._built = None
            self._previews.clear()

    def serves(self, blur_parameter: float) -> bool:
        """True when the kept MPI serves ``A`` (a render needs no build)."""
        with self._lock:
            return self._reusable(blur_parameter)

    def _reusable(self, A: float) -> bool:
        b = self._built
        if b is None:
            return False
        if self.exact_aperture:
            return A == b.blur_parameter
        return b.blur_parameter * REUSE_DOWN_TO <= A <= b.blur_parameter * (1 + 1e-12)

    def mpi_for(self, blur_parameter: float, progress=None) -> tuple[BuiltMPI, str]:
        """The MPI to render ``A`` with: the kept one if it serves (see the module
        docstring), else a new build (kept if it fits ``max_cache_bytes``). Returns it
        and how it was had: ``cached``, ``built`` or ``built, not kept (...)``."""
        with self._lock:
            if self._reusable(blur_parameter):
                return self._built, "cached"
            built = build_mpi(self._template.with_lens(blur_parameter), progress)
            self.builds += 1
            self._built = None
            self._previews.clear()
            size = mpi_bytes(built.mpi)
            if size > self.max_cache_bytes:
                return built, (f"built, not kept ({size / 2**30:.2f} GiB > the session's "
                               f"{self.max_cache_bytes / 2**30:.2f} GiB)")
            self._built = built
            return built, "built"

    def _owns(self, request: RefocusRequest) -> bool:
        t = self._template
        return (request.passes is t.passes and request.preset == t.preset
                and request.far_limit == t.far_limit and request.background is t.background)

    def fetch(self, request: RefocusRequest, progress=None):
        """The cache protocol of :func:`mpib_validate.runtime.refocus.refocus`:
        ``(built, {"mpi": how})`` for a request of this session (:meth:`request`)."""
        if not self._owns(request):
            raise ValueError("the request is not this session's (other passes, preset, far "
                             "limit or background): make it with RefocusSession.request")
        built, how = self.mpi_for(request.build_blur_parameter, progress)
        return built, {"mpi": how}

    def _preview(self, built: BuiltMPI, s: int) -> BuiltMPI:
        if s == 1:
            return built
        with self._lock:
            kept = self._built is built
            p = self._previews.get(s) if kept else None
            if p is None:
                p = BuiltMPI(downsample_mpi(built.mpi, s), built.opaque, built.disparity,
                             built.info, built.blur_parameter, built.pixel_model)
                if kept and self.cache_bytes + mpi_bytes(p.mpi) <= self.max_cache_bytes:
                    self._previews[s] = p
            return p

    def render(self, focus_disparity: float, blur_parameter: float, scale: float = 1.0,
               progress=None, aperture=None) -> RefocusResult:
        """Refocus at ``d_f`` (1/scene-unit) with ``A`` (px per unit disparity, at full
        resolution), at ``scale`` (1, or ``1/s``: an ``ceil(H/s) x ceil(W/s)`` preview).

        ``info`` as :func:`refocus` gives, plus ``mpi`` (cached / built),
        ``mpi_blur_parameter`` (``A_b``), ``scale``, ``composite_seconds`` and
        ``cache_bytes``. ``progress(fraction)`` may raise to cancel, as for
        :func:`refocus`. ``aperture``: the lens's shape (None: a disk); the MPI is built
        for its reach (``RefocusRequest.build_blur_parameter``)."""
        request = self.request(focus_disparity, blur_parameter, aperture)
        s = preview_factor(scale)
        t0 = time.perf_counter()
        first, second = split_progress(progress)
        built, how = self.mpi_for(request.build_blur_parameter, first)
        target = self._preview(built, s)
        t1 = time.perf_counter()
        img = render_built(target, request, second, scale=s)
        t2 = time.perf_counter()
        info = result_info(request, built, t2 - t0)
        info.update({"mpi": how, "mpi_blur_parameter": built.blur_parameter, "scale": 1.0 / s,
                     "composite_seconds": t2 - t1, "cache_bytes": self.cache_bytes})
        return RefocusResult(img, info)

    def quick_preview(self, focus_disparity: float, blur_parameter: float, scale: float,
                      progress=None, aperture=None) -> RefocusResult:
        """A ``1/s`` preview before the MPI exists (the first focus pull after a render):
        an MPI built from the passes subsampled at the centre of each ``s x s`` block
        (:func:`subsample_passes`) for ``A / s``, about ``1/s^2`` of the full build's
        cost; not kept. It shows the same focus as :meth:`render` at ``scale`` but from
        coarser layers (edges placed to the block, thin structures may drop out); later
        previews come from the kept MPI. ``aperture`` as for :meth:`render`."""
        request = self.request(focus_disparity, blur_parameter, aperture)
        s = preview_factor(scale)
        t0 = time.perf_counter()
        small = dataclasses.replace(request, passes=subsample_passes(self.passes, s),
                                    background=None)
        first, second = split_progress(progress)
        built = build_mpi(small.with_lens(blur_parameter / s), first)
        img = render_built(built, small, second, scale=s)
        info = result_info(small, built, time.perf_counter() - t0)
        info.update({"mpi": "quick (subsampled passes)", "mpi_blur_parameter": blur_parameter,
                     "scale": 1.0 / s, "composite_seconds": time.perf_counter() - t0,
                     "cache_bytes": self.cache_bytes})
        return RefocusResult(img, info)

    def focus_at_pixel(self, x: int, y: int) -> float:
        """Disparity to focus on pixel ``(x, y)`` (full-resolution, from the top left)."""
        from mpib_validate.runtime.refocus import focus_from_pixel

        return focus_from_pixel(self.passes, x, y, self.far_limit)


__all__ = ["RefocusSession", "downsample_mpi", "subsample_passes", "take_passes", "FrameFit",
           "passes_digest",
           "file_stamps", "mpi_bytes", "preview_factor", "REUSE_DOWN_TO"]
