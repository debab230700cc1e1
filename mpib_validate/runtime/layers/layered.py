"""From layered passes (one view layer per depth group) to an MPI.

Blender renders each depth group in its own view layer with the film transparent, the
other groups' collections *Indirect Only* (:mod:`mpib_validate.runtime.blender.layers`). Each
group layer then holds, premultiplied, exactly what the group's objects contribute:
colour ``P_k`` (linear radiance times coverage), Cycles' own coverage ``a_k`` at its
silhouettes, and its own depth, including everything that nearer groups hide. The
group layers composited with "over", far to near,

    ``C = P_n + (1 - a_n) (P_n-1 + (1 - a_n-1) (... P_0))``,

give back the single-pass Combined render (to the render noise).

The MPI is built with the same machinery as :func:`mpib_validate.runtime.layers.passes.layers_from_passes`:

- the farthest group is a single-pass input of its own (film alpha as an extra channel,
  as :func:`mpib_validate.runtime.refocus.refocus` does for a transparent film): its internal
  depth edges (a wall behind a ground plane, a brow over an eye socket) are unmixed and
  the hidden surface behind them filled (:mod:`mpib_validate.runtime.layers.fill`). That is the only
  place a fill is needed: behind every nearer group lies a farther group's rendered
  content, or the world (transparent, infinitely far: film alpha 0).
- each nearer group is one :class:`~mpib_validate.runtime.layers.mpi.Sheet` with its straight colour
  ``P_k / a_k`` and alpha ``a_k``: its pixels with ``a_k < 1`` at silhouettes are exact
  coverage, so nothing is unmixed there. A nearer group's own internal depth edges are
  not unmixed (a pixel goes whole to its depth), as in the official pipeline.
- planes and split: :func:`mpib_validate.runtime.layers.passes.mpi_from_sheets` (adaptive planes over
  every group's content, the settings' split).

Depth at a group's partly covered pixel: Cycles writes the Z of the pixel centre's
sample; where that sample missed the group (``Z >= far_limit`` but ``a_k > 0``), the
pixel takes the disparity of the group's nearest pixel with a finite depth.
"""

from __future__ import annotations

import time

import numpy as np

from mpib_validate.runtime.layers.mpi import MPI, Sheet
from mpib_validate.runtime.layers.passes import (DEFAULT_FAR_LIMIT, PassError, PassesInfo, PassesSettings, mpi_from_sheets, sheets_from_passes)

#: A farthest group whose alpha is at least this everywhere is opaque (no film channel).
OPAQUE_ALPHA = 1.0 - 1e-6


def group_disparity(depth: np.ndarray, alpha: np.ndarray, far_limit: float = DEFAULT_FAR_LIMIT,
                    source: str = "depth") -> np.ndarray:
    """Disparity ``1/Z`` (1/scene-unit) of one group layer: 0 where the group has no
    content (``alpha == 0``); where it has content but its Z is at infinity (the pixel
    centre's sample missed it), the disparity of its nearest pixel with a finite Z.
    Raises :class:`PassError` naming ``source`` for NaN or ``Z <= 0`` where the group
    has content, and for content without any finite depth."""
    from scipy import ndimage

    Z = np.asarray(depth, np.float64)
    a = np.asarray(alpha, np.float64)
    has = a > 0
    bad = has & (np.isnan(Z) | (Z <= 0))
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise PassError(f"{source}: depth must be a number > 0 where the layer has content; "
                        f"{int(bad.sum())} pixel(s) are not (first at row {y}, column {x})")
    finite = has & (Z < far_limit)
    if has.any() and not finite.any():
        raise PassError(f"{source}: the layer has content but no finite depth; was the Z "
                        f"pass rendered?")
    D = np.where(finite, 1.0 / np.where(finite, Z, 1.0), 0.0)
    missed = has & ~finite
    if missed.any():
        _, (iy, ix) = ndimage.distance_transform_edt(~finite, return_indices=True)
        D = np.where(missed, D[iy, ix], D)
    return D


def group_layers(groups, far_limit: float = DEFAULT_FAR_LIMIT, source: str = "depth") -> list:
    """The depth groups of a layered input (``Passes.groups`` of
    :func:`mpib_validate.runtime.refocus.load_layered_passes`: far to near, ``(colour,
    alpha, depth[, coverage])``) as :func:`layers_from_layered_passes` takes them:
    ``(colour, alpha, disparity)``, the disparity :func:`group_disparity` of the depth
    over the group's own coverage (``coverage`` where given: the farthest group with the
    world added in, opaque, whose world pixels are at disparity 0)."""
    return [(g[0], g[1], group_disparity(g[2], g[-1] if len(g) > 3 else g[1], far_limit,
                                         f"{source} group {k}"))
            for k, g in enumerate(groups)]


