"""What a job will cost, estimated before it starts, and the limit it is checked against.

A colour image passed as depth, a random depth map, an f/0.01 lens or a billion
samples do not fail: they run for minutes and then exhaust the memory. Each function
here estimates the peak memory of one job from its inputs alone (sizes, the disparity
values, the camera, the sample count), cheaply, so that the command line can refuse
past a limit the user can raise (``--max-memory-gb``) with one line saying what is
large, before any work or output.

Refocusing (:func:`refocus_estimate`, :func:`estimate_request`) reads the layer
builder's plan and follows what ``composite`` does:

- planes and layers: the builder's :class:`~mpib_validate.runtime.layers.mpi.LayerPlan`
  of the disparity map (:func:`~mpib_validate.runtime.layers.passes.layer_plan`: its
  planes are spaced ``2 tol / A``, so the count grows with ``A`` times the disparity
  range: a colour file read as depth, ``d = 1/Z`` up to 1/min(colour), gives
  thousands), with the planes each tile and block reaches and the storage tiles of each
  plane as the plan gives them (:meth:`~mpib_validate.runtime.layers.mpi.LayerPlan.tile_area`:
  a plane straddling two slabs holds two layers);
- layers: each plane stores premultiplied RGBA float32 (16 B) over the bounding box
  of its content, or over its occupied 32 px tiles where those cover at most
  ``TILED_FILL_MAX`` of the box (a thin band of a smooth depth). The boxes are taken on
  blocks of at most 256 x 256 per image and grown by the occlusion reach
  ``A (d_near - d_far)`` of the 4-neighbour depth jumps in them (the hidden-background
  fill, which adds the block grown by its reach to a tiled plane);
- compositing: each layer padded by its kernel radius ``R = ceil(A |d - d_f|) + 1``
  and blurred by a float32 FFT of its four channels (a tiled layer: in batches of
  windows, :data:`TILED_BLUR_BYTES` each), on up to ``composite.blur_threads()``
  threads at once (counted as the largest sum over that many consecutive layers), with
  :data:`HELD_OUTPUTS` more blurred outputs waiting for their "over", plus the kernel,
  the accumulators and the kernel cache;
- the per-pixel working sets of the layer builder and of the output writers;
- a layered input (one view layer per depth group,
  :mod:`~mpib_validate.runtime.layers.layered`): the arrays its passes hold (every
  group's colour, alpha and depth, :func:`held_bytes`), the planes planned over every
  group's content, the farthest group built as a single-pass input (the only one with
  edges and a fill), and per nearer group its disparity, its dense sheet and its
  content's shares of the cut.

The byte counts per pixel are measured (``tests/test_budget.py`` checks the estimate
against the peak resident memory of real runs), not derived. Tracing
(:func:`trace_estimate`) counts the sample set, the per-pixel accumulators and maps,
and the textures (Mitsuba and Cycles hold no sample set: they loop over samples).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

GIB = float(1 << 30)

#: Default limit: this fraction of the machine's memory (or of the cgroup's limit).
DEFAULT_FRACTION = 0.5

#: Bytes per pixel of the layer builder, in its two phases (peak resident memory above
#: the inputs, fresh processes at 512^2 to 1500x1000, 2 cores). Finding the edges and
#: filling behind them (the push-pull pyramid in float64, the unmixing): 268 B/px where
#: the depth has jumps (cards, a tilted floor), plus 150 B/px per edge pixel (random
#: depth, 99 % edge pixels: 405 to 470 B/px); 50 B/px for a smooth depth with no jump
#: (no fill). Cutting the sheets into planes, beside the layers it makes: the sheets
#: and each pixel's shares (a 4-byte index and an 8-byte alpha, about two per pixel),
#: 120 B/px with jumps plus 100 B/px per edge pixel (random: 212 to 264 B/px), 40 B/px
#: without.
BUILD_BYTES_PER_PX = 270
BUILD_BYTES_PER_EDGE_PX = 150
BUILD_SMOOTH_BYTES_PER_PX = 50
CUT_BYTES_PER_PX = 120
CUT_BYTES_PER_EDGE_PX = 100
CUT_SMOOTH_BYTES_PER_PX = 40
#: Bytes per padded pixel of one layer's FFT blur (float32 input, the complex64 half
#: spectrum of four channels, its float32 inverse and the output: 4 x 16 B).
FFT_BYTES_PER_PX = 64
#: Blurred outputs (16 B/px) held besides those being computed: the one being laid
#: and ``composite.HELD_JOBS`` finished ahead of it.
HELD_OUTPUTS = 2
#: Working set of one blur job of a layer stored as tiles: a batch of
#: :data:`mpib_validate.runtime.compositor.kernels.BATCH_BYTES` of float32 windows (the windows
#: at the transform's size, spectrum, inverse and result: about four times that),
#: whatever the layer's box; a held output of one is at most a batch.
TILED_BLUR_BYTES = 4 * (32 << 20)
TILED_OUTPUT_BYTES = 32 << 20  # kernels.BATCH_BYTES (not imported: budget loads light)
#: Bytes per pixel of writing the result (premultiplied copy, EXR channels, sRGB PNG).
WRITE_BYTES_PER_PX = 110
#: Bytes per pixel of the inputs kept during the work (colour float32, depth and
#: disparity float64).
INPUT_BYTES_PER_PX = 28
#: Bytes per pixel of content (alpha > 0) of a layered input's nearer groups while the
#: sheets are cut, beside the layers it makes: its value in the plan's disparities (8 B)
#: and its shares (12 B each, at most two). Measured (numpy's own allocations, traced,
#: 1536x1152, 5 groups): the cut's peak above its start, less the layers, grows 7 B/px
#: from 0.36 to 1.65 frames of nearer content; 2 groups, 0.07 to 0.45 frames: 26 B/px.
LAYERED_CUT_BYTES_PER_PX = 24
#: Bytes per sample of a lens sample set while it is made (Sobol points, the
#: concentric map's temporaries, the kept float64 arrays).
SAMPLE_BYTES = 160
#: Bytes per pixel of the ray tracer (float64 accumulators, pinhole maps, result and
#: its EXR channels) and per pixel and card (hit alpha, disparity, colour).
TRACE_BYTES_PER_PX = 160
TRACE_BYTES_PER_PX_CARD = 25
#: Bytes per texel of a card texture (float32 RGBA, its premultiplied flat copy).
TEXEL_BYTES = 48
#: One numpy tile of the tracer (2^18 pixels), per card.
TRACE_TILE_BYTES_PER_CARD = 16 << 20
#: Mitsuba and Cycles themselves, beyond the per-pixel buffers (measured: Mitsuba's
#: llvm_ad_rgb variant peaks ~105-125 MB above its start at 64^2 to 256^2 pixels and
#: 256 to 512 spp; its samples are not held at once).
RENDERER_BYTES = 256 << 20
#: Bytes per pixel of a generated scene (textures of the frame plus margin, for each
#: of up to four cards, and the generator's float64 noise fields); measured 363 to
#: 490 B/px at 1024 and 512 px (hard cases with wide margins take the most).
GENERATE_BYTES_PER_PX = 700
#: Dr.Jit and the tracer's pixel indices are 32-bit.
MAX_PIXELS = (1 << 31) - 1


class BudgetError(ValueError):
    """A job whose estimated cost is past the limit; the message names the option."""


@dataclass
class Estimate:
    """An estimated peak memory and its parts (bytes), with what drives it."""

    what: str
    parts: dict = field(default_factory=dict)
    planes: int | None = None
    largest_radius_px: float | None = None
    peak: int | None = None  # when the parts are not simply added

    @property
    def bytes(self) -> int:
        return int(self.peak if self.peak is not None else sum(self.parts.values()))

    def largest_part(self) -> str:
        return max(self.parts, key=self.parts.get) if self.parts else "total"

    def describe(self) -> str:
        bits = []
        if self.planes is not None:
            bits.append(f"about {self.planes} planes")
        if self.largest_radius_px is not None:
            r = self.largest_radius_px
            bits.append(f"largest blur radius {r:.1f} px" if r < 1e7 else
                        f"largest blur radius {r:.3g} px")
        bits.append(f"estimated memory {format_bytes(self.bytes)}")
        return ", ".join(bits)


def format_bytes(n: float) -> str:
    try:
        n = float(n)
    except OverflowError:
        n = math.inf
    if n >= 1 << 60:
        return "over a million TiB"
    if n >= 1 << 40:
        return f"{n / (1 << 40):.1f} TiB"
    if n >= 1 << 30:
        return f"{n / GIB:.1f} GB"
    return f"{n / (1 << 20):.0f} MB" if n >= 10 << 20 else f"{n / (1 << 20):.1f} MB"


def machine_memory() -> int:
    """Physical memory in bytes, or the cgroup's memory limit when that is smaller."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        total = 8 << 30
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as fh:
                text = fh.read().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
    return int(total)


