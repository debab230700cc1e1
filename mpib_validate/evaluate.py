"""Scoring renders of card scenes: the true occlusion-boundary mask and the metrics."""

from __future__ import annotations

import numpy as np

from . import metrics
from .scene import Scene
from .trace import pinhole_maps


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
