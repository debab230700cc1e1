"""Classical baselines on the same input (all-in-focus colour + disparity).

- RVR (supplement Eq. 2 and 4) and SteReFo (Eq. 3 and 5): the whole image as every
  layer's colour, with hand-made visible-only alphas; ``N`` layers at the uniform
  disparities of the paper, hyper-parameters exposed.
- Scatter: BokehMe's classical renderer. Every pixel is splatted as a soft disk of its
  own radius ``r = A |d - d_f|``, weight ``(0.5 + 0.5 tanh(4 (r - dist))) / (r^2 + 0.2)``,
  output ``sum(w c) / sum(w)``. No occlusion handling.
- Gather: every output pixel averages the input over a disk of *its own* radius
  (the output pixel's circle of confusion), same weights. No occlusion handling either.

Scatter and gather quantise radii to ``1/step`` px and run one FFT convolution per
radius group, which is exact for the quantised radii (cost: one convolution per group).
All kernels use the project's convolution paths (:mod:`mpib_validate.runtime.compositor.kernels`).
"""

from __future__ import annotations

import numpy as np

from mpib_validate.runtime.compositor import kernels as _k
from mpib_validate.runtime.layers.mpi import uniform_planes


def _blur(img: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Correlate ``(H, W, C)`` with ``kernel``, replication at the image border."""
    R = _k.kernel_radius(kernel)
    padded = np.pad(np.asarray(img, np.float32), ((R, R), (R, R), (0, 0)), mode="edge")
    return _k.correlate(padded, kernel, "auto")


def _layer_kernels(d_layers, A, d_f):
    return [_k.disk_kernel(A * (d - d_f)) for d in d_layers]


def rvr(colour, disparity, A, d_f, n_layers=32, lam=None):
    """RVR (Eq. 2, 4): ``B = sum_i (I a_i * K_i) prod_{j>i} (1 - a_j)`` with
    ``a_i = exp(-lambda (D - d_i)^2)``; ``lambda`` defaults to ``(n / d_max)^2`` so that a
    layer's weight falls to exp(-1) one layer spacing away."""
    D = np.asarray(disparity, np.float64)
    d_layers = uniform_planes(n_layers, max(float(D.max()), 1e-9) * (1 + 1e-9))
    if lam is None:
        lam = (1.0 / (d_layers[1] - d_layers[0])) ** 2 if n_layers > 1 else 1.0
    I = np.asarray(colour, np.float32)[..., :3]
    out = np.zeros_like(I, dtype=np.float64)
    for d_i, k in zip(d_layers, _layer_kernels(d_layers, A, d_f)):  # far to near
        a = np.exp(-lam * (D - d_i) ** 2)[..., None]
        out = out * (1.0 - a) + _blur(I * a, k)
    return out.astype(np.float32)


def sterefo(colour, disparity, A, d_f, n_layers=32, sharpness=None):
    """SteReFo (Eq. 3, 5): Eq. 1's normalised compositing of ``I a_i`` with
    ``a_i = 1/2 + 1/2 tanh(alpha (l - |D - d_i|))``, ``l`` the layer spacing;
    ``alpha`` defaults to ``4 / l``."""
    D = np.asarray(disparity, np.float64)
    d_layers = uniform_planes(n_layers, max(float(D.max()), 1e-9) * (1 + 1e-9))
    l = d_layers[1] - d_layers[0] if n_layers > 1 else 1.0
    alpha = 4.0 / l if sharpness is None else sharpness
    I = np.asarray(colour, np.float32)[..., :3]
    acc = np.zeros(I.shape[:2] + (4,), np.float64)
    for d_i, k in zip(d_layers, _layer_kernels(d_layers, A, d_f)):
        a = (0.5 + 0.5 * np.tanh(alpha * (l - np.abs(D - d_i))))[..., None]
        blurred = _blur(np.concatenate([I * a, a], axis=-1), k)
        acc = acc * (1.0 - blurred[..., 3:4]) + blurred
    out = np.divide(acc[..., :3], acc[..., 3:4], out=np.zeros_like(acc[..., :3]),
                    where=acc[..., 3:4] > 0)
    return out.astype(np.float32)


def _soft_disk_weights(r: float) -> np.ndarray:
    """BokehMe's splat: ``(0.5 + 0.5 tanh(4 (r - dist))) / (r^2 + 0.2)``."""
    R = int(np.ceil(r)) + 1
    y, x = np.mgrid[-R:R + 1, -R:R + 1]
    return (0.5 + 0.5 * np.tanh(4.0 * (r - np.hypot(x, y)))) / (r * r + 0.2)


def _radius_groups(radius, step):
    q = np.round(np.asarray(radius, np.float64) * step) / step
    return q, np.unique(q)


def scatter(colour, disparity, A, d_f, step=4):
    """BokehMe's classical scatter renderer (radii quantised to ``1/step`` px)."""
    I = np.asarray(colour, np.float32)[..., :3]
    q, levels = _radius_groups(A * np.abs(np.asarray(disparity) - d_f), step)
    acc = np.zeros(I.shape[:2] + (4,), np.float64)
    for r in levels:
        m = (q == r).astype(np.float32)[..., None]
        k = _soft_disk_weights(r)  # symmetric: scatter = correlation
        acc += _blur(np.concatenate([I * m, m], axis=-1), k)
    out = np.divide(acc[..., :3], acc[..., 3:4], out=np.zeros_like(acc[..., :3]),
                    where=acc[..., 3:4] > 0)
    return out.astype(np.float32)


def gather(colour, disparity, A, d_f, step=4):
    """Gather: each output pixel averages the input over its own circle of confusion."""
    I = np.asarray(colour, np.float32)[..., :3]
    q, levels = _radius_groups(A * np.abs(np.asarray(disparity) - d_f), step)
    out = np.zeros_like(I)
    ones = np.ones(I.shape[:2] + (1,), np.float32)
    for r in levels:
        m = q == r
        k = _soft_disk_weights(r)
        b = _blur(np.concatenate([I, ones], axis=-1), k)
        out[m] = b[m][:, :3] / b[m][:, 3:4]
    return out