def memory_limit(gb: float | None = None) -> int:
    """The limit in bytes: ``gb`` GiB if given, else :data:`DEFAULT_FRACTION` of
    :func:`machine_memory`."""
    if gb is None:
        return int(DEFAULT_FRACTION * machine_memory())
    return int(gb * GIB)


def check(estimate: Estimate, limit: int, option: str = "--max-memory-gb") -> Estimate:
    """Raise :class:`BudgetError` if ``estimate`` is past ``limit`` bytes."""
    if estimate.bytes > limit:
        part = estimate.largest_part()
        raise BudgetError(
            f"{estimate.what} would need about {format_bytes(estimate.bytes)} of memory "
            f"({estimate.describe()}; largest part: {part} "
            f"{format_bytes(estimate.parts.get(part, estimate.bytes))}), over the limit of "
            f"{format_bytes(limit)}; raise it with {option} if this machine has the memory")
    return estimate


def check_pixels(width: int, height: int, what: str) -> None:
    """Refuse images of more pixels than 32-bit indices reach."""
    if int(width) * int(height) > MAX_PIXELS:
        raise BudgetError(f"{what}: {width}x{height} is {int(width) * int(height):,} pixels; "
                          f"the renderers index pixels with 32-bit integers (at most "
                          f"{MAX_PIXELS:,})")


