"""Point-emitter footprints: the refocused blur of small emitters against Cycles' own
depth of field, compared by shape (issue 29's lens test).

A transparent fronto-parallel card holds a grid of opaque emitting squares of 1, 2 and 3
texels (px) across, behind or in front of the focus plane. Cycles renders it with the
camera's aperture (blades, rotation, ratio) and depth of field; ``mpib``'s refocus
(:func:`mpib_validate.runtime.refocus.refocus`, the card scenes' texel pixel model) blurs
Cycles' own pinhole render of it with its depth pass. Each footprint (the emitter's
window, ``step`` px square) is compared by

- its second moments about its centroid: the covariance's principal axis (orientation,
  degrees, mod 180) and the square roots of its eigenvalues (axis lengths, px), after
  subtracting the two unit boxes' ``1/12`` per axis and the emitter's own ``(s^2 - 1)/12``
  per axis (an ``s``-px square); compared in %;
- the orientation of its ``n``-fold symmetry: ``arg(sum w (z - c)^n) / n`` over the
  window, ``z = x - i y`` (y up, as on screen), which a regular polygon of ``n`` blades
  turns with the aperture's rotation (the second moments do not see the rotation: a
  regular polygon's covariance is isotropic);
- the intersection over union of the regions above half of each footprint's peak, the
  peak being the 95th percentile of the window's values after a 3x3 box (Cycles' noise).
"""

from __future__ import annotations

import math

import numpy as np


def emitter_scene(aperture, side: str, radius: float = 12.0, sizes=(1, 2, 3),
                  copies: int = 2, radiance: float = 1.0):
    """``(scene, centres, step, sizes)``: a card of emitting squares blurred to
    ``radius`` px (circumradius) behind (``side="far"``, d = 0.25) or in front (``"near"``,
    d = 0.75) of the focus (d_f = 0.5); ``centres`` the (row, col) of each square's centre
    (pixel units, may be half-integers), ``sizes`` each square's side (px)."""
    from mpib_validate.cards.scene import Card, Plane, Scene
    from mpib_validate.runtime.camera import Camera

    d = {"far": 0.25, "near": 0.75}[side]
    d_f = 0.5
    step = int(2 * math.ceil(radius * aperture.extent) + 10)
    n = len(sizes) * copies
    cols = len(sizes)
    rows = copies
    W, H = cols * step, rows * step
    cam = Camera(W, H, radius / abs(d - d_f), d_f, aperture=aperture)
    rgba = np.zeros((H, W, 4), np.float32)
    centres, sz = [], []
    for i in range(rows):
        for j, s in enumerate(sizes):
            y0, x0 = i * step + step // 2 - s // 2, j * step + step // 2 - s // 2
            rgba[y0:y0 + s, x0:x0 + s] = [radiance, radiance, radiance, 1.0]
            centres.append((y0 + s / 2.0, x0 + s / 2.0))
            sz.append(s)
    scene = Scene(cam, [Card("emitters", rgba, Plane.fronto(d), (0, 0))]).validate()
    assert len(centres) == n
    return scene, centres, step, sz


def _window(img, centre, step):
    y, x = centre
    y0, x0 = int(round(y - step / 2)), int(round(x - step / 2))
    return np.asarray(img[y0:y0 + step, x0:x0 + step], np.float64), y0, x0


def shape_figures(img: np.ndarray, centre, step: int, size: int, blades: int) -> dict:
    """Second moments, ``n``-fold orientation and the half-peak mask of one footprint."""
    w, y0, x0 = _window(img, centre, step)
    w = np.maximum(w, 0.0)
    yy, xx = np.mgrid[y0:y0 + step, x0:x0 + step] + 0.5
    s = w.sum()
    cy, cx = (w * yy).sum() / s, (w * xx).sum() / s
    dy, dx = yy - cy, xx - cx
    box = 2.0 / 12.0 + (size * size - 1.0) / 12.0
    cxx = (w * dx * dx).sum() / s - box
    cyy = (w * dy * dy).sum() / s - box
    cxy = (w * dx * dy).sum() / s
    ev, evec = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
    major = evec[:, 1]  # (x, y) in y-down axes; on screen the angle is -atan2(y, x)
    orient = math.degrees(math.atan2(-major[1], major[0])) % 180.0
    out = {"axes": np.sqrt(np.maximum(ev[::-1], 0.0)), "orientation": orient,
           "centroid": (cy, cx)}
    if blades:
        z = dx - 1j * dy
        m = (w * z ** blades).sum()
        out["nfold"] = math.degrees(np.angle(m) / blades)
    from scipy import ndimage

    sm = ndimage.uniform_filter(w, 3)
    peak = float(np.percentile(sm[sm > 0], 95)) if (sm > 0).any() else 0.0
    out["mask"] = sm >= 0.5 * peak
    return out


def compare(test: np.ndarray, ref: np.ndarray, centres, step: int, sizes, blades: int) -> list:
    """Per emitter: orientation error (deg), axis length errors (%), ``n``-fold orientation
    error (deg, mod 360/n), IoU at half peak; ``test`` against ``ref`` (luminance)."""
    rows = []
    for c, s in zip(centres, sizes):
        a = shape_figures(test, c, step, s, blades)
        b = shape_figures(ref, c, step, s, blades)
        d_or = (a["orientation"] - b["orientation"] + 90.0) % 180.0 - 90.0
        inter = (a["mask"] & b["mask"]).sum()
        union = (a["mask"] | b["mask"]).sum()
        row = {"size": s, "orientation_ref": b["orientation"], "orientation_err_deg": d_or,
               "axes_ref": b["axes"].tolist(),
               "axis_err_pct": (100.0 * (a["axes"] / b["axes"] - 1.0)).tolist(),
               "iou": float(inter / max(union, 1))}
        if blades:
            period = 360.0 / blades
            row["nfold_ref"] = b["nfold"]
            row["nfold_err_deg"] = (a["nfold"] - b["nfold"] + period / 2) % period - period / 2
        rows.append(row)
    return rows
