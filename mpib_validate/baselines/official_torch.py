"""The official MPIB renderer's computation (``MPIBokehRenderer``), in torch, for the benchmark.

A thin adapter written from the supplement's Eq. 1 and the official code's documented
behaviour (``docs/camera.md``, section "The paper's renderer and generator"); no source of
the official code is copied or vendored. It exists so that ``mpib bench --suite official``
can time and score the official code path side by side with
:func:`mpib_validate.runtime.compositor.composite.composite` on the same MPI. torch is an
optional extra (``pip install -e ".[official]"``, CPU build 2.13.0); nothing else in the
project imports this module.

The official convention. Disparity is normalised to ``[0, 1]``; the MPI has ``n = 32``
planes at ``d_i = (i + 0.5) / n``, plane 0 the farthest; the blur radius of plane ``i``
is ``r_i = round(K |d_i - d_f|)`` pixels (integer; planes within half a pixel of focus
stay sharp), ``K`` the blur parameter in pixels per unit normalised disparity and
``d_f`` the normalised focus. Far to near, with ``S_r`` the soft disk of radius ``r``::

    x_i   = (c_i alpha_i, alpha_i) * S_{r_i}            (4 channels, per-plane conv2d)
    acc  <- acc (1 - x_i[alpha]) + x_i                   (acc = 0 before plane 0)
    B     = acc[colour] / acc[alpha]                     (Eq. 1, no epsilon)

which is Eq. 1, ``B = sum_i (c_i a_i * K_i) prod_{j>i} (1 - a_j * K_j) /
sum_i (a_i * K_i) prod_{j>i} (1 - a_j * K_j)``: the fourth channel carries the
normaliser (the denominator) with the same transmittance as the colour.

Assumptions (each from ``docs/camera.md`` unless marked *ours*):

- Kernel: ``0.5 + 0.5 tanh(0.25 (r^2 - x^2 - y^2) + 0.5)`` on the ``(2r+1)^2`` integer
  grid, normalised to sum 1 (the project's :func:`kernels.soft_disk`, converted to a
  float32 tensor); radius 0 is the identity; the official table stops at 200 px, so a
  larger radius is refused here (*ours*: refused rather than clamped).
- ``round`` is Python's (half to even); the radius is computed in float64 from the
  normalised disparities (*ours*: the official dtype is not recorded).
- Convolution: ``torch.nn.functional.conv2d`` with ``groups = 4`` (depthwise, direct, no
  FFT) on the plane replication-padded by ``r`` (``F.pad(mode="replicate")``), every one
  of the ``n`` planes, empty or not (the official renderer has no notion of an empty
  plane). The kernel is symmetric, so correlation and convolution coincide.
- float32 throughout, batch 1, ``torch.inference_mode``; ``torch.set_num_threads(2)``
  (the issue's set-up: torch 2.13 CPU with 2 threads).
- No clamp of the blurred alpha, no epsilon in the division: a pixel that no plane
  covers is NaN (0/0), as in the official code. The caller counts and reports them.
- Linear input: the MPI's colour is linear radiance (EXR renders), so the official
  gamma 2.2 before and after, meant for photographs, is not applied.
- Input planes are straight colour ``c_i`` and alpha ``a_i`` (the official network's
  outputs); :func:`to_official` divides the project's premultiplied layers by alpha.
  Building that input is not part of the renderer's time.

Mapping the project's MPI (:func:`to_official`). The project's planes are at arbitrary
disparities ``d`` (1/scene-unit) with blur parameter ``A`` (px per unit disparity) and
focus ``d_f``. Given a disparity range ``[lo, hi]`` the affine map
``d_n = (d - lo) / (hi - lo)``, ``K = A (hi - lo)``, ``d_fn = (d_f - lo) / (hi - lo)``
gives ``K |d_n - d_fn| = A |d - d_f|``: the same radius for the same plane. A project
MPI built on ``uniform_planes(32, d_max)`` (``d_i = (i + 0.5) d_max / 32``) with
``[lo, hi] = [0, d_max]`` lands exactly on the official planes, so both renderers use
the same 32 planes. A layer off the official grid goes to the nearest official plane
(layers meeting on one plane are combined with "over", far to near); the largest
resulting radius error ``K |d_n - d_grid|`` is returned so that a caller can refuse an
unfair comparison. Additive interval groups (``Layer.group``) have no official
counterpart and are refused.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

import numpy as np

from mpib_validate.runtime.compositor.kernels import soft_disk
from mpib_validate.runtime.layers.mpi import MPI, uniform_planes

#: planes of the official MPI
OFFICIAL_PLANES = 32
#: the largest radius in the official kernel table (px)
OFFICIAL_MAX_RADIUS = 200
#: CPU threads of the official set-up being reproduced
OFFICIAL_THREADS = 2


def torch_available() -> bool:
    """True when torch can be imported (the optional ``official`` extra)."""
    return importlib.util.find_spec("torch") is not None


@dataclass
class OfficialMPI:
    """An MPI in the official convention.

    Attributes:
        planes: ``(n, 4, H, W)`` float32: straight linear colour (3) and alpha, plane 0
            the farthest, over the project MPI's whole canvas (frame plus margin).
        disparity: ``(n,)`` normalised plane disparities ``(i + 0.5) / n``.
        K: blur parameter, px per unit normalised disparity.
        focus: normalised focus disparity ``d_fn``.
        frame: ``(y0, y1, x0, x1)``: the frame inside the canvas (the output is cropped to it).
        plane_error_px: largest ``K |d_n - d_grid|`` of the mapped layers (0 when the
            project's planes are the official ones).
    """

    planes: np.ndarray
    disparity: np.ndarray
    K: float
    focus: float
    frame: tuple[int, int, int, int]
    plane_error_px: float = 0.0

    def radii(self) -> list[int]:
        """``round(K |d_i - d_fn|)`` per plane (px), as the official renderer takes them."""
        return [int(round(self.K * abs(float(d) - self.focus))) for d in self.disparity]


def to_official(mpi: MPI, blur_parameter: float, focus_disparity: float,
                d_range: tuple[float, float], n: int = OFFICIAL_PLANES) -> OfficialMPI:
    """Map a project MPI onto the official convention (see the module docstring).

    Args:
        mpi: far-to-near premultiplied layers (no additive groups).
        blur_parameter: ``A``, px per unit disparity.
        focus_disparity: ``d_f`` (1/scene-unit).
        d_range: ``(lo, hi)`` disparities mapped to normalised 0 and 1.
        n: official plane count.

    Returns:
        The :class:`OfficialMPI`, canvas-sized.
    """
    lo, hi = (float(v) for v in d_range)
    if not hi > lo:
        raise ValueError(f"disparity range must have hi > lo, got {d_range}")
    if mpi.grouped:
        raise ValueError("the official renderer has no additive interval groups; build the MPI "
                         "with the over split")
    span = hi - lo
    K = blur_parameter * span
    grid = uniform_planes(n, 1.0)
    hc, wc = mpi.canvas_shape
    premul = np.zeros((n, hc, wc, 4), np.float32)  # premultiplied, combined with "over"
    err = 0.0
    for layer in mpi.layers:  # far to near
        dn = (layer.disparity - lo) / span
        i = int(np.clip(np.rint(dn * n - 0.5), 0, n - 1))
        err = max(err, K * abs(dn - grid[i]))
        y0, y1, x0, x1 = layer.box
        region = premul[i, y0:y1, x0:x1]
        region *= 1.0 - layer.rgba[..., 3:4]
        region += layer.rgba[..., :4]
    planes = np.zeros((n, 4, hc, wc), np.float32)
    a = premul[..., 3]
    for c in range(3):
        np.divide(premul[..., c], a, out=planes[:, c], where=a > 0)
    planes[:, 3] = a
    m = mpi.margin
    return OfficialMPI(planes, grid, K, (focus_disparity - lo) / span,
                       (m, m + mpi.height, m, m + mpi.width), err)


class OfficialRenderer:
    """Eq. 1 the way the official ``MPIBokehRenderer`` computes it (module docstring).

    The soft-disk kernels are built once per radius and kept (the official renderer
    builds its table of radii 0..200 at construction); :meth:`prepare` builds those an
    MPI needs, so that a timed :meth:`render` does not include them.
    """

    def __init__(self, threads: int = OFFICIAL_THREADS, max_radius: int = OFFICIAL_MAX_RADIUS):
        import torch

        self._torch = torch
        self.threads = threads
        self.max_radius = max_radius
        self._kernels: dict = {}

    def kernel(self, r: int):
        """``(4, 1, 2r+1, 2r+1)`` float32 soft disk of integer radius ``r``."""
        if r > self.max_radius:
            raise ValueError(f"blur radius {r} px exceeds the official kernel table "
                             f"(0..{self.max_radius} px)")
        if r not in self._kernels:
            k = self._torch.from_numpy(soft_disk(r).astype(np.float32))
            self._kernels[r] = k[None, None].expand(4, 1, *k.shape).contiguous()
        return self._kernels[r]

    def prepare(self, om: OfficialMPI) -> None:
        """Build every kernel that :meth:`render` will use on ``om``."""
        for r in om.radii():
            self.kernel(r)

    def render(self, om: OfficialMPI) -> np.ndarray:
        """Render ``om``: ``(H, W, 3)`` float32 normalised linear colour over the frame
        (NaN where no plane covers a pixel, as in the official code)."""
        torch = self._torch
        F = torch.nn.functional
        torch.set_num_threads(self.threads)
        planes = torch.from_numpy(om.planes)
        n, _, hc, wc = planes.shape
        with torch.inference_mode():
            acc = torch.zeros((1, 4, hc, wc), dtype=torch.float32)
            for i, r in enumerate(om.radii()):  # far to near
                rgb, a = planes[i, :3], planes[i, 3:4]
                x = torch.cat([rgb * a, a], dim=0)[None]  # (1, 4, H, W)
                if r > 0:
                    x = F.conv2d(F.pad(x, (r, r, r, r), mode="replicate"), self.kernel(r),
                                 groups=4)
                acc = acc * (1.0 - x[:, 3:4]) + x
            out = acc[0, :3] / acc[0, 3:4]
        y0, y1, x0, x1 = om.frame
        return np.ascontiguousarray(out.permute(1, 2, 0).numpy()[y0:y1, x0:x1],
                                    dtype=np.float32)
