"""PNG previews of linear-radiance images (sRGB encoded, clipped to [0, 1])."""

from __future__ import annotations

import os

import numpy as np

from mpib_validate.runtime.io.atomic import atomic_path
from mpib_validate.runtime.io.colour import linear_to_srgb


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB OETF on values clipped to [0, 1]: ``12.92 v`` below 0.0031308, else
    ``1.055 v^(1/2.4) - 0.055`` (:func:`mpib_validate.runtime.io.colour.linear_to_srgb`)."""
    return linear_to_srgb(linear)


def to_uint8(linear_rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` linear radiance to 8-bit sRGB."""
    return np.round(srgb_encode(linear_rgb[..., :3]) * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, linear_rgb: np.ndarray) -> None:
    """Write an sRGB PNG preview of a linear image atomically (alpha is dropped)."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(to_uint8(linear_rgb)).save(tmp, format="PNG")