# --------------------------------------------------------------------------------------
# Refocusing


def _blocks(D: np.ndarray, side: int = 256, content: np.ndarray | None = None):
    """Per-block minimum and maximum of ``D`` on a grid of at most ``side x side``
    blocks; returns ``(lo, hi, block)`` with the block size in pixels. ``content``:
    over those pixels only (a block with none: ``lo = inf``, ``hi = -inf``)."""
    from mpib_validate.runtime.layers.mpi import block_ranges

    b = max(1, math.ceil(max(D.shape) / side))
    return (*block_ranges(D, b, content), b)


def _reached(plan, lo, hi):
    """:meth:`LayerPlan.reached` of block ranges, with a block of no content (``lo >
    hi``) reaching none (``(n, n - 1)``: nothing in :func:`_presence_extent`'s counts)."""
    n = plan.plane_count
    s_lo, s_hi = plan.reached(lo, hi)
    empty = lo > hi
    return np.where(empty, n, s_lo), np.where(empty, n - 1, s_hi)


def _presence_extent(s_lo: np.ndarray, s_hi: np.ndarray, n: int, axis: int):
    """First and last block row (axis 0) or column (axis 1) holding each of ``n``
    planes, given each block's plane interval ``[s_lo, s_hi]``."""
    lines = s_lo.shape[axis]
    first = np.full(n, lines, np.int64)
    last = np.full(n, -1, np.int64)
    for i in range(lines):
        lo = np.take(s_lo, i, axis=axis)
        hi = np.take(s_hi, i, axis=axis)
        diff = np.bincount(lo, minlength=n + 1) - np.bincount(hi + 1, minlength=n + 1)
        here = np.cumsum(diff[:n]) > 0
        first = np.where(here & (first == lines), i, first)
        last = np.where(here, i, last)
    return first, last


