"""The sRGB transfer functions (IEC 61966-2-1), one definition for the photo reader and
writer, the PNG previews and the card textures."""

from __future__ import annotations

import numpy as np

#: sRGB knees (IEC 61966-2-1): the encoded and the linear value where the linear
#: segment meets the power segment.
SRGB_KNEE_ENCODED = 0.04045
SRGB_KNEE_LINEAR = 0.0031308


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """sRGB-encoded ``v`` in [0, 1] to linear: ``v / 12.92`` for ``v <= 0.04045``, else
    ``((v + 0.055) / 1.055) ** 2.4`` (IEC 61966-2-1). Values outside [0, 1] are clipped
    first (an encoded file holds nothing else)."""
    v = np.clip(np.asarray(v, np.float64), 0.0, 1.0)
    return np.where(v <= SRGB_KNEE_ENCODED, v / 12.92,
                    np.power((v + 0.055) / 1.055, 2.4))


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear ``c`` to sRGB-encoded values: ``12.92 c`` for ``c <= 0.0031308``, else
    ``1.055 c ** (1 / 2.4) - 0.055`` (IEC 61966-2-1), on ``c`` clipped to [0, 1] (what
    an encoded file can hold; NaN becomes 0)."""
    c = np.clip(np.nan_to_num(np.asarray(c, np.float64)), 0.0, 1.0)
    p = np.power(c, 1.0 / 2.4)
    # 1.055 p - 0.055 written as p + 0.055 (p - 1): the same in exact arithmetic, and
    # exactly 1 at c = 1 in floating point (1.055 - 0.055 rounds to 1 - 1.1e-16)
    return np.where(c <= SRGB_KNEE_LINEAR, 12.92 * c, p + 0.055 * (p - 1.0))
