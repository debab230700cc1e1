"""Card geometry in 3D, for Mitsuba: numpy only (no Mitsuba import).

Camera coordinates are OpenCV's and equal Mitsuba's world coordinates with the sensor
``look_at(origin=[0,0,0], target=[0,0,1], up=[0,-1,0])``: X right, Y down, Z forward
(scene units). A point projects (pinhole) to image coordinates ``x = f X / Z``,
``y = f Y / Z`` in pixels from the image centre, ``f = focal_length_px``.

A card's disparity plane ``d(x, y) = (1 - a x - b y) / c`` is the 3D plane
``Z = a f X + b f Y + c`` (Eq. 9), so the image point ``(x, y)`` back-projects onto the
card at ``Z = c / (1 - a x - b y)``, ``X = x Z / f``, ``Y = y Z / f``. Back-projecting
the four corners of the card's texture extent gives a planar quad whose pinhole
projection is exactly that extent (a projective map keeps straight lines straight).

Triangles are wound so that their geometric normal faces the camera (-Z side): a
one-sided Mitsuba area emitter on them is visible without ``flip_normals``.
"""

from __future__ import annotations

import numpy as np

from mpib_validate.runtime.camera import Camera
from mpib_validate.cards.scene import Card

#: Two triangles over the quad (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left),
#: wound towards the camera: normal = cross(p2 - p0, p1 - p0) points to -Z.
QUAD_FACES = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)


def back_project(card: Card, camera: Camera, x, y) -> np.ndarray:
    """3D points (scene units, float64, shape ``(..., 3)``) of the card's plane that
    project to image coordinates ``x, y`` (pixels from the image centre)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    p = card.plane
    z = p.c / (1.0 - p.a * x - p.b * y)
    f = float(camera.focal_length_px)
    return np.stack([x * z / f, y * z / f, z], axis=-1)


def extent(card: Card, camera: Camera, shift_x: float = 0.0) -> tuple[float, float, float, float]:
    """Texture extent ``(x0, x1, y0, y1)`` in pixels from the centre, moved right by
    ``shift_x`` pixels (0 except for the fault-injection tests)."""
    x0, x1, y0, y1 = card.extent(camera)
    return x0 + shift_x, x1 + shift_x, y0, y1


def quad(card: Card, camera: Camera, shift_x: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The card as two triangles: ``(vertices (4, 3) float64, uv (4, 2) float64)``.

    The uv of a vertex is its position in the texture, ``(0, 0)`` at the top-left
    corner of texel (0, 0) and ``(1, 1)`` at the bottom-right corner of the last texel
    (Mitsuba's bitmap convention: v = 0 is the first stored row). Interpolating uv over
    the triangles is exact only for fronto-parallel cards (an affine map); see
    :func:`texel_grid` for tilted ones.
    """
    x0, x1, y0, y1 = extent(card, camera, shift_x)
    xs = np.array([x0, x1, x1, x0])
    ys = np.array([y0, y0, y1, y1])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return back_project(card, camera, xs, ys), uv


def texel_grid(card: Card, camera: Camera, shift_x: float = 0.0):
    """The card as a grid with one quad (two triangles) per texel.

    Returns ``(vertices (V, 3) float64, uv (V, 2) float64, faces (F, 3) uint32)`` with
    ``V = (W_t + 1)(H_t + 1)`` and ``F = 2 W_t H_t``. Every texel's four corners are
    back-projected exactly and carry the texel's corner uv, so the affine uv inside a
    texel's triangles stays inside that texel: a nearest-texel lookup through mesh uv is
    then exact for tilted cards too (Mitsuba's stock plugins have no projective uv).
    """
    w, h = card.size
    x0, _, y0, _ = extent(card, camera, shift_x)
    cols = np.arange(w + 1, dtype=np.float64)
    rows = np.arange(h + 1, dtype=np.float64)
    cc, rr = np.meshgrid(cols, rows)  # (h+1, w+1)
    verts = back_project(card, camera, x0 + cc, y0 + rr).reshape(-1, 3)
    uv = np.stack([cc / w, rr / h], axis=-1).reshape(-1, 2)
    idx = np.arange((h + 1) * (w + 1), dtype=np.uint32).reshape(h + 1, w + 1)
    tl, tr = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    bl, br = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([tl, br, tr], -1), np.stack([tl, bl, br], -1)], axis=0)
    return verts, uv, faces.astype(np.uint32)


def depth_range(scene) -> tuple[float, float]:
    """Smallest and largest depth Z (scene units) over all cards' extents (at corners)."""
    zs = []
    for card in scene.cards:
        v, _ = quad(card, scene.camera)
        zs.append(v[:, 2])
    z = np.concatenate(zs)
    return float(z.min()), float(z.max())


def write_ply(path, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None) -> None:
    """Write a binary little-endian PLY mesh (float32 x y z [u v], int32 triangle lists)
    that Mitsuba's ``ply`` plugin reads."""
    from mpib_validate.runtime.io.atomic import atomic_path

    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces, np.int32)
    props = ["x", "y", "z"] + (["u", "v"] if uv is not None else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    header += [f"property float {p}" for p in props]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices",
               "end_header"]
    vdata = vertices if uv is None else np.concatenate([vertices, np.asarray(uv, np.float32)], 1)
    vrec = np.ascontiguousarray(vdata, dtype="<f4")
    frec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    frec["n"] = 3
    frec["i"] = faces
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(vrec.tobytes())
            fh.write(frec.tobytes())
