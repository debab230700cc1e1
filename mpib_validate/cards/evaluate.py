"""Scoring renders of card scenes: the true occlusion-boundary mask and the metrics."""

from __future__ import annotations

import numpy as np

from mpib_validate import metrics
from mpib_validate.cards.scene import Scene
from mpib_validate.cards.trace import pinhole_maps


def card_scene_mask(scene: Scene, window: int = 9) -> np.ndarray:
    """PSNR_ob/SSIM_ob mask of a card scene from its true boundaries: where the front-most
    solid card changes (pinhole view), dilated by the largest blur radius around."""
    maps = pinhole_maps(scene)
    boundary = metrics.boundaries_from_layers(maps["layer"], maps["disparity"])
    cam = scene.camera
    return metrics.occlusion_mask(boundary, maps["disparity"], cam.blur_parameter,
                                  cam.focus_disparity, window)


def score(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None,
          with_flip: bool = True) -> dict:
    """:func:`metrics.all_metrics` on the colour of two renders."""
    return metrics.all_metrics(reference[..., :3], test[..., :3], mask, with_flip=with_flip)


def hidden_background(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What lies behind the front-most solid card at each pixel centre (pinhole view).

    Returns ``(colour (H, W, 3), valid (H, W), disparity (H, W))``: the "over" composite
    of every card strictly behind the front-most card with alpha >= 0.5, normalised by
    its coverage; ``valid`` where that coverage is positive; the coverage-weighted
    disparity of those cards (Eq. 16). This is the truth a hidden-background fill is
    scored against, in the form ``passes.layers_from_passes(background=)`` takes.
    """
    maps = pinhole_maps(scene)
    alpha, disp, rgb = maps["card_alpha"], maps["card_disparity"], maps["card_rgb"]
    layer = maps["layer"]
    front_d = np.where(layer >= 0, maps["disparity"], -np.inf)
    order = np.argsort(-disp, axis=0, kind="stable")  # nearest first, per pixel
    C = np.zeros(layer.shape + (3,), np.float64)
    Dsum = np.zeros(layer.shape, np.float64)
    T = np.ones(layer.shape, np.float64)
    for rank in range(order.shape[0]):
        k = order[rank]
        a = np.take_along_axis(alpha, k[None], 0)[0].astype(np.float64)
        d = np.take_along_axis(disp, k[None], 0)[0]
        c = np.take_along_axis(rgb, k[None, ..., None], 0)[0].astype(np.float64)
        behind = (d < front_d) & (layer >= 0)
        a = np.where(behind, a, 0.0)
        C += (T * a)[..., None] * c
        Dsum += T * a * d
        T *= 1.0 - a
    cov = 1.0 - T
    valid = cov > 0
    out = np.divide(C, cov[..., None], out=np.zeros_like(C), where=valid[..., None])
    disparity = np.divide(Dsum, cov, out=np.zeros_like(Dsum), where=valid)
    return out.astype(np.float32), valid, disparity
