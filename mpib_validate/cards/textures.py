"""Content for random "card" scenes: background textures, foreground alpha masks, HDR spots.

In the style of the MPIB synthetic generator a scene is a background image plus a few
fronto-parallel foreground objects, each an RGB texture with a straight alpha mask.
This module makes that content, offline and deterministically:

- real photographs come only from the images that scikit-image ships inside its wheel
  (``SHIPPED_IMAGES``; no pooch download is ever attempted);
- procedural textures (``PROCEDURAL_TEXTURES``) and masks (``MASK_KINDS``) are computed.

Conventions (see also the package docstring):

- every random choice is drawn from the ``rng: np.random.Generator`` argument only, so
  the same generator state gives byte-identical output;
- images are ``(H, W, 3)`` and masks ``(H, W)``, ``float32``, C-contiguous;
- colours are linear radiance; 8-bit sRGB data is decoded with the exact sRGB EOTF
  (:func:`srgb_to_linear`); LDR textures lie in ``[0, 1]``, :func:`hdr_highlights` adds
  values far above 1;
- alpha is straight (not premultiplied), in ``[0, 1]``;
- continuous pixel coordinates: pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)`` with its
  centre at ``(y, x) = (i + 0.5, j + 0.5)``; lengths are in pixels.

Hard edges are anti-aliased by supersampling: the indicator of the shape is evaluated on
an ``s x s`` grid of sub-pixel centres per pixel (``s = 4``) and averaged, so an edge
pixel's alpha is its covered area fraction quantised to ``1/s^2``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np
from scipy import ndimage
from skimage import data as skdata
from skimage import measure
from skimage.transform import resize

from mpib_validate.runtime.io.colour import srgb_to_linear  # the exact sRGB EOTF, one definition

__all__ = [
    "SHIPPED_IMAGES",
    "PROCEDURAL_TEXTURES",
    "MASK_KINDS",
    "srgb_to_linear",
    "shipped_image",
    "procedural_texture",
    "random_texture",
    "alpha_mask",
    "hdr_highlights",
]

#: scikit-image sample images whose files are inside the wheel (load with no network).
#: Left out although they load offline: ``cat`` (same picture as ``chelsea``), ``horse``
#: (a binary silhouette, used as a mask), ``logo`` (RGBA), ``microaneurysms`` (102 px),
#: ``checkerboard`` and ``shepp_logan_phantom`` (synthetic). ``eagle``, ``lily``, ``skin``,
#: ``brain``, ``kidney``, ... need pooch + a download and are not usable.
SHIPPED_IMAGES: tuple[str, ...] = (
    "astronaut", "brick", "camera", "cell", "chelsea", "clock", "coffee", "coins",
    "colorwheel", "grass", "gravel", "hubble_deep_field", "immunohistochemistry", "moon",
    "page", "retina", "rocket", "text",
)
PROCEDURAL_TEXTURES: tuple[str, ...] = ("checker", "stripes", "noise", "gradient", "dots")
MASK_KINDS: tuple[str, ...] = (
    "disk", "ellipse", "rectangle", "blob", "horse", "hair", "thin", "soft",
)

_SS = 4  # supersampling factor per axis for anti-aliased edges
_MARGIN = 0.1  # masks: object kept this fraction of min(H, W) away from the border


# --------------------------------------------------------------------------- helpers
def _out(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _check_size(height: int, width: int) -> tuple[int, int]:
    h, w = int(height), int(width)
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive, got {height} x {width}")
    return h, w


def _unknown(what: str, kind: str, valid: tuple[str, ...]) -> ValueError:
    return ValueError(f"unknown {what} {kind!r}; valid: {', '.join(valid)}")


def _block_mean(a: np.ndarray, s: int) -> np.ndarray:
    """Average ``s x s`` blocks: ``(H*s, W*s) -> (H, W)`` (box filter + decimation)."""
    h, w = a.shape[0] // s, a.shape[1] // s
    return a.reshape(h, s, w, s).mean(axis=(1, 3))


def _subpixel_grid(h: int, w: int, s: int = _SS) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel centre coordinates (pixel units), ``y`` as a column, ``x`` as a row."""
    y = (np.arange(h * s) + 0.5) / s
    x = (np.arange(w * s) + 0.5) / s
    return y[:, None], x[None, :]


