"""Sample sets over the lens aperture and the pixel area.

A renderer averages radiance over the unit aperture (the disk ``mu^2 + nu^2 <= 1``, or
the polygon and ratio of :class:`mpib_validate.runtime.camera.Aperture`; the lens point
is ``(R mu, R nu)``, Eq. 12-13) and, in the canonical pixel model of
``docs/camera.md``, over the pixel's square area too. One :class:`LensSamples`
holds ``S`` joint samples ``(mu, nu, sx, sy)``: an aperture point and a sub-pixel
position in ``[0, 1)^2`` (0.5 is the pixel centre). Pairing each aperture sample with
its own sub-pixel position makes the pixel box average free: no extra samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LensSamples:
    """``S`` joint samples; arrays are float64, shape ``(S,)``.

    Attributes:
        mu, nu: aperture coordinates in the unit aperture (the disk by default).
        sx, sy: sub-pixel positions in ``[0, 1)``, 0.5 = pixel centre.
        kind: how they were made (for metadata).
        aperture: the :class:`~mpib_validate.runtime.camera.Aperture` the aperture
            points cover (None: the disk), or ``"any"`` for the pinhole (all at the
            centre, inside every aperture).
    """

    mu: np.ndarray
    nu: np.ndarray
    sx: np.ndarray
    sy: np.ndarray
    kind: str
    aperture: object = None

    def covers(self, aperture) -> bool:
        """Whether these samples are of ``aperture`` (None or a disk: the disk)."""
        if self.aperture == "any":
            return True
        mine = None if self.aperture is None or self.aperture.is_disk else self.aperture
        theirs = None if aperture is None or aperture.is_disk else aperture
        return mine == theirs

    def __len__(self) -> int:
        return int(self.mu.shape[0])

    def chunks(self, size: int):
        """Consecutive sub-sets of at most ``size`` samples (for batching and progress)."""
        for s in range(0, len(self), size):
            sl = slice(s, s + size)
            yield LensSamples(self.mu[sl], self.nu[sl], self.sx[sl], self.sy[sl], self.kind,
                              self.aperture)


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


def polygon_from_disk(x: np.ndarray, y: np.ndarray, blades: int,
                      rotation: float) -> tuple[np.ndarray, np.ndarray]:
    """Area-preserving map of the unit disk onto the regular polygon of ``blades`` sides
    inscribed in the unit circle, edge normals at ``rotation + 2 pi k / blades``, in
    axes with y up (Cycles' camera space).

    A point at radius ``s`` and angle ``t`` from its sector's edge normal
    (``|t| <= pi / n``) goes to the angle ``t' = atan(c t)``, ``c = n tan(pi / n) / pi``,
    and the radius ``s cos(pi / n) / cos t'``: the sector's boundary arc onto its edge,
    with the Jacobian ``c cos(pi / n)^2`` everywhere (the polygon's area over pi), so
    uniform points stay uniform; a compact part of the disk stays compact."""
    half = math.pi / blades
    s = np.hypot(x, y)
    phi = np.arctan2(y, x) - rotation
    k = np.round(phi / (2.0 * half))
    t = np.arctan(math.tan(half) / half * (phi - 2.0 * half * k))
    rad = s * (math.cos(half) / np.cos(t))
    ang = t + (rotation + 2.0 * half * k)
    return rad * np.cos(ang), rad * np.sin(ang)


def aperture_map(u: np.ndarray, v: np.ndarray, aperture=None) -> tuple[np.ndarray, np.ndarray]:
    """Area-preserving map of ``[0, 1)^2`` onto the unit aperture
    (:class:`mpib_validate.runtime.camera.Aperture`) in image axes (x right, y down):
    ``(mu, nu)``. The concentric map onto the disk (the disk's own map, unchanged), then
    for blades :func:`polygon_from_disk` in Cycles' y-up axes and y flipped, then x
    divided by the ratio (a linear map: uniform stays uniform)."""
    mu, nu = concentric_disk(u, v)
    if aperture is None or aperture.is_disk:
        return mu, nu
    if aperture.blades:
        x, y = polygon_from_disk(mu, nu, aperture.blades, aperture.rotation)
        mu, nu = x, -y
    return mu / aperture.ratio, nu


def stratified(n: int = 1024, seed: int = 0, pixel: str = "box", aperture=None) -> LensSamples:
    """Scrambled 4-D Sobol points: dims 0-1 mapped onto the aperture
    (:func:`aperture_map`: the concentric map onto the disk by default), dims 2-3 the
    sub-pixel position. Same ``(n, seed, aperture)``, same samples.

    A power of two ``n`` keeps the Sobol set balanced.
    """
    from scipy.stats import qmc

    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    sob = qmc.Sobol(d=4, scramble=True, seed=np.random.default_rng(seed))
    m = int(np.log2(n))
    pts = sob.random_base2(m) if 2 ** m == n else sob.random(n)
    mu, nu = aperture_map(pts[:, 0], pts[:, 1], aperture)
    if pixel == "box":
        sx, sy = pts[:, 2], pts[:, 3]
    else:
        sx, sy = _pixel_positions(pixel, n)
    shape = "" if aperture is None or aperture.is_disk else "-" + "-".join(
        f"{k}{v:g}" for k, v in aperture.to_dict().items())
    return LensSamples(mu, nu, sx, sy, f"sobol{n}-seed{seed}-{pixel}{shape}", aperture)


def pinhole(pixel_side: int = 4) -> LensSamples:
    """Aperture centre only (``A = 0`` view: the all-in-focus image), with a
    ``pixel_side^2`` grid of sub-pixel positions for the pixel box average."""
    t = (np.arange(pixel_side) + 0.5) / pixel_side
    sx, sy = np.meshgrid(t, t)
    z = np.zeros(sx.size)
    return LensSamples(z, z.copy(), sx.ravel(), sy.ravel(), f"pinhole{pixel_side}", "any")


def _pixel_positions(pixel: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    if pixel == "centre":
        return np.full(n, 0.5), np.full(n, 0.5)
    if pixel == "box":
        return _r2_offsets(n)
    raise ValueError(f"pixel must be 'centre' or 'box', got {pixel!r}")