def _plane_boxes(D: np.ndarray, plan, A: float, jump: float, nearer=()):
    """Estimated ``(height, width)`` of each plane's content box (see the module
    docstring) for the builder's ``plan``
    (:class:`~mpib_validate.runtime.layers.mpi.LayerPlan`) of the disparities ``D``, and
    the pixels each plane stores: its tile area (:meth:`LayerPlan.tile_area`) where a
    layer is kept as tiles (:data:`mpi.TILED_FILL_MAX` of its box or less) and nothing
    grows it (the hidden-background fill behind a depth edge, whose extent is known
    only as a box), else its box.

    ``nearer``: the nearer groups of a layered input, ``(disparity (H, W), content (H,
    W) bool)`` each, whose sheets are cut into the same planes without a fill (``D`` is
    then the farthest group's, the only one filled): a plane's box is the bounding box
    of every group's content on it, its tiles the sum of each group's (an upper bound
    where two groups share a tile of one plane)."""
    from mpib_validate.runtime.layers.mpi import TILED_FILL_MAX

    H, W = D.shape
    n = plan.plane_count
    lo, hi, b = _blocks(D)
    s_lo, s_hi = plan.reached(lo, hi)
    # hidden background behind depth edges: the fill reaches A (d_near - d_far) from
    # each 4-neighbour jump larger than ``jump`` (the layer builder's edges), so the
    # planes of a block holding such a jump may grow by that much (a smooth gradient,
    # however steep across a block, has no jump and grows nothing)
    # (growth past the frame is clipped anyway)
    reach = np.minimum(A * _block_jumps(D, jump, b), 2.0 * max(H, W))
    grow = np.zeros(n)
    top = float(reach.max()) if reach.size else 0.0
    level = 1.0
    while level <= top:
        sel = reach >= level
        diff = (np.bincount(s_lo[sel], minlength=n + 1)
                - np.bincount(s_hi[sel] + 1, minlength=n + 1))
        grow = np.where(np.cumsum(diff[:n]) > 0, 2.0 * level, grow)
        level *= 2.0
    g = np.ceil(np.minimum(grow, top)).astype(np.int64)
    # each plane's extent (block lines, grown by its reach): first and one past the last
    # pixel row and column, over the groups that reach it
    spans = []
    for axis, size in ((0, H), (1, W)):
        first, last = _presence_extent(s_lo, s_hi, n, axis)
        on = last >= first
        start = np.where(on, first * b - g, np.iinfo(np.int64).max)
        end = np.where(on, (last + 1) * b + g, np.iinfo(np.int64).min)
        spans.append([start, end, on])
    for Dk, ck in nearer:
        k_lo, k_hi = _reached(plan, *_blocks(Dk, content=ck)[:2])
        for axis, span in enumerate(spans):
            first, last = _presence_extent(k_lo, k_hi, n, axis)
            on = last >= first
            span[0] = np.where(on, np.minimum(span[0], first * b), span[0])
            span[1] = np.where(on, np.maximum(span[1], (last + 1) * b), span[1])
            span[2] = span[2] | on
    (r_start, r_end, r_on), (c_start, c_end, c_on) = spans
    h = np.where(r_on, np.minimum(r_end - r_start, H), 0)
    w = np.where(c_on, np.minimum(c_end - c_start, W), 0)
    box = h.astype(np.float64) * w
    area, count = plan.tile_area(D)
    for Dk, ck in nearer:
        area = area + plan.tile_area(Dk, content=ck)[0]
    # the fill behind the jumps of a block lands on that block's planes, within its
    # reach: the block grown by it on every side
    sel = reach > 0
    fill = np.zeros(n)
    if sel.any():
        wt = np.minimum((b + 2.0 * reach[sel]) ** 2, float(H) * W)
        diff = (np.bincount(s_lo[sel], weights=wt, minlength=n + 1)
                - np.bincount(s_hi[sel] + 1, weights=wt, minlength=n + 1))
        fill = np.cumsum(diff[:n])
    # (a plane's two layers, where slabs split it, each take the box: an upper bound)
    held = area + fill
    stored = np.where(held <= TILED_FILL_MAX * box * count, held, box * count)
    return h, w, stored