def _supersample(inside: Callable[[np.ndarray, np.ndarray], np.ndarray], h: int, w: int,
                 s: int = _SS) -> np.ndarray:
    """Area coverage of the shape ``inside(y, x) -> bool`` per pixel, in [0, 1].

    Computed in bands of output rows so that memory stays ~64 rows of sub-samples."""
    y, x = _subpixel_grid(h, w, s)
    out = np.empty((h, w), np.float64)
    band = 64
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        yb = y[r0 * s:r1 * s]
        out[r0:r1] = _block_mean(
            np.broadcast_to(inside(yb, x), ((r1 - r0) * s, w * s)).astype(np.float64), s)
    return out


def _rotate(y, x, theta: float):
    """Coordinates ``(u, v)`` along/across the direction at angle ``theta`` (radians)."""
    c, s = np.cos(theta), np.sin(theta)
    return x * c + y * s, -x * s + y * c


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _random_colours(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` random colours, uniform in sRGB-encoded space, returned linear ``(n, 3)``."""
    return srgb_to_linear(rng.uniform(0.0, 1.0, size=(n, 3)))


def _colour_map(t: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp: ``t`` in [0, 1] -> colours at equally spaced stops."""
    stops = np.linspace(0.0, 1.0, len(colours))
    return np.stack([np.interp(t, stops, colours[:, c]) for c in range(3)], axis=-1)


def _value_noise(h: int, w: int, rng: np.random.Generator, cell: float,
                 octaves: int = 4, persistence: float = 0.5) -> np.ndarray:
    """Smooth multi-octave value noise in [-1, 1], shape ``(h, w)``.

    Octave ``k`` is a lattice of i.i.d. U(-1, 1) values with spacing ``cell / 2**k`` px,
    interpolated by a cubic spline (``skimage.transform.resize(order=3)``), weighted by
    ``persistence**k``; the sum is divided by the sum of weights and clipped to [-1, 1].
    """
    total = np.zeros((h, w))
    norm = 0.0
    for k in range(octaves):
        c = max(cell / 2**k, 2.0)
        lattice = rng.uniform(-1.0, 1.0, size=(int(np.ceil(h / c)) + 2, int(np.ceil(w / c)) + 2))
        total += persistence**k * resize(lattice, (h, w), order=3, mode="reflect",
                                         anti_aliasing=False)
        norm += persistence**k
    return np.clip(total / norm, -1.0, 1.0)


def _centre(h: int, w: int, rng: np.random.Generator, jitter: float = 0.04):
    """Object centre: image centre plus U(-jitter, jitter) * min(h, w) on each axis."""
    m = min(h, w)
    return h / 2 + rng.uniform(-jitter, jitter) * m, w / 2 + rng.uniform(-jitter, jitter) * m


# --------------------------------------------------------------------------- images
@lru_cache(maxsize=None)
def _load_shipped(name: str) -> np.ndarray:
    """Shipped image as 8-bit sRGB ``(H, W, 3)`` (grey replicated), read-only, cached."""
    img = np.asarray(getattr(skdata, name)())
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    img = np.ascontiguousarray(img[:, :, :3], dtype=np.uint8)
    img.flags.writeable = False
    return img


def shipped_image(name: str, height: int, width: int,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """A scikit-image sample photograph as a linear ``(height, width, 3)`` float32 texture.

    The 8-bit sRGB image is decoded to linear radiance in [0, 1] (:func:`srgb_to_linear`;
    grey images become neutral RGB), a crop with the target aspect ``width / height`` is
    taken, and it is resampled to the requested size with ``skimage.transform.resize``
    (bilinear, Gaussian anti-aliasing when shrinking), in linear space.

    Without ``rng`` the crop is the largest centred one. With ``rng`` the crop side is a
    random fraction ``z ~ U(0.5, 1)`` of the largest one (a random zoom of up to 2x), at a
    uniformly random position, mirrored left-right with probability 1/2.
    Raises ``ValueError`` for a name not in :data:`SHIPPED_IMAGES`.
    """
    if name not in SHIPPED_IMAGES:
        raise _unknown("shipped image", name, SHIPPED_IMAGES)
    height, width = _check_size(height, width)
    src = _load_shipped(name)
    ih, iw = src.shape[:2]
    f = min(ih / height, iw / width)  # largest crop with the target aspect: (f*H, f*W)
    z = 1.0 if rng is None else rng.uniform(0.5, 1.0)
    ch = min(ih, max(1, round(z * f * height)))
    cw = min(iw, max(1, round(z * f * width)))
    if rng is None:
        y0, x0, flip = (ih - ch) // 2, (iw - cw) // 2, False
    else:
        y0 = int(rng.integers(0, ih - ch + 1))
        x0 = int(rng.integers(0, iw - cw + 1))
        flip = bool(rng.random() < 0.5)
    crop = srgb_to_linear(src[y0:y0 + ch, x0:x0 + cw] / 255.0)
    if flip:
        crop = crop[:, ::-1]
    out = resize(crop, (height, width, 3), order=1, mode="reflect", anti_aliasing=True,
                 preserve_range=True)
    return _out(np.clip(out, 0.0, 1.0))


# --------------------------------------------------------------------------- procedural
def procedural_texture(kind: str, height: int, width: int,
                       rng: np.random.Generator) -> np.ndarray:
    """A computed linear ``(height, width, 3)`` float32 texture with values in [0, 1].

    Colours are drawn uniform in sRGB-encoded space and linearised; periods are in pixels.
    Patterns with hard edges are anti-aliased by 4x4 supersampling.

    - ``"checker"``: squares of period ``p ~ LogU(4, max(5, min(H,W)/3))`` px (the side of
      one square is ``p``), two colours; axis-aligned or rotated with probability 1/2,
      random phase. Colour 1 where ``(floor(u/p) + floor(v/p)) mod 2 = 1``.
    - ``"stripes"``: parallel bars, period ``p ~ LogU(3, max(4, min/3))`` px, duty cycle
      ``d ~ U(0.2, 0.8)``, angle ``U(0, pi)``: colour 1 where ``frac(u/p) < d``.
    - ``"noise"``: value noise (:func:`_value_noise`, base cell ``LogU(min/16, min/2)``,
      3-6 octaves, persistence U(0.4, 0.65)), min-max normalised to ``t`` in [0, 1] and
      mapped through a piecewise-linear colour map with 3-5 random colours.
    - ``"gradient"``: ``t`` linear along a random direction (or radial from a random
      centre, probability 1/2), normalised to [0, 1] over the image, 2-4 colour stops.
    - ``"dots"``: disks of radius ``r = p * U(0.15, 0.45)`` on a rotated square lattice of
      period ``p ~ LogU(6, max(7, min/4))`` px: inside where ``du^2 + dv^2 < r^2`` with
      ``du = u - p round(u/p)`` (same for ``v``); dot and background colours.
    """
    if kind not in PROCEDURAL_TEXTURES:
        raise _unknown("procedural texture", kind, PROCEDURAL_TEXTURES)
    h, w = _check_size(height, width)
    m = min(h, w)

    def two_colour(inside) -> np.ndarray:
        c = _random_colours(rng, 2)
        a = _supersample(inside, h, w)[..., None]
        return (1.0 - a) * c[0] + a * c[1]

    if kind == "checker":
        p = _log_uniform(rng, 4.0, max(5.0, m / 3))
        theta = 0.0 if rng.random() < 0.5 else rng.uniform(0.0, np.pi / 2)
        py, px = rng.uniform(0.0, p, size=2)

        def inside(y, x):
            u, v = _rotate(y - py, x - px, theta)
            return (np.floor(u / p) + np.floor(v / p)) % 2 == 1
        out = two_colour(inside)
    elif kind == "stripes":
        p = _log_uniform(rng, 3.0, max(4.0, m / 3))
        duty, theta, phase = rng.uniform(0.2, 0.8), rng.uniform(0.0, np.pi), rng.uniform(0.0, p)
        out = two_colour(lambda y, x: np.mod(_rotate(y, x, theta)[0] + phase, p) < duty * p)
    elif kind == "dots":
        p = _log_uniform(rng, 6.0, max(7.0, m / 4))
        r = p * rng.uniform(0.15, 0.45)
        theta = rng.uniform(0.0, np.pi / 2)
        py, px = rng.uniform(0.0, p, size=2)

        def inside(y, x):
            u, v = _rotate(y - py, x - px, theta)
            du, dv = u - p * np.round(u / p), v - p * np.round(v / p)
            return du**2 + dv**2 < r**2
        out = two_colour(inside)
    elif kind == "noise":
        cell = _log_uniform(rng, max(2.0, m / 16), max(3.0, m / 2))
        octaves, persistence = int(rng.integers(3, 7)), rng.uniform(0.4, 0.65)
        n = _value_noise(h, w, rng, cell, octaves, persistence)
        t = (n - n.min()) / max(float(np.ptp(n)), 1e-12)
        out = _colour_map(t, _random_colours(rng, int(rng.integers(3, 6))))
    else:  # gradient
        y, x = np.mgrid[0:h, 0:w] + 0.5
        if rng.random() < 0.5:
            u = _rotate(y, x, rng.uniform(0.0, 2 * np.pi))[0]
        else:
            u = np.hypot(y - rng.uniform(0, h), x - rng.uniform(0, w))
        t = (u - u.min()) / max(float(np.ptp(u)), 1e-12)
        out = _colour_map(t, _random_colours(rng, int(rng.integers(2, 5))))
    return _out(out)


def random_texture(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A shipped photograph (probability 1/2, random crop/zoom) or a procedural texture,
    the image or kind chosen uniformly; linear ``(height, width, 3)`` float32 in [0, 1]."""
    if rng.random() < 0.5:
        name = SHIPPED_IMAGES[int(rng.integers(len(SHIPPED_IMAGES)))]
        return shipped_image(name, height, width, rng)
    kind = PROCEDURAL_TEXTURES[int(rng.integers(len(PROCEDURAL_TEXTURES)))]
    return procedural_texture(kind, height, width, rng)


# --------------------------------------------------------------------------- masks
def _blob_hires(h: int, w: int, rng: np.random.Generator, extent: float,
                s: int = _SS) -> np.ndarray:
    """Binary random blob on the ``(h*s, w*s)`` sub-pixel grid, one 4-connected component
    without holes, contained in the disk of radius ``extent`` px around a jittered centre.

    Inside where ``f = 1 - rho^2 + a n > 0``, with ``n`` smooth value noise in [-1, 1],
    ``a ~ U(0.4, 0.8)``, and ``rho`` the elliptical radius ``|(dy/Ry, dx/Rx)|``,
    ``Rx, Ry = R * U(0.75, 1)``, ``R = extent / sqrt(1 + a)``: ``f < 0`` for
    ``rho^2 > 1 + a`` bounds the blob, ``f >= 1 - a > 0`` at the centre makes it non-empty.
    """
    a = rng.uniform(0.4, 0.8)
    r = extent / np.sqrt(1.0 + a)
    ry, rx = r * rng.uniform(0.75, 1.0, size=2)
    cy, cx = _centre(h, w, rng)
    noise = _value_noise(h, w, rng, cell=max(2.0, r * rng.uniform(0.5, 1.2)), octaves=3)
    noise = resize(noise, (h * s, w * s), order=1, mode="edge")
    y, x = _subpixel_grid(h, w, s)
    inside = 1.0 - ((y - cy) / ry) ** 2 - ((x - cx) / rx) ** 2 + a * noise > 0
    labels = measure.label(inside, connectivity=1)
    keep = labels == labels[min(int(cy * s), h * s - 1), min(int(cx * s), w * s - 1)]
    return ndimage.binary_fill_holes(keep)


@lru_cache(maxsize=1)
def _horse_silhouette() -> np.ndarray:
    """The horse (True pixels; a few 1-2 px pinholes filled) cropped to its bounding box,
    float64 0/1, read-only."""
    sil = ndimage.binary_fill_holes(~np.asarray(skdata.horse(), dtype=bool))
    rows, cols = np.flatnonzero(sil.any(1)), np.flatnonzero(sil.any(0))
    sil = sil[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].astype(np.float64)
    sil.flags.writeable = False
    return sil


def _horse(h: int, w: int, rng: np.random.Generator, s: int = _SS) -> np.ndarray:
    """``skimage.data.horse`` (black horse on white, so alpha = ~image), cropped to its
    bounding box, scaled to ``U(0.65, 0.8)`` of the largest fit, mirrored with p = 1/2,
    thresholded at 0.5 on the sub-pixel grid and box-filtered."""
    sil = _horse_silhouette()
    if rng.random() < 0.5:
        sil = sil[:, ::-1]
    scale = rng.uniform(0.65, 0.8) * min(h / sil.shape[0], w / sil.shape[1])
    bh, bw = max(1, round(s * scale * sil.shape[0])), max(1, round(s * scale * sil.shape[1]))
    sil = resize(sil, (bh, bw), order=1, mode="edge", anti_aliasing=True) > 0.5
    cy, cx = _centre(h, w, rng)
    y0 = int(np.clip(round(s * cy - bh / 2), 0, h * s - bh))
    x0 = int(np.clip(round(s * cx - bw / 2), 0, w * s - bw))
    canvas = np.zeros((h * s, w * s))
    canvas[y0:y0 + bh, x0:x0 + bw] = sil
    return _block_mean(canvas, s)


def _hair(h: int, w: int, rng: np.random.Generator, s: int = _SS) -> np.ndarray:
    """A fringe of thin curved strands hanging from a gently curved parting line.

    Roots are spaced ``1/density`` px apart (``density ~ U(0.15, 0.3)``/px, jittered by
    +-30 %) along the top of the box. Strand ``i`` has width ``w_i ~ U(1, 2)`` px, opacity
    ``o_i = min(1, U(0.6, 1.6))``, length ``L_i ~ U(0.45, 0.8)`` of the box height and
    heading ``phi(t) = phi0 + kappa t + A sin(2 pi t / lambda + psi)`` (``t`` arc length,
    ``phi0 = pi/2 + N(0, 0.2)`` i.e. downwards), truncated where it leaves the box.
    Its coverage ``c_i`` is the area fraction of pixels within ``w_i / 2`` of the centre
    line (distance transform on the sub-pixel grid); strands combine as independent
    occluders, ``alpha = 1 - prod_i (1 - o_i c_i)``. Most pixels are partially covered;
    fully opaque ones (where an opaque strand covers a whole pixel) are usual but, for
    small masks, not guaranteed.
    """
    mg = _MARGIN * min(h, w)
    top, bottom, left, right = mg, h - mg, mg, w - mg
    span = right - left
    density = rng.uniform(0.15, 0.3)
    n = max(3, int(span * 0.8 * density))
    slots = np.arange(n) + 0.5 + rng.uniform(-0.3, 0.3, n)
    roots_x = left + 0.1 * span + slots * (0.8 * span / n)
    sag = rng.uniform(-0.1, 0.1) * (bottom - top)
    roots_y = top + 0.05 * (bottom - top) + sag * (1 - ((roots_x - w / 2) / (span / 2)) ** 2)
    transmit = np.ones((h, w))
    ds = 0.5 / s
    for i in range(n):
        width_i, opacity = rng.uniform(1.0, 2.0), min(1.0, rng.uniform(0.6, 1.6))
        length = rng.uniform(0.45, 0.8) * (bottom - top)
        kappa = rng.normal(0.0, 0.8) / length
        amp, lam = rng.uniform(0.0, 0.35), rng.uniform(0.3, 1.0) * length
        psi = rng.uniform(0, 2 * np.pi)
        t = np.arange(0.0, length, ds)
        phi = np.pi / 2 + rng.normal(0.0, 0.2) + kappa * t + amp * np.sin(2 * np.pi * t / lam + psi)
        py = roots_y[i] + np.concatenate([[0.0], np.cumsum(np.sin(phi[:-1]) * ds)])
        px = roots_x[i] + np.concatenate([[0.0], np.cumsum(np.cos(phi[:-1]) * ds)])
        ok = (py > top) & (py < bottom) & (px > left) & (px < right)
        stop = np.argmin(ok) if not ok.all() else len(ok)
        py, px = py[:stop], px[:stop]
        if len(py) < 2:
            continue
        pad = width_i + 1.0
        i0, i1 = max(0, int(py.min() - pad)), min(h, int(np.ceil(py.max() + pad)))
        j0, j1 = max(0, int(px.min() - pad)), min(w, int(np.ceil(px.max() + pad)))
        line = np.ones(((i1 - i0) * s, (j1 - j0) * s), dtype=bool)
        line[(py * s).astype(int) - i0 * s, (px * s).astype(int) - j0 * s] = False
        cover = _block_mean(ndimage.distance_transform_edt(line) <= width_i * s / 2, s)
        transmit[i0:i1, j0:j1] *= 1.0 - opacity * cover
    return 1.0 - transmit


def _thin(h: int, w: int, rng: np.random.Generator, s: int = _SS) -> np.ndarray:
    """A wire fence: 1 px wires on integer pixel rows/columns (exactly opaque, no
    anti-aliasing: the point is thinness) every ``U{4..12}`` px, vertical, horizontal or
    both, inside a box of half-size ``U(0.25, 0.4)`` of the image, plus 1-3 diagonal
    wires of width 1 px, anti-aliased by supersampling, clipped to the box."""
    cy, cx = _centre(h, w, rng)
    hy, hx = rng.uniform(0.25, 0.4, size=2) * np.array([h, w])
    mg = _MARGIN * min(h, w)
    i0, i1 = int(max(mg, cy - hy)), int(min(h - mg, cy + hy))
    j0, j1 = int(max(mg, cx - hx)), int(min(w - mg, cx + hx))
    alpha = np.zeros((h, w))
    families = ("vertical", "horizontal", "both")[int(rng.integers(3))]
    if families != "horizontal":
        alpha[i0:i1, j0:j1:int(rng.integers(4, 13))] = 1.0
    if families != "vertical":
        alpha[i0:i1:int(rng.integers(4, 13)), j0:j1] = 1.0
    for _ in range(int(rng.integers(1, 4))):
        theta = rng.uniform(0.0, np.pi)
        y0, x0 = rng.uniform(i0, i1), rng.uniform(j0, j1)

        def wire(y, x, theta=theta, y0=y0, x0=x0):
            on = np.abs(_rotate(y - y0, x - x0, theta)[1]) < 0.5
            return on & (y >= i0) & (y < i1) & (x >= j0) & (x < j1)
        alpha = np.maximum(alpha, _supersample(wire, h, w, s))
    return alpha


def _soft(h: int, w: int, rng: np.random.Generator, s: int = _SS) -> np.ndarray:
    """A blob with a wide soft edge, optionally of glass-like uniform partial opacity.

    With ``d`` the signed distance to the blob outline (px, positive inside) and ramp
    width ``r = max(10, 0.1 min(H, W)) * U(1, 1.5)`` px, ``alpha = g * S(1/2 + d / r)``,
    ``S(t) = 3t^2 - 2t^3`` on ``t`` clipped to [0, 1]: alpha goes from 0 to ``g`` over
    ``r`` px. ``g = 1`` (an opaque core) with probability 1/2, else ``g ~ U(0.3, 0.7)``.
    """
    m = min(h, w)
    ramp = max(10.0, 0.1 * m) * rng.uniform(1.0, 1.5)
    glass = 1.0 if rng.random() < 0.5 else rng.uniform(0.3, 0.7)
    blob = _blob_hires(h, w, rng, extent=max(2.0, (0.5 - _MARGIN - 0.04) * m - ramp / 2), s=s)
    d = (ndimage.distance_transform_edt(blob) - ndimage.distance_transform_edt(~blob)) / s
    t = np.clip(0.5 + d / ramp, 0.0, 1.0)
    return glass * _block_mean(t * t * (3.0 - 2.0 * t), s)


def alpha_mask(kind: str, height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A straight-alpha mask ``(height, width)`` float32 in [0, 1] for a foreground object.

    The object is roughly centred (centre jitter up to 4 % of ``min(H, W)``) and kept
    inside the image with a margin of about 10 % of ``min(H, W)``. Kinds:

    - ``"disk"``: radius ``U(0.25, 0.36) * min(H, W)``;
    - ``"ellipse"``: semi-axes ``a ~ U(0.2, 0.36) * min``, ``b = a * U(0.4, 0.85)``,
      random orientation;
    - ``"rectangle"``: half-sides ``U(0.15, 0.35) * min``, rotated by ``U(-pi/6, pi/6)``,
      shrunk so that the half-diagonal is at most ``0.36 * min``;
    - ``"blob"``: thresholded smooth noise, one connected component (:func:`_blob_hires`);
    - ``"horse"``: the ``skimage.data.horse`` silhouette (:func:`_horse`);
    - ``"hair"``: many curved strands 1-2 px wide with partial opacity (:func:`_hair`);
    - ``"thin"``: 1 px wire fence plus diagonal wires (:func:`_thin`);
    - ``"soft"``: blob with a >= 10 px soft edge, possibly glass-like (:func:`_soft`).

    Shapes with hard outlines are anti-aliased by 4x4 supersampling (alpha = covered area).
    """
    if kind not in MASK_KINDS:
        raise _unknown("mask kind", kind, MASK_KINDS)
    h, w = _check_size(height, width)
    m = min(h, w)
    rmax = (0.5 - _MARGIN - 0.04) * m  # largest object "radius" that keeps the margin
    if kind == "disk":
        r = rng.uniform(0.25, 0.36) * m
        cy, cx = _centre(h, w, rng)
        alpha = _supersample(lambda y, x: (y - cy) ** 2 + (x - cx) ** 2 < r**2, h, w)
    elif kind == "ellipse":
        a = rng.uniform(0.2, 0.36) * m
        b = a * rng.uniform(0.4, 0.85)
        theta = rng.uniform(0.0, np.pi)
        cy, cx = _centre(h, w, rng)

        def inside(y, x):
            u, v = _rotate(y - cy, x - cx, theta)
            return (u / a) ** 2 + (v / b) ** 2 < 1.0
        alpha = _supersample(inside, h, w)
    elif kind == "rectangle":
        hu, hv = rng.uniform(0.15, 0.35, size=2) * m
        shrink = min(1.0, rmax / np.hypot(hu, hv))
        hu, hv = hu * shrink, hv * shrink
        theta = rng.uniform(-np.pi / 6, np.pi / 6)
        cy, cx = _centre(h, w, rng)

        def inside(y, x):
            u, v = _rotate(y - cy, x - cx, theta)
            return (np.abs(u) < hu) & (np.abs(v) < hv)
        alpha = _supersample(inside, h, w)
    elif kind == "blob":
        alpha = _block_mean(_blob_hires(h, w, rng, extent=rmax).astype(np.float64), _SS)
    elif kind == "horse":
        alpha = _horse(h, w, rng)
    elif kind == "hair":
        alpha = _hair(h, w, rng)
    elif kind == "thin":
        alpha = _thin(h, w, rng)
    else:
        alpha = _soft(h, w, rng)
    return _out(np.clip(alpha, 0.0, 1.0))


# --------------------------------------------------------------------------- HDR
def hdr_highlights(rgb: np.ndarray, rng: np.random.Generator, count: int,
                   peak: tuple[float, float] = (20.0, 200.0),
                   radius: tuple[float, float] = (0.5, 3.0)) -> np.ndarray:
    """A copy of ``rgb`` with ``count`` small, very bright disks added ("bokeh balls").

    Spot ``k``: centre uniform over the image, radius ``r_k ~ U(radius)`` px, peak
    radiance ``P_k ~ LogU(peak)`` (linear units, so far above the LDR white of 1), colour
    ``P_k * tint_k`` with ``tint_k`` a random near-white colour whose largest channel
    is 1. The added radiance is ``P_k tint_k c_k(x)``, ``c_k`` the pixel's area coverage by
    the disk (4x4 supersampling), so a spot's integrated power is about ``pi r^2 P``.
    Pixels farther than ``r_k`` + 1 px from every centre are unchanged.
    Input ``(H, W, 3)``; output float32, C-contiguous.
    """
    out = np.array(rgb, dtype=np.float32, order="C", copy=True)
    if out.ndim != 3 or out.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3), got {out.shape}")
    h, w = out.shape[:2]
    for _ in range(int(count)):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        r = rng.uniform(*radius)
        p = _log_uniform(rng, *peak)
        tint = rng.uniform(0.6, 1.0, size=3)
        tint /= tint.max()
        i0, i1 = max(0, int(cy - r) - 1), min(h, int(np.ceil(cy + r)) + 1)
        j0, j1 = max(0, int(cx - r) - 1), min(w, int(np.ceil(cx + r)) + 1)
        cover = _supersample(lambda y, x: (y + i0 - cy) ** 2 + (x + j0 - cx) ** 2 < r * r,
                             i1 - i0, j1 - j0)
        out[i0:i1, j0:j1] += (cover[..., None] * (p * tint)).astype(np.float32)
    return out