def far_group_opaque(alpha: np.ndarray) -> bool:
    """Whether the farthest group's ``alpha`` covers every pixel (at least
    :data:`OPAQUE_ALPHA`): then the MPI needs no film channel."""
    return bool(np.all(np.clip(np.asarray(alpha, np.float64), 0.0, 1.0) >= OPAQUE_ALPHA))


def composite_over(groups) -> tuple[np.ndarray, np.ndarray]:
    """The group layers ``(premultiplied colour, alpha, ...)`` composited with "over",
    far to near: ``(colour (H, W, 3) premultiplied, alpha (H, W))``, which is the
    single-pass Combined render (see the module docstring)."""
    colour = alpha = None
    for g in groups:
        P, a = np.asarray(g[0], np.float64)[..., :3], np.asarray(g[1], np.float64)
        colour = P.copy() if colour is None else P + (1.0 - a[..., None]) * colour
        alpha = a.copy() if alpha is None else a + (1.0 - a) * alpha
    return colour, alpha


def layers_from_layered_passes(groups, blur_parameter: float,
                               settings: PassesSettings = PassesSettings(),
                               progress=None) -> tuple[MPI, PassesInfo]:
    """Build the MPI of depth-group layers (see the module docstring).

    Args:
        groups: far to near, ``(colour (H, W, 3) premultiplied linear radiance,
            alpha (H, W) coverage, disparity (H, W) 1/scene-unit)`` per group (the
            disparity from :func:`group_disparity`). At least one group.
        blur_parameter: ``A`` (pixels per unit disparity): plane spacing and fill reach.
        settings: as for :func:`~mpib_validate.runtime.layers.passes.layers_from_passes`.
        progress: optional ``progress(fraction)``; raising from it stops the work.

    Returns the MPI (colour channels premultiplied RGB, alpha, then, unless the farthest
    group is opaque, the film alpha: 1 on content, 0 on the world) and its info
    (``extra["groups"]``: the number of groups).
    """
    t0 = time.perf_counter()
    groups = [tuple(g) for g in groups]
    if not groups:
        raise PassError("layered passes: no group layers")
    H, W = np.shape(groups[0][1])
    for k, (P, a, D) in enumerate(groups):
        if np.shape(P)[:2] != (H, W) or np.shape(a) != (H, W) or np.shape(D) != (H, W):
            raise PassError(f"layered passes: group {k} is not {W}x{H} in colour, alpha and "
                            f"disparity")
        if np.ndim(P) != 3 or np.shape(P)[2] < 3:
            raise PassError(f"layered passes: group {k}'s colour must be (H, W, 3)")
    P0, a0, D0 = (np.asarray(v, np.float64) for v in groups[0])
    opaque = far_group_opaque(a0)
    a0 = np.clip(a0, 0.0, 1.0)
    # the farthest group as a single-pass input: the film alpha rides as a premultiplied
    # extra channel, the world (a0 = 0, Z at infinity) is its disparity-0 content
    far_colour = P0[..., :3] if opaque else np.concatenate([P0[..., :3], a0[..., None]], -1)
    D0 = np.where(a0 > 0, D0, 0.0)
    first = None if progress is None else (lambda f: progress(0.5 * f))  # noqa: E731
    sheets, info = sheets_from_passes(far_colour, D0, blur_parameter, settings, progress=first)
    for P, a, D in groups[1:]:
        a = np.clip(np.asarray(a, np.float64), 0.0, 1.0)
        P = np.asarray(P, np.float64)[..., :3]
        straight = np.divide(P, a[..., None], out=np.zeros_like(P), where=a[..., None] > 0)
        if not opaque:
            straight = np.concatenate([straight, np.ones((H, W, 1))], -1)
        sheets.append(Sheet((0, 0), straight, a, np.asarray(D, np.float64)))
    mpi = mpi_from_sheets(sheets, blur_parameter, settings, H, W)
    if progress is not None:
        progress(1.0)
    info.planes = mpi.plane_count
    info.extra["groups"] = len(groups)
    info.disparity_range = (min(float(np.min(g[2])) for g in groups),
                            max(float(np.max(g[2])) for g in groups))
    info.seconds = time.perf_counter() - t0
    return mpi, info