def _block_jumps(D: np.ndarray, jump: float, b: int) -> np.ndarray:
    """Largest 4-neighbour disparity jump above ``jump`` touching each ``b x b`` block
    (the grid of :func:`_blocks`; 0 where none), one image row band at a time."""
    H, W = D.shape
    ny, nx = -(-H // b), -(-W // b)
    out = np.zeros((ny, nx))
    for by in range(ny):
        r0, r1 = by * b, min(H, by * b + b)
        band = D[max(r0 - 1, 0):min(r1 + 1, H)]  # with the rows above and below
        top = r0 - max(r0 - 1, 0)
        mag = np.zeros((band.shape[0], nx * b))
        dx = np.abs(np.diff(band, axis=1))
        dx = np.where(dx > jump, dx, 0.0)
        mag[:, :W - 1] = dx
        mag[:, 1:W] = np.maximum(mag[:, 1:W], dx)
        dy = np.abs(np.diff(band, axis=0))
        dy = np.where(dy > jump, dy, 0.0)
        mag[:-1, :W] = np.maximum(mag[:-1, :W], dy)
        mag[1:, :W] = np.maximum(mag[1:, :W], dy)
        own = mag[top:top + r1 - r0]
        out[by] = own.reshape(r1 - r0, nx, b).max(axis=(0, 2))
    return out


def _edge_fraction(D: np.ndarray, jump: float) -> float:
    """Fraction of pixels with a 4-neighbour more than ``jump`` away in disparity (the
    pixels the layer builder unmixes)."""
    from mpib_validate.runtime.layers.fill import jump_pixels

    return float(jump_pixels(D, jump).mean())


def _fast_len(n: int) -> int:
    from scipy import fft

    return fft.next_fast_len(int(n), real=True)


#: Radii are capped here for the arithmetic (any such blur is refused anyway).
_RADIUS_CAP = 1e9
#: Beyond this many planes their boxes are not estimated one by one: the layers are
#: counted at their bookkeeping cost per plane, plus every pixel once.
MAX_PLANES_PLACED = 1_000_000
PLANE_BYTES = 200


def _concurrent(works: list, threads: int) -> int:
    """The most working memory ``threads`` blurs may hold at once: the compositor runs
    the layers' jobs in order, so the largest sum over ``threads`` consecutive layers
    (a tiled layer's own batches are counted in its ``works`` entry)."""
    if not works:
        return 0
    k = min(threads, len(works))
    c = np.concatenate([[0], np.cumsum(np.asarray(works, np.float64))])
    return int(max(float((c[k:] - c[:-k]).max()), max(works)))


def _blur_bytes(h: int, w: int, rho: float, H: int, W: int, composite) -> tuple[int, int, int]:
    """Working set of blurring one layer whose content box is ``h x w`` (its own output
    included), the bytes of its output, and those of its kernel."""
    r = min(abs(rho), _RADIUS_CAP)
    R = int(math.ceil(r)) + 1
    oh, ow = min(h + 2 * R, H), min(w + 2 * R, W)
    if r < 0.5 / 1024:
        return 16 * oh * ow, 16 * oh * ow, 0
    taps = (2 * R + 1) ** 2
    if composite.reduce_above is not None and r > composite.reduce_above:
        s = int(math.ceil(r / composite.reduce_above))
        Rc = int(math.ceil(r / s)) + 1
        pad = (Rc + 2) * s
        ph, pw = oh + 2 * pad, ow + 2 * pad
        ch, cw = -(-oh // s) + 2 * Rc + 2, -(-ow // s) + 2 * Rc + 2
        work = (16 * ph * pw + 32 * ph * pw // s
                + FFT_BYTES_PER_PX * _fast_len(ch) * _fast_len(cw) + 16 * oh * ow)
        return work, 16 * oh * ow, 9 * (2 * Rc + 1) ** 2
    work = FFT_BYTES_PER_PX * _fast_len(oh + 2 * R) * _fast_len(ow + 2 * R) + 16 * oh * ow
    return work, 16 * oh * ow, 9 * taps


def estimate_request(request, threads: int | None = None) -> Estimate:
    """Estimated peak memory of :func:`mpib_validate.runtime.refocus.refocus` of a
    :class:`~mpib_validate.runtime.request.RefocusRequest` (:func:`refocus_estimate` of its
    disparity, ``A``, ``d_f`` and preset, with its background render if any; for a
    layered input, of its depth groups as the builder takes them, with the arrays the
    passes hold)."""
    from mpib_validate.runtime.layers.layered import group_layers
    from mpib_validate.runtime.layers.passes import passes_disparity

    passes = request.passes
    D = passes_disparity(passes, request.far_limit)
    groups = held = None
    if passes.groups is not None:
        groups = group_layers(passes.groups, request.far_limit, passes.depth_source)
        held = held_bytes(passes) + D.nbytes  # and the disparity the refocus derives
    return refocus_estimate(D, request.blur_parameter, request.focus_disparity,
                            request.preset, background=request.background is not None,
                            threads=threads, aperture=request.aperture, groups=groups,
                            held=held)


def held_bytes(passes) -> int:
    """Bytes of the arrays ``passes`` (:class:`mpib_validate.runtime.refocus.Passes`) hold,
    each counted once with whatever it is a view of (a layered input's group colour is
    a view of its RGBA)."""
    arrays = [passes.colour, passes.depth, passes.alpha, passes.disparity]
    arrays += [a for g in (passes.groups or ()) for a in g]
    bases = {}
    for a in arrays:
        while isinstance(a, np.ndarray) and isinstance(a.base, np.ndarray):
            a = a.base
        if isinstance(a, np.ndarray):
            bases[id(a)] = a.nbytes
    return int(sum(bases.values()))


def refocus_estimate(disparity: np.ndarray, blur_parameter: float, focus_disparity: float,
                     preset, background: bool = False,
                     threads: int | None = None, aperture=None, groups=None,
                     held: int | None = None) -> Estimate:
    """Estimated peak memory of ``refocus.refocus`` on a disparity map (1/scene-unit,
    0 = infinitely far) with the blur parameter ``A`` (px per unit disparity), focus
    ``d_f`` and a preset's settings (a :class:`~mpib_validate.runtime.presets.Preset`),
    blurring on ``threads`` threads (default: as many as the compositor uses here,
    ``composite.blur_threads()``). Costs a few passes over the disparity. ``aperture``:
    the lens's shape (``camera.Aperture``); its reach ``A extent`` (``extent = max(1,
    1/ratio)``, what the refocus builds and blurs with) stands for ``A``.

    ``groups``: a layered input's depth groups, far to near, ``(colour, alpha,
    disparity)`` as :func:`~mpib_validate.runtime.layers.layered.layers_from_layered_passes`
    takes them (:func:`~mpib_validate.runtime.layers.layered.group_layers`): the planes
    are then planned over every group's content, the farthest group is built (edges,
    fill) as a single-pass input and each nearer one adds its dense sheet (float64
    colour and alpha) and its content's shares of the cut
    (:data:`LAYERED_CUT_BYTES_PER_PX`).
    ``held``: bytes of the inputs the refocus keeps throughout (default
    :data:`INPUT_BYTES_PER_PX` per pixel: a single-pass colour and depth)."""
    from mpib_validate.runtime.compositor.composite import blur_threads
    from mpib_validate.runtime.compositor.kernels import KERNEL_CACHE_BYTES
    from mpib_validate.runtime.layers.passes import layer_plan

    threads = blur_threads() if threads is None else max(1, int(threads))
    D = np.asarray(disparity, np.float64)
    H, W = D.shape
    A = float(blur_parameter) * (1.0 if aperture is None else aperture.extent)
    p = preset
    px = H * W
    kept = INPUT_BYTES_PER_PX * px if held is None else int(held)
    nearer, extra_build, extra_cut = (), 0.0, 0.0
    values = D
    if groups is not None:
        from mpib_validate.runtime.layers.layered import far_group_opaque

        # the farthest group is the single-pass input; the nearer ones are sheets of
        # their content (alpha > 0), cut into the planes of every group's content
        D = np.asarray(groups[0][2], np.float64)
        nearer = [(np.asarray(g[2], np.float64), np.asarray(g[1]) > 0) for g in groups[1:]]
        values = np.concatenate([D.ravel()] + [Dk[ck] for Dk, ck in nearer])
        K = 3 if far_group_opaque(groups[0][1]) else 4  # colour channels of the sheets
        content = sum(int(np.count_nonzero(ck)) for _, ck in nearer)
        # the group disparities (8 B/px each) and, with a film channel, the farthest
        # group's colour and alpha copy (8 K B/px) through the whole build; the nearer
        # groups' dense sheets (colour 8 K, alpha 8 B/px) and their shares through the cut
        extra_build = (8 * len(groups) + (0 if K == 3 else 8 * K)) * px
        extra_cut = (extra_build + (8 * K + 8) * len(nearer) * px
                     + LAYERED_CUT_BYTES_PER_PX * content)
    # the builder's plan for these disparities (an upper bound: its content is a subset
    # of these values)
    plan = layer_plan(values, A, p.passes, exact=False, max_planes=MAX_PLANES_PLACED)
    n_planes = plan.plane_count
    largest = float(A * max(abs(float(values.max()) - focus_disparity),
                            abs(float(values.min()) - focus_disparity)))
    del values
    if plan.planes is None:  # too many to place: bookkeeping, one full-frame blur
        rho = np.array([largest])
        hs, ws = np.array([H]), np.array([W])
        as_tiles = np.array([False])
        layers = PLANE_BYTES * n_planes + 16 * px
    else:
        rho = A * (plan.planes - focus_disparity)
        hs, ws, tiled = _plane_boxes(D, plan, A, p.passes.jump_px / A, nearer)
        layers = int(16 * np.sum(tiled)
                     ) + PLANE_BYTES * n_planes
        as_tiles = tiled < hs.astype(np.float64) * ws
    works, held, kern = [], 0, 0
    kernels_total = 0
    for h, w, r, t in zip(hs, ws, rho, as_tiles):
        if h == 0:
            continue
        work, out, kb = _blur_bytes(int(h), int(w), float(r), H, W, p.composite)
        if t and p.composite.tiles and p.composite.crop:
            # batches of one layer may run on every thread at once
            work = min(work, threads * TILED_BLUR_BYTES)
            out = min(out, TILED_OUTPUT_BYTES)
        works.append(work + kb)
        held = max(held, out)
        kern = max(kern, kb)
        kernels_total += kb
    acc = 32 * px if p.subapertures == 1 else 64 * px
    if p.composite.chain_px is not None:
        # composite._Chain: the chain's own sum and its last slab (16 B/px each), two
        # slab footprints, the chain's summed footprint and its reach-weighted sum
        # (float32, 4 B/px each) and the weights of a push over the slab's box: the
        # depth weight (float32), and while it is computed the opaque mask, its
        # column distances (two int16), their padded float32 copy and a bounded part of
        # the ring's pixels: up to 18 B/px (traced, a busy 2000x1336 mask)
        acc += (16 + 16 + 16 + 18) * px
    edge = _edge_fraction(D, p.passes.jump_px / A)
    if edge > 0:  # jumps: the hidden background is filled
        edges_phase = (BUILD_BYTES_PER_PX + BUILD_BYTES_PER_EDGE_PX * edge) * px
        cut = (CUT_BYTES_PER_PX + CUT_BYTES_PER_EDGE_PX * edge) * px
    else:
        edges_phase, cut = BUILD_SMOOTH_BYTES_PER_PX * px, CUT_SMOOTH_BYTES_PER_PX * px
    edges_phase, cut = edges_phase + extra_build, cut + extra_cut
    parts = {
        "inputs": kept + (16 if background else 0) * px,
        "layers": layers,
        "layer building": int(max(edges_phase, cut)),
        "blurs": _concurrent(works, threads) + HELD_OUTPUTS * held,
        "kernel cache": min(KERNEL_CACHE_BYTES, kernels_total),
        "accumulators": acc,
        "writing": WRITE_BYTES_PER_PX * px,
    }
    phases = (edges_phase, cut + layers,
              layers + parts["blurs"] + parts["kernel cache"] + acc,
              parts["writing"] + 16 * px)
    return Estimate(f"refocusing {W}x{H} ({p.name})", parts, planes=int(n_planes),
                    largest_radius_px=largest, peak=parts["inputs"] + max(phases))


#: The least any refocus of a picture needs per pixel, whatever its disparity: the
#: inputs it keeps and its writing phase (:func:`refocus_estimate`'s ``inputs`` and
#: ``writing`` parts with the 16 B/px result they hold).
REFOCUS_FLOOR_BYTES_PER_PX = INPUT_BYTES_PER_PX + WRITE_BYTES_PER_PX + 16


def reading_estimate(what: str, reads: dict, pixels: int) -> Estimate:
    """The memory a refocus needs before its disparity is known, from the inputs'
    headers: decoding the inputs (``reads``: label -> peak bytes, each held while the
    next is read, so summed) and at least :data:`REFOCUS_FLOOR_BYTES_PER_PX` per pixel
    for the refocus itself; the larger of the two. Checked before any pixel is decoded,
    so that a small file declaring a huge image is refused at the size it declares."""
    reads = {k: int(v) for k, v in reads.items()}
    floor = REFOCUS_FLOOR_BYTES_PER_PX * int(pixels)
    return Estimate(what, {**reads, "refocusing (at the least)": floor},
                    peak=max(sum(reads.values()), floor))


# --------------------------------------------------------------------------------------
# Rendering and generating


def samples_estimate(aperture: str, spp: int, grid_side: int) -> tuple[int, int]:
    """``(sample count, bytes while the set is made)`` of a tracer sample set."""
    if aperture == "grid":
        n = int(round(math.pi / 4 * grid_side * grid_side)) + 1
        return n, 40 * int(grid_side) ** 2 + SAMPLE_BYTES * n
    return int(spp), SAMPLE_BYTES * int(spp)


def trace_estimate(width: int, height: int, cards: int, texels: int, samples_bytes: int,
                   engine: str = "trace") -> Estimate:
    """Estimated peak memory of ``mpib render``: the sample set, the per-pixel
    accumulators and maps, the textures; for Mitsuba and Cycles their own start-up."""
    px = int(width) * int(height)
    parts = {
        "textures": TEXEL_BYTES * int(texels),
        "per-pixel buffers": (TRACE_BYTES_PER_PX + TRACE_BYTES_PER_PX_CARD * cards) * px,
    }
    if engine == "trace":
        parts["sample set"] = int(samples_bytes)
        parts["tracer tiles"] = TRACE_TILE_BYTES_PER_CARD * max(cards, 1) * min(1.0, px / (1 << 18))
    else:
        parts["renderer"] = RENDERER_BYTES
    parts = {k: int(v) for k, v in parts.items()}
    return Estimate(f"rendering {width}x{height} with {engine}", parts)


def generate_estimate(width: int, height: int) -> Estimate:
    """Estimated peak memory of generating a scene of ``width x height``."""
    return Estimate(f"generating a {width}x{height} scene",
                    {"textures": GENERATE_BYTES_PER_PX * int(width) * int(height)})
