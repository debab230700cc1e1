"""Sample sets over the lens aperture and the pixel area.

A renderer averages radiance over the unit aperture disk ``mu^2 + nu^2 <= 1`` (the
lens point is ``(R mu, R nu)``, Eq. 12-13) and, in the canonical pixel model of
``docs/camera.md``, over the pixel's square area too. One :class:`LensSamples`
holds ``S`` joint samples ``(mu, nu, sx, sy)``: an aperture point and a sub-pixel
position in ``[0, 1)^2`` (0.5 is the pixel centre). Pairing each aperture sample with
its own sub-pixel position makes the pixel box average free: no extra samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LensSamples:
    """``S`` joint samples; arrays are float64, shape ``(S,)``.

    Attributes:
        mu, nu: aperture coordinates in the unit disk.
        sx, sy: sub-pixel positions in ``[0, 1)``, 0.5 = pixel centre.
        kind: how they were made (for metadata).
    """

    mu: np.ndarray
    nu: np.ndarray
    sx: np.ndarray
    sy: np.ndarray
    kind: str

    def __len__(self) -> int:
        return int(self.mu.shape[0])

    def chunks(self, size: int):
        """Consecutive sub-sets of at most ``size`` samples (for batching and progress)."""
        for s in range(0, len(self), size):
            sl = slice(s, s + size)
            yield LensSamples(self.mu[sl], self.nu[sl], self.sx[sl], self.sy[sl], self.kind)


def _r2_offsets(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Roberts' R2 low-discrepancy sequence in ``[0, 1)^2``, started at the centre."""
    g = 1.32471795724474602596  # plastic number
    k = np.arange(n, dtype=np.float64)
    return (0.5 + k / g) % 1.0, (0.5 + k / g ** 2) % 1.0


def grid(n_side: int = 51, pixel: str = "centre") -> LensSamples:
    """The official generator's aperture samples: an ``n_side`` square grid over
    ``[-1, 1]^2`` clipped to the unit disk (51 per side = 1,957 samples; 101 = 7,841).

    Args:
        pixel: ``"centre"`` samples each pixel at its centre (the official way);
            ``"box"`` pairs each aperture sample with a sub-pixel position from the R2
            sequence, so that the result is the pixel's box average.
    """
    if n_side < 1:
        raise ValueError(f"n_side must be >= 1, got {n_side}")
    t = np.linspace(-1.0, 1.0, n_side) if n_side > 1 else np.zeros(1)
    mu, nu = np.meshgrid(t, t)
    keep = mu ** 2 + nu ** 2 <= 1.0
    mu, nu = mu[keep], nu[keep]
    sx, sy = _pixel_positions(pixel, mu.size)
    return LensSamples(mu, nu, sx, sy, f"grid{n_side}-{pixel}")


def concentric_disk(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley-Chiu concentric map of ``[0, 1)^2`` onto the unit disk (area preserving)."""
    a = 2.0 * u - 1.0
    b = 2.0 * v - 1.0
    use_a = np.abs(a) > np.abs(b)
    safe_a = np.where(a == 0, 1.0, a)
    safe_b = np.where(b == 0, 1.0, b)
    r = np.where(use_a, a, b)
    phi = np.where(use_a, (np.pi / 4) * (b / safe_a), np.pi / 2 - (np.pi / 4) * (a / safe_b))
    r = np.where((a == 0) & (b == 0), 0.0, r)
    return r * np.cos(phi), r * np.sin(phi)


def stratified(n: int = 1024, seed: int = 0, pixel: str = "box") -> LensSamples:
    """Scrambled 4-D Sobol points: dims 0-1 mapped onto the disk (concentric map),
    dims 2-3 the sub-pixel position. Same ``(n, seed)``, same samples.

    A power of two ``n`` keeps the Sobol set balanced.
    """
    from scipy.stats import qmc

    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    sob = qmc.Sobol(d=4, scramble=True, seed=np.random.default_rng(seed))
    m = int(np.log2(n))
    pts = sob.random_base2(m) if 2 ** m == n else sob.random(n)
    mu, nu = concentric_disk(pts[:, 0], pts[:, 1])
    if pixel == "box":
        sx, sy = pts[:, 2], pts[:, 3]
    else:
        sx, sy = _pixel_positions(pixel, n)
    return LensSamples(mu, nu, sx, sy, f"sobol{n}-seed{seed}-{pixel}")


def pinhole(pixel_side: int = 4) -> LensSamples:
    """Aperture centre only (``A = 0`` view: the all-in-focus image), with a
    ``pixel_side^2`` grid of sub-pixel positions for the pixel box average."""
    t = (np.arange(pixel_side) + 0.5) / pixel_side
    sx, sy = np.meshgrid(t, t)
    z = np.zeros(sx.size)
    return LensSamples(z, z.copy(), sx.ravel(), sy.ravel(), f"pinhole{pixel_side}")


def _pixel_positions(pixel: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    if pixel == "centre":
        return np.full(n, 0.5), np.full(n, 0.5)
    if pixel == "box":
        return _r2_offsets(n)
    raise ValueError(f"pixel must be 'centre' or 'box', got {pixel!r}")
