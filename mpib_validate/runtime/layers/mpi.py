"""The multiplane image (MPI): premultiplied RGBA layers at fixed disparities.

Storage models only what is there: each non-empty layer keeps the bounding box of its
content (alpha > 0) and nothing else; an empty plane is not stored at all. Layers live
on a *canvas*: the frame plus ``margin`` pixels on every side, so that layers taken
from card scenes can hold the real content a defocused view sees beyond the frame
edge. An MPI built from a picture has ``margin = 0``, and the compositor continues its
content past the frame edge by replication (the official padding).

Plane placement (:func:`uniform_planes`, :func:`adaptive_planes`) and the split of a
disparity between its two neighbouring planes (:func:`split_between_planes`) live here
too, since both the card path and the colour + depth path use them.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np



#: Side (px) of the canvas-aligned tiles in which a sparse layer is stored (and on whose
#: multiples the compositor skips empty parts of a layer): tile ``(ty, tx)`` covers canvas
#: rows ``[ty T, ty T + T)`` and columns ``[tx T, tx T + T)``. 32 px: a band of a
#: smooth depth (tens of rows of each plane) wastes less of its tiles than with 64 px
#: (the 2000x1333 photo stand-in's MPI: 0.33 GB at 64 px, 0.20 GB at 32 px, 0.14 GB at
#: 16 px; the same composite to the bit). A multiple of the compositor's 16 px cells
#: and a divisor of its 64 to 512 px output tiles.
TILE_PX = 32
#: A layer is stored as tiles when its occupied tiles cover at most this fraction of its
#: bounding box (a thin band across the frame, a level set of a smooth depth); otherwise
#: as one dense box.
TILED_FILL_MAX = 0.6


class Layer:
    """One MPI plane: premultiplied RGBA over a box of the canvas.

    Stored either dense (``rgba``, the whole box) or, for content spread thinly over a
    large box, as the box's occupied canvas-aligned tiles of :data:`TILE_PX` px
    (``tiles``: ``(keys (n, 2) tile row/column, data (n, T, T, C))``; every pixel
    outside them is zero). ``rgba`` always reads the dense box (built on demand for a
    tiled layer); the compositor reads tiles through :meth:`read` and :meth:`occupancy`.

    Attributes:
        disparity: the plane's disparity (1/scene-unit).
        rgba: ``(h, w, C)`` float32: colour premultiplied by alpha (linear radiance),
            alpha, then any extra channels premultiplied like the colour (``C = 4``
            unless the builder was given extras).
        y0, x0: top-left of the box in canvas pixels.
        group: ``None``: the layer occludes every farther one (Eq. 1). An integer:
            additive groups (slabs), far to near. Content exactly on plane ``k`` forms
            one group, the two additive shares of content strictly inside the interval
            ``(d_k, d_k+1)`` another (see :func:`split_between_planes`), and consecutive
            groups within a disparity span may be merged into one slab
            (:func:`layers_from_sheets`). The layers of one group are blurred and
            *summed*; groups are composited with "over".
    """

    __slots__ = ("disparity", "_rgba", "y0", "x0", "group", "tiles", "_shape", "_memo")

    def __init__(self, disparity: float, rgba: np.ndarray | None, y0: int, x0: int,
                 group: int | None = None, tiles=None, shape=None):
        self.disparity = disparity
        self._rgba = rgba
        self.y0, self.x0 = y0, x0
        self.group = group
        self.tiles = tiles
        self._memo = {}  # derived, read-only: tile lookup, occupancy maps
        if rgba is not None:
            self._shape = tuple(rgba.shape)
        elif tiles is None or shape is None:
            raise ValueError("a layer needs its dense rgba, or tiles and the box shape")
        else:
            self._shape = tuple(shape)

    def __repr__(self) -> str:
        kind = "dense" if self.tiles is None else f"{len(self.tiles[0])} tiles"
        return (f"Layer(disparity={self.disparity!r}, box={self.box}, group={self.group!r}, "
                f"{kind})")

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(h, w, C)`` of the box."""
        return self._shape

    @property
    def nbytes(self) -> int:
        """Bytes held by the layer's pixels."""
        return int(self._rgba.nbytes if self._rgba is not None else self.tiles[1].nbytes)

    @property
    def rgba(self) -> np.ndarray:
        if self._rgba is not None:
            return self._rgba
        out = np.zeros(self._shape, np.float32)
        self.read(out, self.y0, self.x0)
        return out

    @rgba.setter
    def rgba(self, value: np.ndarray) -> None:
        self._rgba, self.tiles, self._shape = value, None, tuple(value.shape)
        self._memo = {}

    @property
    def box(self) -> tuple[int, int, int, int]:
        h, w = self._shape[:2]
        return self.y0, self.y0 + h, self.x0, self.x0 + w

    def read(self, out: np.ndarray, y0: int, x0: int, channel: int | None = None) -> None:
        """Write the layer's content into ``out``, whose pixel ``[0, 0]`` is canvas pixel
        ``(y0, x0)``, where they overlap (``out`` is expected zero elsewhere). With
        ``channel``, only that channel, into a 2-D ``out``."""
        H, W = out.shape[:2]
        ch = (slice(None),) if channel is None else (channel,)
        if self.tiles is None:
            ly0, ly1, lx0, lx1 = self.box
            a0, a1 = max(ly0, y0), min(ly1, y0 + H)
            b0, b1 = max(lx0, x0), min(lx1, x0 + W)
            if a0 < a1 and b0 < b1:
                out[a0 - y0:a1 - y0, b0 - x0:b1 - x0] = self._rgba[
                    (slice(a0 - ly0, a1 - ly0), slice(b0 - lx0, b1 - lx0)) + ch]
            return
        keys, data = self.tiles
        T = data.shape[1]
        index = self._memo.get("index")
        if index is None:
            index = self._memo["index"] = {(int(a), int(b)): i for i, (a, b) in enumerate(keys)}
        for ky in range(max(y0, 0) // T, -(-(y0 + H) // T)):
            for kx in range(max(x0, 0) // T, -(-(x0 + W) // T)):
                i = index.get((ky, kx))
                if i is None:
                    continue
                ty, tx = ky * T, kx * T
                a0, a1 = max(ty, y0), min(ty + T, y0 + H)
                b0, b1 = max(tx, x0), min(tx + T, x0 + W)
                out[a0 - y0:a1 - y0, b0 - x0:b1 - x0] = data[
                    (i, slice(a0 - ty, a1 - ty), slice(b0 - tx, b1 - tx)) + ch]

    def add_channel(self, out: np.ndarray, channel: int) -> None:
        """Add the layer's ``channel`` into ``out``, a canvas-aligned 2-D array whose
        sides are whole multiples of the storage tile (:data:`TILE_PX`) and cover the
        layer's box (a tiled layer's stored tiles in one step)."""
        if self.tiles is None:
            y0, y1, x0, x1 = self.box
            out[y0:y1, x0:x1] += self._rgba[..., channel]
            return
        keys, data = self.tiles
        T = data.shape[1]
        if out.shape[0] % T or out.shape[1] % T:
            raise ValueError(f"add_channel: out's sides {out.shape} are not multiples "
                             f"of the storage tile ({T} px)")
        grid = out.reshape(out.shape[0] // T, T, out.shape[1] // T, T).swapaxes(1, 2)
        grid[keys[:, 0], keys[:, 1]] += data[..., channel]  # stored tiles are distinct

    def occupancy(self, canvas: tuple[int, int], T: int = TILE_PX) -> np.ndarray:
        """Boolean map over the canvas-aligned tiles of side ``T`` (a multiple or a
        divisor of :data:`TILE_PX`, or any side for a dense layer): True where the tile
        holds content of this layer (for a tiled layer and ``T`` a multiple of the
        storage tile: where a stored tile lies). Read-only (kept for reuse)."""
        key = ("occupancy", tuple(canvas), T)
        if key not in self._memo:
            occ = self._occupancy(canvas, T)
            occ.setflags(write=False)
            self._memo[key] = occ
        return self._memo[key]

    def _occupancy(self, canvas, T):
        ny, nx = -(-canvas[0] // T), -(-canvas[1] // T)
        occ = np.zeros((ny, nx), bool)
        if self.tiles is not None and T % self.tiles[1].shape[1] == 0:
            f = T // self.tiles[1].shape[1]
            keys = self.tiles[0]
            occ[keys[:, 0] // f, keys[:, 1] // f] = True
            return occ
        if self.tiles is not None and self.tiles[1].shape[1] % T == 0:
            keys, data = self.tiles
            S = data.shape[1]
            f = S // T
            sub = (data != 0).any(axis=3).reshape(len(keys), f, T, f, T).any(axis=(2, 4))
            big = np.zeros((-(-canvas[0] // S) * f, -(-canvas[1] // S) * f), bool)
            for (ty, tx), blk in zip(keys, sub):
                big[ty * f:ty * f + f, tx * f:tx * f + f] = blk
            return big[:ny, :nx]
        y0, y1, x0, x1 = self.box
        ty0, tx0 = y0 // T, x0 // T
        ty1, tx1 = -(-y1 // T), -(-x1 // T)
        a = np.zeros(((ty1 - ty0) * T, (tx1 - tx0) * T), bool)
        self_nz = (self.rgba != 0).any(axis=2)
        a[y0 - ty0 * T:y1 - ty0 * T, x0 - tx0 * T:x1 - tx0 * T] = self_nz
        occ[ty0:ty1, tx0:tx1] = a.reshape(ty1 - ty0, T, tx1 - tx0, T).any(axis=(1, 3))
        return occ


def tile_layer(canvas_layer: np.ndarray, box, touched, T: int = TILE_PX):
    """The occupied ``T``-tiles of a canvas-sized layer ``(H_c, W_c, C)`` within ``box``
    (r0, r1, c0, c1), given the flat canvas indices of the pixels it holds: ``(keys,
    data)`` for :class:`Layer` (tile parts outside the canvas are zero), or None when
    they cover more than :data:`TILED_FILL_MAX` of the box (dense is then no larger)."""
    hc, wc, C = canvas_layer.shape
    r, c = np.divmod(np.asarray(touched, np.int64), wc)
    ntx = -(-wc // T)
    ids = np.unique((r // T) * ntx + c // T)
    r0, r1, c0, c1 = box
    if ids.size * T * T > TILED_FILL_MAX * (r1 - r0) * (c1 - c0):
        return None
    keys = np.stack(np.divmod(ids, ntx), axis=1)
    data = np.zeros((ids.size, T, T, C), np.float32)
    for i, (ty, tx) in enumerate(keys):
        blk = canvas_layer[ty * T:ty * T + T, tx * T:tx * T + T]
        data[i, :blk.shape[0], :blk.shape[1]] = blk
    return keys, data


@dataclass
class MPI:
    """Layers sorted far to near (increasing disparity).

    Attributes:
        height, width: the frame size in pixels.
        margin: canvas pixels beyond the frame on each side that the layers may hold.
        layers: non-empty layers, far to near.
    """

    height: int
    width: int
    margin: int = 0
    layers: list[Layer] = field(default_factory=list)
    #: the largest straight colour per channel, when the builder knows it (saves the
    #: compositor a pass over every layer); None: computed from the layers
    colour_max: np.ndarray | None = None
    #: derived data that does not depend on the focus (the compositor's merged slabs),
    #: keyed by what it was derived from, layer identities included
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def grouped(self) -> bool:
        """True when the layers are additive interval groups (:attr:`Layer.group`)."""
        return any(l.group is not None for l in self.layers)

    @property
    def channels(self) -> int:
        """Channels per layer: premultiplied RGB, alpha, then any extra premultiplied
        channels (e.g. the film alpha of a transparent render); 4 when empty."""
        return self.layers[0].shape[2] if self.layers else 4

    @property
    def canvas_shape(self) -> tuple[int, int]:
        return self.height + 2 * self.margin, self.width + 2 * self.margin

    @property
    def plane_count(self) -> int:
        """Distinct plane disparities (with additive groups a plane holds up to three
        layers: its own content and a share of each neighbouring interval)."""
        return len({l.disparity for l in self.layers})

    @property
    def disparities(self) -> np.ndarray:
        return np.array([l.disparity for l in self.layers])

    def dense(self) -> np.ndarray:
        """``(N, H_c, W_c, C)`` canvas-sized layers (for tests and small images)."""
        hc, wc = self.canvas_shape
        out = np.zeros((len(self.layers), hc, wc, self.channels), np.float32)
        for i, l in enumerate(self.layers):
            y0, y1, x0, x1 = l.box
            out[i, y0:y1, x0:x1] = l.rgba
        return out

    @classmethod
    def from_dense(cls, disparities, rgba: np.ndarray, margin: int = 0) -> "MPI":
        """Build from ``(N, H_c, W_c, 4)`` premultiplied layers; crops each to its content
        and drops empty ones. Disparities need not be sorted."""
        rgba = np.asarray(rgba, np.float32)
        if rgba.ndim != 4 or rgba.shape[-1] != 4:
            raise ValueError(f"layers must be (N, H, W, 4), got {rgba.shape}")
        if len(disparities) != rgba.shape[0]:
            raise ValueError(f"{len(disparities)} disparities for {rgba.shape[0]} layers")
        hc, wc = rgba.shape[1:3]
        mpi = cls(hc - 2 * margin, wc - 2 * margin, margin)
        for d, layer in sorted(zip(disparities, rgba), key=lambda t: t[0]):
            mpi.add(float(d), layer, 0, 0)
        return mpi

    def add(self, disparity: float, rgba: np.ndarray, y0: int, x0: int,
            box: tuple[int, int, int, int] | None = None, group: int | None = None,
            touched=None) -> None:
        """Add premultiplied content at canvas position ``(y0, x0)``, cropped to where
        alpha or colour is non-zero (or to ``box`` = (r0, r1, c0, c1) within ``rgba``
        when the caller knows it); nothing is stored for empty content. ``group``: see
        :attr:`Layer.group`. ``touched``: for canvas-sized ``rgba`` at ``(0, 0)``, the
        flat canvas indices of every pixel it holds; the layer is then stored as tiles
        where that is smaller (:func:`tile_layer`)."""
        if not np.isfinite(disparity) or disparity < 0:
            raise ValueError(f"layer disparity must be finite and >= 0, got {disparity}")
        if box is None:
            nz = (rgba != 0).any(axis=2)
            if not nz.any():
                return
            rows = np.flatnonzero(nz.any(axis=1))
            cols = np.flatnonzero(nz.any(axis=0))
            r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        else:
            r0, r1, c0, c1 = box
        tiles = None
        if touched is not None and y0 == 0 and x0 == 0 and rgba.dtype == np.float32:
            tiles = tile_layer(rgba, (r0, r1, c0, c1), touched)
        if tiles is not None:
            layer = Layer(float(disparity), None, int(r0), int(c0), group, tiles,
                          (int(r1 - r0), int(c1 - c0), rgba.shape[2]))
        else:
            crop = np.array(rgba[r0:r1, c0:c1], dtype=np.float32, order="C", copy=True)
            layer = Layer(float(disparity), crop, y0 + int(r0), x0 + int(c0), group)
        self.layers.append(layer)
        self.layers.sort(key=lambda l: (-1 if l.group is None else l.group, l.disparity))


# --------------------------------------------------------------------------------------
# Plane placement


#: Content whose blur radius is within this many pixels of a plane's goes wholly to that
#: plane (see :func:`split_between_planes`); a radius error of 0.02 px is invisible.
SNAP_PX = 0.02


def uniform_planes(n: int = 32, d_max: float = 1.0) -> np.ndarray:
    """The paper's planes: ``d_i = (i + 0.5) / n * d_max``, far to near."""
    return (np.arange(n) + 0.5) / n * d_max


def plane_spacing(blur_parameter: float, tolerance_px: float) -> float:
    """Largest disparity step whose blur-radius step ``A * step`` keeps the radius
    quantisation error within ``tolerance_px``: a disparity between two planes is at
    most half a step from one of them, so ``step = 2 tol / A``."""
    if blur_parameter <= 0 or tolerance_px <= 0:
        raise ValueError("blur parameter and tolerance must be > 0")
    return 2.0 * tolerance_px / blur_parameter


def adaptive_planes(intervals, blur_parameter: float, tolerance_px: float = 0.25) -> np.ndarray:
    """Planes only where content is: each disparity interval ``[lo, hi]`` (a point when
    ``lo == hi``) gets the fewest evenly spaced planes whose step is at most
    :func:`plane_spacing`, ends included. Overlapping intervals are merged first.
    Returns sorted disparities (far to near); empty disparity ranges cost nothing.
    """
    step = plane_spacing(blur_parameter, tolerance_px)
    spans = sorted((float(lo), float(hi)) for lo, hi in intervals)
    merged: list[list[float]] = []
    for lo, hi in spans:
        if merged and lo <= merged[-1][1] + 1e-12:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    planes = []
    for lo, hi in merged:
        n = max(1, int(math.ceil((hi - lo) / step - 1e-9)))
        planes.extend(np.linspace(lo, hi, n + 1) if hi > lo else [lo])
    return np.unique(np.asarray(planes, np.float64))


def split_between_planes(d: np.ndarray, alpha: np.ndarray, planes: np.ndarray,
                         snap: float = 0.0, additive: bool = False):
    """Share content of disparity ``d`` and alpha ``alpha`` between its two neighbouring
    planes so that compositing gives back alpha and Eq. 16 gives back ``d``.

    With ``w = (d - d_lo) / (d_hi - d_lo)``, the near plane gets ``a_hi = w alpha`` and
    the far plane ``a_lo = alpha (1 - w) / (1 - w alpha)``, so that
    ``a_hi + (1 - a_hi) a_lo = alpha`` ("over" restores coverage, an opaque pixel stays
    opaque: no cracks between slabs) and ``d_hi a_hi + d_lo (1 - a_hi) a_lo = d alpha``
    (Eq. 16). Both layers keep the pixel's own colour. Disparities outside the planes'
    range go wholly to the first or last plane.

    The far plane is an opaque backing wherever the content is opaque (``w < 1``), which
    is what keeps slabs of a tilted surface from cracking; but it would also duplicate
    opaque content that lies on a plane up to rounding. Content within ``snap`` (in
    disparity) of a plane therefore goes wholly to that plane.

    ``additive=True`` shares the alpha instead: ``a_hi = w alpha``, ``a_lo = (1 - w)
    alpha``, so that the two shares *add up* to the content (and Eq. 16 holds for the
    sum). The compositor then sums the two blurred shares of an interval instead of
    laying one over the other (:attr:`Layer.group`): the over split's opaque backing,
    blurred with Eq. 1, counts a small out-of-focus highlight up to twice (once per
    plane, since a blurred near share hardly occludes the blurred backing).

    Returns ``(index_lo, alpha_lo, alpha_hi)``: the far plane's index and both alphas.
    """
    planes = np.asarray(planes, np.float64)
    d = np.asarray(d, np.float64)
    alpha = np.asarray(alpha, np.float64)
    if len(planes) == 1:
        return np.zeros(d.shape, np.int64), alpha, np.zeros_like(alpha)
    idx = np.clip(np.searchsorted(planes, d, side="right") - 1, 0, len(planes) - 2)
    lo, hi = planes[idx], planes[idx + 1]
    w = np.clip((d - lo) / (hi - lo), 0.0, 1.0)
    if snap > 0:
        w = np.where(d - lo <= snap, 0.0, np.where(hi - d <= snap, 1.0, w))
    a_hi = w * alpha
    if additive:
        return idx, alpha - a_hi, a_hi
    denom = 1.0 - a_hi
    # denom = 0 only for opaque content exactly on the near plane: nothing goes behind it
    a_lo = np.where(denom > 0, alpha * (1.0 - w) / np.where(denom > 0, denom, 1.0), 0.0)
    return idx, a_lo, a_hi


@dataclass
class Sheet:
    """Content to be cut into planes: straight colour, alpha and disparity per pixel
    over a box of the canvas starting at ``origin`` (row, column)."""

    origin: tuple[int, int]
    colour: np.ndarray  # (h, w, K) straight, linear radiance (K = 3, or 3 + extras)
    alpha: np.ndarray  # (h, w)
    disparity: np.ndarray  # (h, w), 1/scene-unit

    def pixels(self, canvas_width: int) -> "Pixels":
        """The pixels with alpha > 0, as a :class:`Pixels` list on the canvas."""
        alpha = np.asarray(self.alpha, np.float64)
        h, w = alpha.shape
        keep = np.flatnonzero(alpha.ravel() > 0)
        rows, cols = np.divmod(keep, w)
        y0, x0 = self.origin
        colour = np.asarray(self.colour, np.float64)
        return Pixels((rows + y0) * canvas_width + (cols + x0),
                      colour.reshape(-1, colour.shape[-1])[keep],
                      alpha.ravel()[keep],
                      np.broadcast_to(np.asarray(self.disparity, np.float64),
                                      alpha.shape).ravel()[keep])


@dataclass
class Pixels:
    """Sparse content to be cut into planes: flat canvas indices (row * canvas width +
    column) with straight colour ``(n, K)``, alpha ``(n,)`` and disparity ``(n,)``; for
    content that covers a small part of the canvas (fills, edge pixels)."""

    index: np.ndarray
    colour: np.ndarray
    alpha: np.ndarray
    disparity: np.ndarray


def slab_of_groups(planes, span: float) -> dict:
    """Slab id of each additive group (``2k``: plane ``k``; ``2k + 1``: the interval
    ``(d_k, d_k+1)``): consecutive groups merged while the slab's disparity span stays
    within ``span`` (0: one slab per group)."""
    n = len(planes)
    out, slab, start = {}, -1, 0.0
    for g in range(max(2 * n - 1, 1)):
        lo, hi = planes[g // 2], planes[min((g + 1) // 2, n - 1)]
        if slab < 0 or span <= 0 or hi - start > span:
            slab, start = slab + 1, lo
        out[g] = slab
    return out


#: The additive groups of a plane's content by role (:func:`_share_parts`): 0 content
#: exactly on plane ``p`` (group ``2p``), 1 its far share of the interval above (group
#: ``2p + 1``), 2 its near share of the interval below (group ``2p - 1``).
_GROUP_OF_ROLE = {0: lambda p: 2 * p, 1: lambda p: 2 * p + 1, 2: lambda p: 2 * p - 1}


@dataclass(frozen=True, eq=False)
class LayerPlan:
    """What the layer builder lays, decided before any pixel is cut: the planes (far to
    near) and the layers on them, slab by slab. :func:`layers_from_sheets` follows it;
    the memory estimate (:mod:`mpib_validate.runtime.budget`) reads it.

    Attributes:
        planes: the plane disparities, sorted (None when more than the ``max_planes``
            they were planned with: :attr:`plane_count` then says how many).
        plane_count: how many planes.
        split: how a pixel is shared between its two planes (:func:`split_between_planes`).
        slab_of: with ``split="additive"``, the slab of each additive group
            (:func:`slab_of_groups`); else empty.
        slabs: ``((slab, ((plane, roles), ...)), ...)`` in the order the layers are laid:
            each ``(plane, roles)`` is one layer (``roles`` as in :func:`_share_parts`;
            slab None without the additive split). Computed when first read.
    """

    planes: np.ndarray | None
    plane_count: int
    split: str = "linear"
    slab_of: dict = field(default_factory=dict)

    @functools.cached_property
    def slabs(self) -> tuple:
        slab_layers: dict = {}  # slab -> [(plane, roles)], in the order first reached
        for p in range(self.plane_count):
            if self.split != "additive":
                slab_layers.setdefault(None, []).append((p, (0, 1)))
                continue
            by_slab: dict = {}
            for role in (1, 0, 2):
                g = _GROUP_OF_ROLE[role](p)
                if g in self.slab_of:
                    by_slab.setdefault(self.slab_of[g], []).append(role)
            for sl, roles in by_slab.items():
                slab_layers.setdefault(sl, []).append((p, tuple(roles)))
        return tuple((sl, tuple(m)) for sl, m in slab_layers.items())

    def reached(self, lo, hi):
        """The planes content in the disparity ranges ``[lo, hi]`` (arrays) is cut into:
        ``(first, last)`` plane indices. A value ``d`` goes to the two planes around it
        (:func:`split_between_planes`), one below the first plane or above the last to
        that plane."""
        n = self.plane_count
        first = np.clip(np.searchsorted(self.planes, lo, side="right") - 1, 0, n - 1)
        last = np.clip(np.searchsorted(self.planes, hi, side="right"), 0, n - 1)
        return first, last

    def intervals_reached(self, lo, hi):
        """The intervals ``(d_k, d_k+1)`` content in the ranges ``[lo, hi]`` falls in:
        ``(first, last)`` interval indices ``k`` (``n >= 2`` planes)."""
        n = self.plane_count
        first = np.clip(np.searchsorted(self.planes, lo, side="right") - 1, 0, n - 2)
        last = np.clip(np.searchsorted(self.planes, hi, side="left") - 1, 0, n - 2)
        return first, np.maximum(last, first)

    def straddling(self) -> np.ndarray:
        """``(n,)`` bool: planes ``0 < k < n - 1`` whose interval below and interval above
        lie in different slabs (additive split), so that their shares of the two are two
        layers."""
        n = self.plane_count
        out = np.zeros(n, bool)
        if self.split == "additive" and n >= 2:
            for k in range(1, n - 1):
                out[k] = self.slab_of[2 * k - 1] != self.slab_of[2 * k + 1]
        return out

    def tile_area(self, D: np.ndarray, T: int = TILE_PX,
                  content: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of the canvas-aligned storage tiles (side ``T``) that may hold each
        plane's content for a frame of disparities ``D`` (no margin): a tile holds plane
        ``k`` when its disparity range reaches the interval around ``d_k`` (every pixel
        is shared by the two planes around its disparity). A :meth:`straddling` plane
        stores the tiles of each of its two intervals. ``content``: ``(H, W)`` bool, the
        pixels that hold content (a sheet's ``alpha > 0``; default all): the range of a
        tile is over those, and a tile with none holds no plane. Returns the tile pixels
        per plane and the number of layers on it counted so (1 or 2)."""
        n = self.plane_count
        lo, hi = (v.ravel() for v in block_ranges(D, T, content))
        if content is not None:
            lo, hi = lo[lo <= hi], hi[lo <= hi]  # the tiles that hold content
        s_lo, s_hi = self.reached(lo, hi)
        diff = np.bincount(s_lo, minlength=n + 1) - np.bincount(s_hi + 1, minlength=n + 1)
        union = np.cumsum(diff[:n]).astype(np.float64) * T * T
        count = np.ones(n, np.int64)
        two = self.straddling()
        if not two.any():
            return union, count
        i_lo, i_hi = self.intervals_reached(lo, hi)
        diff = np.bincount(i_lo, minlength=n) - np.bincount(i_hi + 1, minlength=n)
        per = np.cumsum(diff[:n - 1]).astype(np.float64) * T * T
        out = union.copy()
        for k in np.flatnonzero(two):  # plane k between interval k - 1 and interval k
            out[k] = per[k - 1] + per[k]
            count[k] = 2
        return out, count


def block_ranges(D: np.ndarray, T: int, content: np.ndarray | None = None):
    """``(lo, hi)``, each ``(ceil(H / T), ceil(W / T))``: the minimum and maximum of ``D``
    over each ``T x T`` block (the last row and column of blocks padded with the edge
    values). ``content``: ``(H, W)`` bool, over those pixels only; a block with none has
    ``lo = inf``, ``hi = -inf``."""
    H, W = D.shape
    ny, nx = -(-H // T), -(-W // T)
    pad = ((0, ny * T - H), (0, nx * T - W))
    v = np.pad(D, pad, mode="edge").reshape(ny, T, nx, T)
    if content is None:
        return v.min(axis=(1, 3)), v.max(axis=(1, 3))
    c = np.pad(np.asarray(content, bool), pad).reshape(ny, T, nx, T)
    return np.where(c, v, np.inf).min(axis=(1, 3)), np.where(c, v, -np.inf).max(axis=(1, 3))


def plan_layers(planes, split: str = "linear", slab: float = 0.0) -> LayerPlan:
    """The :class:`LayerPlan` of ``planes``: with ``split="additive"``, content exactly on
    plane ``k`` is group ``2k`` and the two shares of content strictly inside the
    interval ``(d_k, d_k+1)`` group ``2k + 1`` (the far share on plane ``k``, the near
    one on plane ``k + 1``); groups within ``slab`` of disparity form one slab
    (:func:`slab_of_groups`), and each plane holds one layer per slab it reaches.
    Otherwise a plane is one layer."""
    planes = np.asarray(planes, np.float64)
    slab_of = slab_of_groups(planes, slab) if split == "additive" else {}
    return LayerPlan(planes, len(planes), split, slab_of)


#: Pixels per step when a sheet's pixels are split between planes (bounds the
#: temporaries of the split: ~100 B per pixel of the step).
SPLIT_CHUNK_PX = 1 << 20


def _share_parts(split: str, d, alpha, planes, snap):
    """The parts of a split (:func:`layers_from_sheets`): ``[(plane index, share alpha,
    where the share is > 0, role, cover_is_alpha)]``. ``role`` 0 is content on its plane
    exactly, 1 the far and 2 the near share of an interval (additive);
    ``cover_is_alpha``: a nearer sheet in the same layer hides a farther one by the
    content's whole alpha (both additive shares, or the nearest split) rather than by
    this share's."""
    if split == "nearest":
        return [(np.abs(d[..., None] - planes).argmin(axis=-1), alpha, alpha > 0, 0, True)]
    if split == "linear":
        idx, a_lo, a_hi = split_between_planes(d, alpha, planes, snap)
        return [(idx, a_lo, a_lo > 0, 0, False),
                (np.minimum(idx + 1, len(planes) - 1), a_hi, a_hi > 0, 1, False)]
    if split == "additive":
        idx, a_lo, a_hi = split_between_planes(d, alpha, planes, snap, additive=True)
        pos_lo, pos_hi = a_lo > 0, a_hi > 0
        inside = pos_lo & pos_hi  # strictly between two planes
        hi = np.minimum(idx + 1, len(planes) - 1)
        return [(idx, a_lo, pos_lo & ~pos_hi, 0, True), (hi, a_hi, pos_hi & ~pos_lo, 0, True),
                (idx, a_lo, inside, 1, True), (hi, a_hi, inside, 2, True)]
    raise ValueError(f"split must be 'linear', 'additive' or 'nearest', got {split!r}")


class _Source:
    """One sheet's pixels as flat arrays (views of the sheet where possible): straight
    colour ``(n, K)`` (float32 kept as it is: it is multiplied in float64, exactly as
    its float64 copy would be), alpha and disparity ``(n,)`` float64, and the map from
    a flat source index to canvas ``(row, column)``."""

    def __init__(self, sheet, canvas_width: int):
        if isinstance(sheet, Sheet):
            alpha = np.asarray(sheet.alpha, np.float64)
            self.h, self.w = alpha.shape
            self.origin = tuple(int(v) for v in sheet.origin)
            self.index = None
            self.alpha = alpha.reshape(-1)
            self.disparity = np.broadcast_to(np.asarray(sheet.disparity, np.float64),
                                             alpha.shape).reshape(-1)
            colour = _float_colour(sheet.colour)
        else:
            self.index = np.asarray(sheet.index, np.int64)
            self.alpha = np.asarray(sheet.alpha, np.float64).reshape(-1)
            self.disparity = np.asarray(sheet.disparity, np.float64).reshape(-1)
            colour = _float_colour(sheet.colour)
        self.colour = colour.reshape(-1, colour.shape[-1])
        self.canvas_width = canvas_width

    def rows_cols(self, src: np.ndarray):
        """Canvas rows and columns of the source pixels ``src``."""
        if self.index is not None:
            return np.divmod(self.index[src], self.canvas_width)
        r, c = np.divmod(src, self.w)
        return r + self.origin[0], c + self.origin[1]

    def canvas_index(self, src: np.ndarray) -> np.ndarray:
        """Flat canvas indices (row * canvas width + column) of the source pixels."""
        if self.index is not None:
            return self.index[src]
        r, c = self.rows_cols(src)
        return r.astype(np.int64) * self.canvas_width + c


def _layer_shares(shares, p: int, role_set):
    """``(entry, share)`` for each share (far to near) with pixels on the layer of plane
    ``p`` whose roles are ``role_set`` (see :func:`layers_from_sheets`)."""
    for j, share in enumerate(shares):
        bounds, role = share[3], share[4]
        if role in role_set and bounds[p] != bounds[p + 1]:
            yield j, share


def _float_colour(colour) -> np.ndarray:
    c = np.asarray(colour)
    return c if c.dtype in (np.float32, np.float64) else c.astype(np.float64)


def _slab_weights(members, shares, sources, trans: np.ndarray) -> dict:
    """The weight of each share on the layers of one slab (see :func:`layers_from_sheets`):
    ``{(plane, share entry): float32 array}``, the transmission of the nearer sheets'
    content in the slab at the share's pixels, ``prod (1 - alpha_t)`` over the sheets
    ``t`` after its own that have a share in the slab there (a sheet's alpha counted once
    per pixel, however many of the slab's planes it reaches; a sheet's pixels are
    distinct). ``members``: the slab's layers ``(plane, roles)``; ``trans``: a
    canvas-sized float32 array of ones, left as ones. Memory: 4 B per share of the slab,
    and one sheet's canvas indices at a time."""
    entries: dict = {}  # sheet -> [(plane, entry, source pixels)]
    for p, role_set in members:
        for j, (si, srt, _, bounds, _, _) in _layer_shares(shares, p, role_set):
            entries.setdefault(si, []).append((p, j, srt[bounds[p]:bounds[p + 1]]))
    weights = {}
    for si in sorted(entries, reverse=True):  # near to far
        # every share of the sheet reads the transmission before the sheet changes it;
        # the shares of one pixel then write the same value
        seen = []
        for p, j, sel in entries[si]:
            px = sources[si].canvas_index(sel)
            weights[p, j] = trans[px]
            seen.append((px, sel, weights[p, j]))
        for px, sel, w in seen:
            trans[px] = w * (1.0 - np.take(sources[si].alpha, sel)).astype(np.float32)
        del seen
    for si, found in entries.items():
        for _, _, sel in found:
            trans[sources[si].canvas_index(sel)] = 1.0
    return weights


def layers_from_sheets(sheets, planes, height: int, width: int, margin: int = 0,
                       split: str = "linear", snap: float = 0.0, slab: float = 0.0) -> MPI:
    """Cut sheets (given far to near) into planes and combine them into an MPI.

    ``planes``: the plane disparities (sorted), or their :class:`LayerPlan` (which then
    gives the split and the slabs: ``split`` and ``slab`` are not read). ``sheets`` holds :class:`Sheet` (dense boxes) or :class:`Pixels` (sparse lists).
    Each pixel is shared between its two neighbouring planes by
    :func:`split_between_planes` (``split="linear"``) or goes wholly to the nearest plane
    (``split="nearest"``); ``snap`` (disparity) is passed on to the split. On each plane
    the sheets are combined with "over", later (nearer) sheets on top:
    ``L = L (1 - cover) + premult``, in float32. With ``split="additive"`` the layers of
    a slab are summed by the compositor, so there the nearer sheets hide a farther one
    on every plane of the slab: each share is weighted by ``prod (1 - alpha_t)`` over
    the nearer sheets with content in the slab at its pixel (:func:`_slab_weights`) and
    the layer is the sum, which on one plane is that "over". Only pixels with alpha > 0
    are touched.

    Memory: one canvas-sized float32 plane, and per share of a pixel 12 B (its source
    index and share alpha, grouped by plane with a stable counting sort); with the
    additive split one more canvas-sized float32 array and 4 B per share of the slab
    being laid; the colour is read from the sheets plane by plane. A layer is stored as
    its occupied :data:`TILE_PX` tiles where they cover at most :data:`TILED_FILL_MAX` of its box.
    """
    plan = planes if isinstance(planes, LayerPlan) else plan_layers(planes, split, slab)
    planes, split, n_planes = plan.planes, plan.split, plan.plane_count
    hc, wc = height + 2 * margin, width + 2 * margin
    T = TILE_PX
    nty, ntx = -(-hc // T), -(-wc // T)
    plane_dtype = np.int16 if n_planes < (1 << 15) else np.int64  # radix sort when 16 bit
    # For every sheet and each of its shares: the source pixels with share alpha > 0,
    # grouped by plane (stable: in source order within a plane)
    sources, shares, cmax, K = [], [], [], None
    for sh in sheets:
        src = _Source(sh, wc)
        if K is None:
            K = src.colour.shape[1]
        elif src.colour.shape[1] != K:
            raise ValueError("all sheets must have the same colour channels")
        sources.append(src)
        idx_dtype = np.int32 if src.alpha.size < (1 << 31) else np.int64
        parts = None
        for k0 in range(0, max(src.alpha.size, 1), SPLIT_CHUNK_PX):
            kc = np.flatnonzero(src.alpha[k0:k0 + SPLIT_CHUNK_PX] > 0) + k0
            got = _share_parts(split, src.disparity[kc], src.alpha[kc], planes, snap)
            if parts is None:
                parts = [([], [], [], role, cover) for _, _, _, role, cover in got]
            anyp = np.zeros(kc.size, bool)
            for (index, a, m, _, _), (s_l, p_l, a_l, _, _) in zip(got, parts):
                anyp |= m
                s_l.append(kc[m].astype(idx_dtype))
                p_l.append(index[m].astype(plane_dtype))
                a_l.append(a[m])
            if anyp.any():
                used = kc[anyp]
                cmax.append([src.colour[used, k].max() for k in range(K)])
        for s_l, p_l, a_l, role, cover in parts:
            s_all, p_all, a_all = np.concatenate(s_l), np.concatenate(p_l), np.concatenate(a_l)
            order = np.argsort(p_all, kind="stable")
            bounds = np.concatenate([[0], np.cumsum(np.bincount(p_all, minlength=n_planes))])
            shares.append((len(sources) - 1, s_all[order], a_all[order], bounds, role, cover))
            del s_all, p_all, a_all, order
    K = 3 if K is None else K
    mpi = MPI(height, width, margin)
    mpi.colour_max = (np.max(cmax, axis=0).astype(np.float32) if cmax
                      else np.zeros(K, np.float32))
    tile_slot = np.full(nty * ntx, -1, np.int64)

    def layer_parts(p, role_set):
        """Every share on the layer of plane ``p`` and ``role_set``, far to near:
        ``(sheet, source pixels, share alpha, cover_is_alpha, rows, cols, tiles,
        share entry)``."""
        parts = []
        for j, (si, srt, a, bounds, _, cover_is_alpha) in _layer_shares(shares, p, role_set):
            s0, s1 = bounds[p], bounds[p + 1]
            sel = srt[s0:s1]
            r, c = sources[si].rows_cols(sel)
            parts.append((si, sel, a[s0:s1], cover_is_alpha, r, c, (r // T) * ntx + c // T,
                          j))
        return parts

    # the layers slab by slab (without the additive split: one slab, None), plane by
    # plane inside a slab. The layers of one slab are summed by the compositor, so a
    # nearer sheet hides a farther one on every plane of the slab (by its whole alpha),
    # not only on its own plane: each share is weighted by the transmission of the
    # nearer sheets' content in the same slab at its pixel (:func:`_slab_weights`), and
    # the layer is their sum. On one plane that is "over" with the whole alpha as the
    # cover; across the planes of a slab it keeps an opaque pixel from counting twice
    # (two sheets of one pixel on two planes of one slab gave a coverage up to 2).
    trans = np.ones(hc * wc, np.float32) if split == "additive" else None
    layers = []
    for slab_id, members in plan.slabs:
        weights = (_slab_weights(members, shares, sources, trans)
                   if trans is not None else None)
        for p, rs in members:
            d_p = planes[p]
            parts = layer_parts(p, rs)
            if not parts:
                continue
            if not np.isfinite(d_p) or d_p < 0:
                raise ValueError(f"layer disparity must be finite and >= 0, got {d_p}")
            r0 = min(int(q[4].min()) for q in parts)
            r1 = max(int(q[4].max()) for q in parts) + 1
            c0 = min(int(q[5].min()) for q in parts)
            c1 = max(int(q[5].max()) for q in parts) + 1
            occupied = np.zeros(nty * ntx, bool)
            for q in parts:
                occupied[q[6]] = True
            ids = np.flatnonzero(occupied)
            dense = ids.size * T * T > TILED_FILL_MAX * (r1 - r0) * (c1 - c0)
            # the layer's own storage, written directly: the box, or its occupied tiles
            if dense:
                data = np.zeros((r1 - r0, c1 - c0, K + 1), np.float32)
            else:
                data = np.zeros((ids.size, T, T, K + 1), np.float32)
                tile_slot[ids] = np.arange(ids.size)
            flat = data.reshape(-1, K + 1)
            rows16 = flat.view(np.complex128).reshape(-1) if K + 1 == 4 else None
            for si, sel, a_s, cover_is_alpha, r, c, tile, entry in parts:  # far to near
                src = sources[si]
                if dense:
                    px = (r - r0) * (c1 - c0) + (c - c0)
                else:
                    px = tile_slot[tile] * (T * T) + (r % T) * T + c % T
                # premultiplied in float64, then float32 (np.take: a row gather several
                # times faster than fancy indexing)
                col = np.take(src.colour, sel, axis=0)
                premult = np.empty((sel.size, K + 1))
                np.multiply(col[:, :3], a_s[:, None], out=premult[:, :3])
                premult[:, 3] = a_s
                np.multiply(col[:, 3:], a_s[:, None], out=premult[:, 4:])
                cur = np.take(flat, px, axis=0)
                if weights is not None:  # the sum, each share behind the slab's nearer ones
                    premult *= weights.pop((p, entry))[:, None]
                else:  # "over" on this plane
                    cover = np.take(src.alpha, sel) if cover_is_alpha else a_s
                    cur *= (1.0 - cover).astype(np.float32)[:, None]
                cur += premult.astype(np.float32)
                if rows16 is not None:  # 16 B rows: one complex128 each, a 1-D scatter
                    rows16[px] = cur.view(np.complex128).reshape(-1)
                else:
                    flat[px] = cur
            if dense:
                layers.append(Layer(float(d_p), data, r0, c0, slab_id))
            else:
                tile_slot[ids] = -1
                keys = np.stack(np.divmod(ids, ntx), axis=1)
                layers.append(Layer(float(d_p), None, r0, c0, slab_id, (keys, data),
                                    (r1 - r0, c1 - c0, K + 1)))
    layers.sort(key=lambda l: (-1 if l.group is None else l.group, l.disparity))
    mpi.layers = layers
    return mpi


def save_mpi(mpi: MPI, path) -> None:
    """Write an MPI to a ``.npz`` file (atomically): sizes, disparities, boxes, layers and
    the colour bound (:attr:`MPI.colour_max`) when known."""
    from mpib_validate.runtime.io.atomic import atomic_path

    arrays = {"meta": np.array([mpi.height, mpi.width, mpi.margin, len(mpi.layers)], np.int64)}
    if mpi.colour_max is not None:
        arrays["colour_max"] = np.asarray(mpi.colour_max, np.float32)
    for i, l in enumerate(mpi.layers):
        arrays[f"rgba{i}"] = l.rgba
        arrays[f"where{i}"] = np.array([l.disparity, l.y0, l.x0,
                                        -1 if l.group is None else l.group], np.float64)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def load_mpi(path) -> MPI:
    """Read an MPI written by :func:`save_mpi`."""
    with np.load(path) as z:
        h, w, margin, n = (int(v) for v in z["meta"])
        mpi = MPI(h, w, margin)
        if "colour_max" in z.files:
            mpi.colour_max = z["colour_max"]
        for i in range(n):
            where = z[f"where{i}"]
            d, y0, x0 = where[:3]
            group = int(where[3]) if len(where) > 3 and where[3] >= 0 else None
            mpi.layers.append(Layer(float(d), z[f"rgba{i}"], int(y0), int(x0), group))
    return mpi
