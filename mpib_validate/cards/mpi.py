"""MPIs from card scenes, and card scenes from MPIs: the harness's bridge to the runtime.

:func:`layers_from_cards` cuts a card scene into its exact MPI (every card's full
texture, hidden parts included), :func:`mpi_to_scene` turns an MPI back into fronto-parallel
cards, and :func:`render_exact` renders an MPI through every aperture sample with the
Eq. 15 tracer (exact for fronto-parallel layers).
"""

from __future__ import annotations

import math

import numpy as np

from mpib_validate.cards.scene import Card, Plane, Scene
from mpib_validate.cards.trace import trace
from mpib_validate.runtime import samples as _s
from mpib_validate.runtime.layers.mpi import (MPI, SNAP_PX, Sheet, adaptive_planes,
                                              layers_from_sheets)


def card_disparity_intervals(scene: Scene, margin: int = 0) -> list[tuple[float, float]]:
    """Each card's disparity range over the part of it inside the canvas."""
    cam = scene.camera
    out = []
    for card in scene.cards:
        x0, x1, y0, y1 = card.extent(cam)
        hw, hh = 0.5 * cam.width + margin, 0.5 * cam.height + margin
        x0, x1 = max(x0, -hw), min(x1, hw)
        y0, y1 = max(y0, -hh), min(y1, hh)
        if x0 >= x1 or y0 >= y1:
            continue
        if card.plane.is_fronto:
            d = 1.0 / card.plane.c
            out.append((d, d))
        else:
            xs = np.array([x0 + 0.5, x1 - 0.5, x0 + 0.5, x1 - 0.5])
            ys = np.array([y0 + 0.5, y0 + 0.5, y1 - 0.5, y1 - 0.5])
            d = card.plane.disparity(xs, ys)
            out.append((float(d.min()), float(d.max())))
    return out


def layers_from_cards(scene: Scene, planes: np.ndarray | None = None,
                      margin: int | None = None, split: str = "linear") -> MPI:
    """The exact MPI of a card scene: every card's full texture (hidden parts included).

    Fronto-parallel cards go to the plane at their own disparity when ``planes`` is
    ``None`` (one plane per distinct card disparity: no quantisation at all), else are
    split like tilted ones. Tilted cards are cut into slabs: each texel, at the
    disparity of its centre, is shared between its two neighbouring planes by
    :func:`split_between_planes` (``split="linear"``: no cracks at slab edges, Eq. 16
    exact) or goes wholly to the nearest plane (``split="nearest"``, the hard cut whose
    slab edges can crack, as in the paper's failure case).

    Cards meeting on one plane are combined with "over", nearer card (by disparity at
    its centre) on top. ``margin`` defaults to the largest blur radius plus 2 px, so
    that border pixels see real content.
    """
    cam = scene.camera
    if margin is None:
        margin = int(math.ceil(scene.max_blur_radius())) + 2
    H, W = cam.height, cam.width
    hc, wc = H + 2 * margin, W + 2 * margin
    if planes is None:
        fronto = sorted({1.0 / c.plane.c for c in scene.cards if c.plane.is_fronto})
        tilted = [iv for iv, c in zip(card_disparity_intervals(scene, margin), scene.cards)
                  if not c.plane.is_fronto]
        extra = adaptive_planes(tilted, cam.blur_parameter) if tilted else []
        planes = np.unique(np.concatenate([fronto, extra]))
    planes = np.asarray(planes, np.float64)

    def centre_d(card):
        x0, x1, y0, y1 = card.extent(cam)
        return float(card.plane.disparity(0.5 * (x0 + x1), 0.5 * (y0 + y1)))

    sheets = []
    for card in sorted(scene.cards, key=centre_d):  # far to near: nearer goes "over"
        ox, oy = card.offset[0] + margin, card.offset[1] + margin
        h, w = card.rgba.shape[:2]
        cy0, cy1 = max(0, oy), min(hc, oy + h)
        cx0, cx1 = max(0, ox), min(wc, ox + w)
        if cy0 >= cy1 or cx0 >= cx1:
            continue
        tex = card.rgba[cy0 - oy:cy1 - oy, cx0 - ox:cx1 - ox]
        ys = np.arange(cy0, cy1) + 0.5 - margin - 0.5 * H
        xs = np.arange(cx0, cx1) + 0.5 - margin - 0.5 * W
        d = card.plane.disparity(xs[None, :], ys[:, None]) * np.ones(tex.shape[:2])
        sheets.append(Sheet((cy0, cx0), tex[..., :3], tex[..., 3], d))
    return layers_from_sheets(sheets, planes, H, W, margin, split,
                              snap=SNAP_PX / cam.blur_parameter)


def mpi_to_scene(mpi: MPI, camera) -> Scene:
    """The MPI as a card scene: one fronto-parallel card per layer (straight alpha).

    Rendering it with the Eq. 15 tracer is the *exact* MPI renderer: every aperture
    sample shifts each layer by ``A (d_i - d_f) (mu, nu)`` and composites front to back.
    A plane at disparity 0 (infinitely far) is placed at 1e-9.
    """
    cards = []
    for i, l in enumerate(mpi.layers):
        a = l.rgba[..., 3:4]
        rgb = np.divide(l.rgba[..., :3], a, out=np.zeros_like(l.rgba[..., :3]), where=a > 0)
        straight = np.concatenate([rgb, a], axis=-1).astype(np.float32)
        cards.append(Card(f"layer{i:03d}", straight, Plane.fronto(max(l.disparity, 1e-9)),
                          (l.x0 - mpi.margin, l.y0 - mpi.margin)))
    return Scene(camera, cards, {"from": "mpi"})



def render_exact(mpi: MPI, camera, samples=None, backend: str = "auto") -> np.ndarray:
    """Render the MPI through every aperture sample (exact for fronto-parallel layers).

    Each layer becomes a fronto-parallel card and the Eq. 15 tracer renders it: each
    sample shifts layer ``i`` by ``A (d_i - d_f) (mu, nu)`` and composites front to
    back. Returns ``(H, W, 4)`` in the same form as :func:`composite` (normalised colour
    and coverage). The aperture points are the camera's aperture's (default samples: 1,024
    over ``camera.aperture``).
    """
    img, _ = trace(mpi_to_scene(mpi, camera),
                   samples or _s.stratified(1024, aperture=camera.aperture),
                   backend=backend, notices=False)
    out = np.zeros_like(img)
    a = img[..., 3:4]
    np.divide(img[..., :3], a, out=out[..., :3], where=a > 0)
    out[..., 3] = img[..., 3]
    return out
