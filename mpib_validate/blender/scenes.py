"""Ordinary 3D Blender scenes (bpy, Cycles on the CPU): sharp passes and depth-of-field truth.

Every figure of the card suites comes from planar cards; artists render curved,
self-occluding objects, thin structures, small lights, ground planes and veils. This
module builds such scenes with ``bpy``, **parametric and seeded**: a
:class:`SceneSpec` (kind, seed, size, focus ``near``/``far``, lens, f-stop) fixes the
scene, so the suite grows by adding specs, not code. Kinds (:data:`KINDS`):

- ``suzanne``: Suzanne (self-occluding, subdivided, smooth) before a brick wall;
- ``spheres``: smooth checkered balls at several depths before a wall;
- ``fence``: thin structures before a wall: fence wires about 1.5 px wide, grass
  blades, hair-like strands (sub-pixel to 1 px ribbons);
- ``bokeh``: small HDR emitters (radiance 4-20, 2.4-6 px across) partly hidden by a
  pillar and a bar;
- ``ground``: a receding checkered ground plane with balls and boxes on it
  (continuous depth) under a sky;
- ``veil``: a semi-transparent sheet (Transparent mixed with diffuse) before a
  textured wall and a ball;
- ``emitters``: isolated fronto-parallel emitting disks (1 to 3 px across) on black,
  in front of and behind the focus plane: the radius and energy check.

Camera (as :mod:`mpib_validate.blender.cycles`, whose helpers build the render settings): at
the origin, turned 180 degrees about X, so world axes = camera axes (x right, y down,
looking down +Z) and the Z pass is planar depth; sensor fit horizontal,
``f_px = lens / sensor * W``, disk aperture of radius ``R = lens / (2 N)`` (metres,
1 unit = 1 m), so a point at disparity ``d = 1/Z`` blurs to radius ``A |d - d_f|``
pixels with ``A = R f_px``; Box pixel filter (1 px).

Shading is noise-free and view-independent, so the truth converges fast and the
layered model (one colour per surface point) is valid: diffuse albedo lit by one sun
of angle 0 (deterministic direction, hard shadows) plus a small emission
``ambient * albedo`` (so shadows are not black), ``max_bounces = 0`` (direct light
only); emitters and the ambient term have emission sampling off (they light nothing);
the world colour is seen by camera rays only (a Light Path "Is Camera Ray" mix) and is
not sampled as a light. Noise then comes only from sampling the pixel area and the
aperture (and, on the veil, Cycles' choice between its transparent and diffuse parts).

Renders per scene and focus (:func:`render_suite`):

- ``passes.exr``: what an artist renders: depth of field off, film opaque, Box filter,
  ``ViewLayer.Combined.R/G/B/A`` (unbiased sample subset) and ``ViewLayer.Depth.Z``
  from a separate 1-spp render (Cycles writes Z from sample 0, at the pixel centre);
  header attribute ``mpib`` = JSON ``{"camera": {...}}`` (``Camera.to_dict()`` plus the
  Blender lens settings), as ``mpib render`` writes it, so ``mpib refocus`` takes it;
- ``truth.exr``: Cycles' own depth of field, same camera and filter, two seeds:
  ``R, G, B, A`` = their mean, ``Seed0.*`` and ``Seed1.*`` each render, and
  ``Variance.R/G/B`` = ``(a - b)^2 / 4``, the per-value variance estimate of the mean;
- ``meta.json``: spec, ``A``, ``d_f``, lens, f-stop, noise figures, render times.

``bpy`` is imported inside the functions only; each build resets Blender to empty
factory settings.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

#: Bump when a scene's geometry, materials or render settings change: the cache key.
BUILDER_VERSION = 2
KINDS = ("suzanne", "spheres", "fence", "bokeh", "ground", "veil", "emitters")
FOCI = ("near", "far")
#: Scene kinds of the accuracy suite (``emitters`` is the radius and energy check).
SUITE_KINDS = KINDS[:6]
#: The sun: strength (W/m^2) and the direction its light travels (right, down, away).
SUN_STRENGTH = 2.5
SUN_DIRECTION = (0.35, 0.55, 0.76)
#: Emission added to every diffuse surface, as a fraction of its albedo (no light).
AMBIENT = 0.25
#: Reference width of the default f-stops: radii scale with the width (``f_px``).
REFERENCE_WIDTH = 320
#: Radiance and radius (px at 320 px wide) of the bokeh scene's emitters. Aperture
#: sampling of a small bright source is noisy: a pixel's samples hit it with probability
#: ``p = (s / r)^2`` (s its radius, r the blur radius), so the noise is
#: ``L sqrt(p (1 - p) / N)`` for a mean of ``L p``. Measured with radiance 20-200 and
#: 1-3 px across, the mean of two 1024-spp renders at 160x120 still had a PSNR of only
#: 31 dB (clipped); for the same mean, larger and dimmer emitters are less noisy
#: (``L / sqrt(p)`` at fixed ``L p``): radiance 4-20 (4x to 20x white) and 2.4 to 6 px
#: across give about 7 dB more.
BOKEH_STRENGTH = (4.0, 20.0)
BOKEH_RADIUS_PX = (1.2, 3.0)


# --------------------------------------------------------------------------------------
# The specification


@dataclass(frozen=True)
class SceneSpec:
    """One scene and focus. ``fstop`` None takes the kind's default (blur radii of about
    8 to 20 px at 320 px wide; radii scale with the width). ``blades``, ``rotation_deg``
    and ``ratio``: the camera's aperture (Blender's Blades, Rotation in degrees, Ratio;
    a disk by default)."""

    kind: str
    seed: int = 0
    width: int = 320
    height: int = 240
    focus: str = "far"
    lens_mm: float = 85.0
    sensor_mm: float = 36.0
    fstop: float | None = None
    blades: int = 0
    rotation_deg: float = 0.0
    ratio: float = 1.0

    @property
    def aperture(self):
        """The camera's :class:`~mpib_validate.runtime.camera.Aperture`."""
        from mpib_validate.runtime.camera import Aperture

        return Aperture(self.blades, math.radians(self.rotation_deg), self.ratio)

    def validate(self) -> "SceneSpec":
        if self.kind not in KINDS:
            raise ValueError(f"scene kind {self.kind!r}: choose from {', '.join(KINDS)}")
        if self.focus not in FOCI:
            raise ValueError(f"focus {self.focus!r}: choose 'near' or 'far'")
        if not (8 <= self.width <= 8192 and 8 <= self.height <= 8192):
            raise ValueError(f"size {self.width}x{self.height}: each side must be 8 to 8192")
        if not (self.lens_mm > 0 and self.sensor_mm > 0):
            raise ValueError("lens and sensor must be > 0 mm")
        if self.fstop is not None and not (0 < self.fstop < math.inf):
            raise ValueError(f"f-stop must be finite and > 0, got {self.fstop}")
        self.aperture  # noqa: B018 - raises ApertureError naming the field
        return self

    @property
    def name(self) -> str:
        f = "" if self.fstop is None else f"-f{self.fstop:g}"
        ap = self.aperture
        lens = "" if ap.is_disk else (f"-b{ap.blades}r{self.rotation_deg:g}" if ap.blades
                                      else "") + (f"-q{ap.ratio:g}" if ap.ratio != 1 else "")
        return f"{self.kind}-s{self.seed}-{self.focus}-{self.width}x{self.height}{f}{lens}"

    def to_dict(self) -> dict:
        """The fields; a disk's aperture fields are left out (a disk's cache keys are
        those of the suite before the aperture's shape)."""
        d = asdict(self)
        if self.aperture.is_disk:
            for k in ("blades", "rotation_deg", "ratio"):
                d.pop(k)
        return d

    def key(self, spp: int, sharp_spp: int | None = None) -> str:
        """Cache key: the spec, the truth's samples per seed (``spp`` times the kind's
        ``spp_factor``), the sharp pass's and :data:`BUILDER_VERSION`."""
        blob = json.dumps({"spec": self.to_dict(), "spp": truth_spp(self, spp),
                           "sharp_spp": int(sharp_spp or spp), "v": BUILDER_VERSION},
                          sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


def suite_specs(width: int = 320, height: int = 240, seed: int = 0, kinds=SUITE_KINDS) -> list:
    """Every kind in both focus variants."""
    return [SceneSpec(k, seed, width, height, f) for k in kinds for f in FOCI]


# --------------------------------------------------------------------------------------
# Layouts: pure descriptions (JSON-able), one function per kind


def _diffuse(c):
    return {"type": "diffuse", "colour": [float(v) for v in c]}


def _checker(c1, c2, scale):
    return {"type": "checker", "colour1": [float(v) for v in c1],
            "colour2": [float(v) for v in c2], "scale": float(scale)}


def _brick(c1, c2, mortar, brick_width, row_height, mortar_size):
    return {"type": "brick", "colour1": list(c1), "colour2": list(c2), "mortar": list(mortar),
            "brick_width": brick_width, "row_height": row_height, "mortar_size": mortar_size}


def _emitter(c, strength):
    return {"type": "emitter", "colour": [float(v) for v in c], "strength": float(strength)}


def _wall(z, half_w, half_h, mat, name="wall"):
    return {"name": name, "shape": "quad", "z": float(z), "half": [half_w, half_h], "mat": mat}


def _half_view(z, spec):
    """Half-width and half-height (m) of the view at depth z."""
    f = spec.lens_mm / spec.sensor_mm * spec.width
    return z * 0.5 * spec.width / f, z * 0.5 * spec.height / f


def _px(z, spec):
    """Metres per pixel at depth z at the reference width (thin parts keep their pixel
    widths at 320 px and scale with the image)."""
    return z / (spec.lens_mm / spec.sensor_mm * REFERENCE_WIDTH)


def _layout_suzanne(rng, spec):
    zw = 2.2
    hw, hh = _half_view(zw, spec)
    objs = [_wall(zw, 2 * hw, 2 * hh, _brick([0.55, 0.22, 0.12], [0.42, 0.3, 0.2], [0.75] * 3,
                                              0.12, 0.05, 0.006))]
    objs.append({"name": "suzanne", "shape": "monkey", "loc": [float(rng.uniform(-0.03, 0.03)),
                                                               float(rng.uniform(-0.01, 0.02)), 1.0],
                 "size": 0.095, "yaw": float(rng.uniform(-0.5, 0.5)),
                 "mat": _diffuse([0.8, 0.55, 0.25])})
    return {"objects": objs, "focus": {"near": 1.0, "far": zw}, "fstop": 1.1,
            "world": [0.0, 0.0, 0.0]}


def _layout_spheres(rng, spec):
    zw = 4.0
    hw, hh = _half_view(zw, spec)
    objs = [_wall(zw, 2 * hw, 2 * hh, _checker([0.2, 0.35, 0.5], [0.6, 0.6, 0.55], 8.0))]
    depths = [1.0, 1.5, 2.2, 3.0]
    xs = rng.permutation(np.linspace(-0.7, 0.7, len(depths)))
    for i, (z, u) in enumerate(zip(depths, xs)):
        hwz, hhz = _half_view(z, spec)
        r = 0.1 * z * (0.9 + 0.3 * rng.random())
        col = rng.uniform(0.2, 0.85, 3)
        objs.append({"name": f"ball{i}", "shape": "sphere",
                     "loc": [float(u * hwz), float(rng.uniform(-0.4, 0.4) * hhz), z + r],
                     "radius": float(r),
                     "mat": _checker(col, 0.4 * col, float(3.0 / r))})
    return {"objects": objs, "focus": {"near": 1.0, "far": zw}, "fstop": 1.5,
            "world": [0.0, 0.0, 0.0]}


def _layout_fence(rng, spec):
    zw, zf = 3.0, 1.3
    hw, hh = _half_view(zw, spec)
    objs = [_wall(zw, 2 * hw, 2 * hh, _brick([0.45, 0.35, 0.28], [0.3, 0.38, 0.45], [0.6] * 3,
                                              0.2, 0.08, 0.01))]
    fw, fh = _half_view(zf, spec)
    wire_r = 0.75 * _px(zf, spec)  # 1.5 px across at 320 px wide
    tubes = []
    step = 0.06
    x0 = -fw * 1.3 + rng.uniform(0, step)
    while x0 < fw * 1.3:
        tubes.append([[x0, -fh * 1.3, zf], [x0 + 0.02 * rng.standard_normal(), fh * 0.35, zf]])
        x0 += step
    y0 = -fh * 1.3 + rng.uniform(0, step)
    while y0 < fh * 0.35:
        tubes.append([[-fw * 1.3, y0, zf], [fw * 1.3, y0 + 0.01 * rng.standard_normal(), zf]])
        y0 += step
    objs.append({"name": "fence", "shape": "tubes", "tubes": tubes, "radius": float(wire_r),
                 "mat": _diffuse([0.08, 0.08, 0.09])})
    blades = []
    for _ in range(60):
        z = float(rng.uniform(1.0, 1.6))
        bw, bh = _half_view(z, spec)
        x = float(rng.uniform(-1.1, 1.1) * bw)
        base = bh * 1.05
        height = float(rng.uniform(0.25, 0.6) * bh)
        width = float(rng.uniform(1.5, 4.0)) * _px(z, spec)
        lean = float(rng.uniform(-0.4, 0.4) * height)
        blades.append([[x - width / 2, base, z], [x + width / 2, base, z],
                       [x + lean, base - height, z + float(rng.uniform(-0.05, 0.05))]])
    objs.append({"name": "grass", "shape": "triangles", "triangles": blades,
                 "mat": _diffuse([0.3, 0.6, 0.15])})
    strands = []
    for _ in range(14):
        z = float(rng.uniform(0.9, 1.1))
        sw, sh = _half_view(z, spec)
        x = float(rng.uniform(-1.0, -0.2) * sw)
        pts = []
        n = 12
        amp = float(rng.uniform(0.02, 0.08))
        ph = float(rng.uniform(0, 2 * math.pi))
        for k in range(n):
            t = k / (n - 1)
            pts.append([x + amp * math.sin(3 * t + ph), -sh * 1.1 + t * sh * 1.4, z])
        width = float(rng.uniform(0.5, 1.2)) * _px(z, spec)
        strands.append({"points": pts, "width": width})
    objs.append({"name": "strands", "shape": "ribbons", "ribbons": strands,
                 "mat": _diffuse([0.95, 0.85, 0.55])})
    return {"objects": objs, "focus": {"near": zf, "far": zw}, "fstop": 1.2,
            "world": [0.0, 0.0, 0.0]}


def _layout_bokeh(rng, spec):
    zw, zp = 5.0, 1.2
    hw, hh = _half_view(zw, spec)
    objs = [_wall(zw, 2 * hw, 2 * hh, _brick([0.06, 0.05, 0.05], [0.1, 0.08, 0.06], [0.15] * 3,
                                              0.25, 0.1, 0.012))]
    ph, pv = _half_view(zp, spec)
    cx = float(rng.uniform(-0.15, 0.15) * ph)
    objs.append({"name": "pillar", "shape": "box", "centre": [cx, 0.0, zp + 0.05],
                 "half": [0.22 * ph, 2 * pv, 0.05], "mat": _checker([0.5, 0.45, 0.4],
                                                                   [0.3, 0.27, 0.25], 25.0)})
    objs.append({"name": "bar", "shape": "box", "centre": [0.0, 0.55 * pv, zp + 0.25],
                 "half": [2 * ph, 0.06 * pv, 0.03], "mat": _diffuse([0.35, 0.4, 0.45])})
    for i in range(22):
        z = float(rng.uniform(2.6, 3.6))
        ew, eh = _half_view(z, spec)
        r = float(rng.uniform(*BOKEH_RADIUS_PX)) * _px(z, spec)
        col = rng.uniform(0.4, 1.0, 3)
        col = col / col.max()
        objs.append({"name": f"light{i}", "shape": "sphere",
                     "loc": [float(rng.uniform(-0.9, 0.9) * ew), float(rng.uniform(-0.8, 0.8) * eh), z],
                     "radius": r, "mat": _emitter(col, float(rng.uniform(*BOKEH_STRENGTH)))})
    # the emitters' aperture noise (see BOKEH_STRENGTH): 4x the samples, 6 dB less noise
    return {"objects": objs, "focus": {"near": zp, "far": 3.0}, "fstop": 1.3,
            "world": [0.0, 0.0, 0.0], "spp_factor": 4}


def _layout_ground(rng, spec):
    h = 0.25  # ground 0.25 m below the camera (world +Y is down)
    objs = [{"name": "ground", "shape": "ground", "y": h, "z": [0.5, 60.0], "half_x": 40.0,
             "mat": _checker([0.75, 0.72, 0.65], [0.15, 0.2, 0.25], 4.0)}]
    for i, z in enumerate((2.0, 3.5, 6.0, 10.0)):
        gw, _ = _half_view(z, spec)
        x = float(rng.uniform(-0.7, 0.7) * gw)
        col = rng.uniform(0.2, 0.85, 3)
        if i % 2 == 0:
            r = 0.12 * z / 2.0
            objs.append({"name": f"ball{i}", "shape": "sphere", "loc": [x, h - r, z], "radius": r,
                         "mat": _checker(col, 0.5 * col, float(2.5 / r))})
        else:
            s = 0.1 * z / 2.0
            objs.append({"name": f"box{i}", "shape": "box", "centre": [x, h - s, z + s],
                         "half": [s, s, s], "yaw": float(rng.uniform(0, 1.5)),
                         "mat": _diffuse(col)})
    return {"objects": objs, "focus": {"near": 2.0, "far": 6.0}, "fstop": 1.0,
            "world": [0.45, 0.6, 0.85]}


def _layout_veil(rng, spec):
    zw, zv = 3.0, 1.3
    hw, hh = _half_view(zw, spec)
    objs = [_wall(zw, 2 * hw, 2 * hh, _checker([0.8, 0.25, 0.2], [0.2, 0.5, 0.7], 10.0))]
    vw, vh = _half_view(zv, spec)
    objs.append({"name": "veil", "shape": "quad", "z": zv, "half": [0.55 * vw, 0.6 * vh],
                 "offset": [float(rng.uniform(-0.2, 0.2) * vw), float(rng.uniform(-0.1, 0.1) * vh)],
                 "mat": {"type": "veil", "colour": [0.9, 0.9, 0.8], "opacity": 0.6}})
    bw, bh = _half_view(2.0, spec)
    objs.append({"name": "ball", "shape": "sphere", "loc": [float(0.5 * bw), float(0.2 * bh), 2.0],
                 "radius": 0.2, "mat": _diffuse([0.3, 0.7, 0.3])})
    return {"objects": objs, "focus": {"near": zv, "far": zw}, "fstop": 0.9,
            "world": [0.0, 0.0, 0.0]}


#: Depths of the isolated emitters (m) and of the focus variants.
EMITTER_DEPTHS = (1.2, 4.0)
EMITTER_FOCUS = {"near": 1.6, "far": 2.5}
#: Diameters of the isolated emitting disks in pixels at the spec's width.
EMITTER_DIAMETERS_PX = (1.0, 1.5, 2.0, 3.0)


def emitter_grid(spec: SceneSpec, step: int | None = None) -> tuple[list[dict], int]:
    """The isolated emitters of an ``emitters`` spec: each ``{"row", "col", "z",
    "diameter_px"}`` (the disk centre's pixel) on a grid of ``step`` px (each owns a
    ``step`` x ``step`` window); depths alternate along rows and columns."""
    if step is None:
        step = max(24, spec.width // 8)
    rng = np.random.default_rng(spec.seed)
    out = []
    ny, nx = spec.height // step, spec.width // step
    for i in range(ny):
        for j in range(nx):
            k = i * nx + j
            out.append({"row": int(i * step + step // 2 + rng.integers(-1, 2)),
                        "col": int(j * step + step // 2 + rng.integers(-1, 2)),
                        "z": float(EMITTER_DEPTHS[(i + j) % 2]),
                        "diameter_px": float(EMITTER_DIAMETERS_PX[k % len(EMITTER_DIAMETERS_PX)])})
    return out, step


def _layout_emitters(rng, spec):
    f = spec.lens_mm / spec.sensor_mm * spec.width
    objs = []
    dots, _ = emitter_grid(spec)
    for k, e in enumerate(dots):
        z = e["z"]
        x = (e["col"] + 0.5 - spec.width / 2) * z / f
        y = (e["row"] + 0.5 - spec.height / 2) * z / f
        objs.append({"name": f"dot{k}", "shape": "disk", "loc": [x, y, z],
                     "radius": 0.5 * e["diameter_px"] * z / f, "mat": _emitter([1, 1, 1], 1.0)})
    # energies to 1 % need less noise than the suite's scenes; on black they are cheap
    return {"objects": objs, "focus": dict(EMITTER_FOCUS), "fstop": 1.4,
            "world": [0.0, 0.0, 0.0], "sun": False, "spp_factor": 4}


_LAYOUTS = {"suzanne": _layout_suzanne, "spheres": _layout_spheres, "fence": _layout_fence,
            "bokeh": _layout_bokeh, "ground": _layout_ground, "veil": _layout_veil,
            "emitters": _layout_emitters}


def layout(spec: SceneSpec) -> dict:
    """The scene of ``spec`` as plain data (objects, materials, focus depths, default
    f-stop, world colour); the same spec always gives the same layout."""
    spec.validate()
    rng = np.random.default_rng([spec.seed, KINDS.index(spec.kind)])
    return _LAYOUTS[spec.kind](rng, spec)


def truth_spp(spec: SceneSpec, spp: int) -> int:
    """Samples per seed of ``spec``'s truth: ``spp`` times the kind's ``spp_factor``."""
    return int(spp) * int(layout(spec).get("spp_factor", 1))


def lens(spec: SceneSpec) -> dict:
    """The camera of ``spec``: Blender settings and the image-space form.

    ``f_px = lens / sensor * W``, ``R = lens / (2 N)`` (m), ``A = R f_px`` (px per 1/m),
    ``d_f = 1 / z_f`` with ``z_f`` the kind's near or far focus depth (m)."""
    lay = layout(spec)
    fstop = float(spec.fstop if spec.fstop is not None else lay["fstop"])
    z_f = float(lay["focus"][spec.focus])
    f_px = spec.lens_mm / spec.sensor_mm * spec.width
    A = spec.lens_mm * 1e-3 / (2.0 * fstop) * f_px
    return {"lens_mm": float(spec.lens_mm), "sensor_width_mm": float(spec.sensor_mm),
            "sensor_fit": "HORIZONTAL", "fstop": fstop, "focus_distance": z_f,
            "unit_scale": 1.0, "focal_length_px": f_px, "blur_parameter": A,
            "focus_disparity": 1.0 / z_f, "width": spec.width, "height": spec.height,
            "aperture_blades": spec.blades, "aperture_rotation": math.radians(spec.rotation_deg),
            "aperture_ratio": spec.ratio}


def camera(spec: SceneSpec):
    """The :class:`~mpib_validate.runtime.camera.Camera` of ``spec``."""
    from mpib_validate.runtime.camera import Camera

    c = lens(spec)
    return Camera(spec.width, spec.height, c["blur_parameter"], c["focus_disparity"],
                  c["focal_length_px"], spec.aperture)


# --------------------------------------------------------------------------------------
# Meshes (numpy; world coordinates = camera coordinates)


def _quad(z, half, offset=(0.0, 0.0)):
    hx, hy = half
    ox, oy = offset
    v = [(ox - hx, oy - hy, z), (ox + hx, oy - hy, z), (ox + hx, oy + hy, z), (ox - hx, oy + hy, z)]
    return v, [(0, 1, 2, 3)]


def _uv_sphere(centre, r, nu=48, nv=24):
    cx, cy, cz = centre
    verts = [(cx, cy - r, cz)]
    for i in range(1, nv):
        th = math.pi * i / nv
        for j in range(nu):
            ph = 2 * math.pi * j / nu
            verts.append((cx + r * math.sin(th) * math.cos(ph), cy - r * math.cos(th),
                          cz + r * math.sin(th) * math.sin(ph)))
    verts.append((cx, cy + r, cz))
    faces = []
    for j in range(nu):
        faces.append((0, 1 + (j + 1) % nu, 1 + j))
    for i in range(nv - 2):
        a, b = 1 + i * nu, 1 + (i + 1) * nu
        for j in range(nu):
            k = (j + 1) % nu
            faces.append((a + j, a + k, b + k, b + j))
    last = len(verts) - 1
    base = 1 + (nv - 2) * nu
    for j in range(nu):
        faces.append((base + j, base + (j + 1) % nu, last))
    return verts, faces


def _box(centre, half, yaw=0.0):
    cx, cy, cz = centre
    hx, hy, hz = half
    c, s = math.cos(yaw), math.sin(yaw)
    verts = []
    for dz in (-hz, hz):
        for dy in (-hy, hy):
            for dx in (-hx, hx):
                verts.append((cx + c * dx + s * dz, cy + dy, cz - s * dx + c * dz))
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return verts, faces


def _disk(centre, r, n=32):
    cx, cy, cz = centre
    verts = [(cx, cy, cz)] + [(cx + r * math.cos(2 * math.pi * k / n),
                               cy + r * math.sin(2 * math.pi * k / n), cz) for k in range(n)]
    return verts, [(0, 1 + k, 1 + (k + 1) % n) for k in range(n)]


def _tubes(tubes, r, n=8):
    verts, faces = [], []
    for p0, p1 in tubes:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        axis = p1 - p0
        axis /= np.linalg.norm(axis)
        u = np.cross(axis, [0.0, 0.0, 1.0])
        u /= np.linalg.norm(u)
        w = np.cross(axis, u)
        base = len(verts)
        for p in (p0, p1):
            for k in range(n):
                a = 2 * math.pi * k / n
                verts.append(tuple(p + r * (math.cos(a) * u + math.sin(a) * w)))
        for k in range(n):
            k1 = (k + 1) % n
            faces.append((base + k, base + k1, base + n + k1, base + n + k))
    return verts, faces


def _ribbons(ribbons):
    verts, faces = [], []
    for rb in ribbons:
        pts = np.asarray(rb["points"], float)
        half = 0.5 * rb["width"]
        base = len(verts)
        for k, p in enumerate(pts):
            t = pts[min(k + 1, len(pts) - 1)] - pts[max(k - 1, 0)]
            nrm = np.array([-t[1], t[0], 0.0])
            nrm /= np.linalg.norm(nrm)
            verts += [tuple(p - half * nrm), tuple(p + half * nrm)]
        for k in range(len(pts) - 1):
            a = base + 2 * k
            faces.append((a, a + 1, a + 3, a + 2))
    return verts, faces


def _ground(y, z, half_x):
    z0, z1 = z
    return [(-half_x, y, z0), (half_x, y, z0), (half_x, y, z1), (-half_x, y, z1)], [(0, 1, 2, 3)]


def mesh_of(obj: dict):
    """``(verts, faces, smooth)`` of a layout object (not ``monkey``)."""
    s = obj["shape"]
    if s == "quad":
        return (*_quad(obj["z"], obj["half"], obj.get("offset", (0.0, 0.0))), False)
    if s == "sphere":
        return (*_uv_sphere(obj["loc"], obj["radius"]), True)
    if s == "box":
        return (*_box(obj["centre"], obj["half"], obj.get("yaw", 0.0)), False)
    if s == "disk":
        return (*_disk(obj["loc"], obj["radius"]), False)
    if s == "tubes":
        return (*_tubes(obj["tubes"], obj["radius"]), True)
    if s == "triangles":
        tris = obj["triangles"]
        return [tuple(p) for t in tris for p in t], [(3 * i, 3 * i + 1, 3 * i + 2)
                                                     for i in range(len(tris))], False
    if s == "ribbons":
        return (*_ribbons(obj["ribbons"]), False)
    if s == "ground":
        return (*_ground(obj["y"], obj["z"], obj["half_x"]), False)
    raise ValueError(f"unknown shape {s!r}")


# --------------------------------------------------------------------------------------
# bpy adapter


def _material(bpy, name: str, m: dict):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    mat.cycles.emission_sampling = "NONE"  # emitters and the ambient term light nothing
    nt = mat.node_tree
    nt.nodes.clear()
    N, L = nt.nodes, nt.links
    out = N.new("ShaderNodeOutputMaterial")
    out.target = "CYCLES"
    t = m["type"]
    if t == "emitter":
        em = N.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (*m["colour"], 1.0)
        em.inputs["Strength"].default_value = m["strength"]
        L.new(em.outputs[0], out.inputs["Surface"])
        return mat
    if t in ("checker", "brick"):
        tc = N.new("ShaderNodeTexCoord")
        off = N.new("ShaderNodeVectorMath")  # off the checker's cell faces (no parity flips)
        off.operation = "ADD"
        off.inputs[1].default_value = (0.0123, 0.0217, 0.0311)
        L.new(tc.outputs["Object"], off.inputs[0])
        if t == "checker":
            tex = N.new("ShaderNodeTexChecker")
            tex.inputs["Color1"].default_value = (*m["colour1"], 1.0)
            tex.inputs["Color2"].default_value = (*m["colour2"], 1.0)
            tex.inputs["Scale"].default_value = m["scale"]
        else:
            tex = N.new("ShaderNodeTexBrick")
            tex.inputs["Color1"].default_value = (*m["colour1"], 1.0)
            tex.inputs["Color2"].default_value = (*m["colour2"], 1.0)
            tex.inputs["Mortar"].default_value = (*m["mortar"], 1.0)
            tex.inputs["Scale"].default_value = 1.0
            tex.inputs["Mortar Size"].default_value = m["mortar_size"]
            tex.inputs["Mortar Smooth"].default_value = 0.0
            tex.inputs["Bias"].default_value = 0.0
            tex.inputs["Brick Width"].default_value = m["brick_width"]
            tex.inputs["Row Height"].default_value = m["row_height"]
        L.new(off.outputs[0], tex.inputs["Vector"])
        albedo = tex.outputs["Color"]
    else:
        rgb = N.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = (*m["colour"], 1.0)
        albedo = rgb.outputs[0]
    dif = N.new("ShaderNodeBsdfDiffuse")
    dif.inputs["Roughness"].default_value = 0.0  # Lambert
    L.new(albedo, dif.inputs["Color"])
    amb = N.new("ShaderNodeEmission")
    amb.inputs["Strength"].default_value = AMBIENT
    L.new(albedo, amb.inputs["Color"])
    add = N.new("ShaderNodeAddShader")
    L.new(dif.outputs[0], add.inputs[0])
    L.new(amb.outputs[0], add.inputs[1])
    shader = add.outputs[0]
    if t == "veil":
        tr = N.new("ShaderNodeBsdfTransparent")
        tr.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        mix = N.new("ShaderNodeMixShader")
        mix.inputs["Fac"].default_value = m["opacity"]
        L.new(tr.outputs[0], mix.inputs[1])
        L.new(shader, mix.inputs[2])
        shader = mix.outputs[0]
    L.new(shader, out.inputs["Surface"])
    return mat


def _camera_world(bpy, bl, colour):
    """The world: ``colour`` for camera rays only (Is Camera Ray), black for any other
    ray, and never sampled as a light."""
    world = bpy.data.worlds.new("World")
    if world.node_tree is None:
        world.use_nodes = True
    world.cycles.sampling_method = "NONE"
    nt = world.node_tree
    nt.nodes.clear()
    N, L = nt.nodes, nt.links
    out = N.new("ShaderNodeOutputWorld")
    lp = N.new("ShaderNodeLightPath")
    dark = N.new("ShaderNodeBackground")
    dark.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    dark.inputs["Strength"].default_value = 0.0
    sky = N.new("ShaderNodeBackground")
    sky.inputs["Color"].default_value = (*colour, 1.0)
    sky.inputs["Strength"].default_value = 1.0
    mix = N.new("ShaderNodeMixShader")
    L.new(lp.outputs["Is Camera Ray"], mix.inputs["Fac"])
    L.new(dark.outputs[0], mix.inputs[1])
    L.new(sky.outputs[0], mix.inputs[2])
    L.new(mix.outputs[0], out.inputs["Surface"])
    bl.world = world
    return world


def _sun(bpy, bl):
    from mathutils import Vector

    data = bpy.data.lights.new("Sun", "SUN")
    data.energy = SUN_STRENGTH
    data.angle = 0.0  # a point source at infinity: one deterministic shadow ray
    obj = bpy.data.objects.new("Sun", data)
    obj.rotation_mode = "QUATERNION"
    # a sun shines along its local -Z
    obj.rotation_quaternion = Vector(SUN_DIRECTION).normalized().to_track_quat("-Z", "Y")
    bl.collection.objects.link(obj)
    return obj


def _object(bpy, bl, obj: dict):
    mat = _material(bpy, obj["name"], obj["mat"])
    if obj["shape"] == "monkey":
        import bmesh

        mesh = bpy.data.meshes.new(obj["name"])
        bm = bmesh.new()
        bmesh.ops.create_monkey(bm)
        bm.to_mesh(mesh)
        bm.free()
        for p in mesh.polygons:
            p.use_smooth = True
        ob = bpy.data.objects.new(obj["name"], mesh)
        ob.location = obj["loc"]
        ob.scale = (obj["size"],) * 3
        # Suzanne looks down her local -Y with +Z up: +90 degrees about X turns her to
        # look at the camera (world -Z) with her top up (world -Y); then a yaw about Y
        ob.rotation_euler = (math.pi / 2, obj["yaw"], 0.0)
        mod = ob.modifiers.new("subsurf", "SUBSURF")
        mod.levels = mod.render_levels = 2
    else:
        verts, faces, smooth = mesh_of(obj)
        mesh = bpy.data.meshes.new(obj["name"])
        mesh.from_pydata([tuple(map(float, v)) for v in verts], [], faces)
        mesh.update()
        if smooth:
            for p in mesh.polygons:
                p.use_smooth = True
        ob = bpy.data.objects.new(obj["name"], mesh)
    mesh.materials.append(mat)
    bl.collection.objects.link(ob)
    return ob


def build(spec: SceneSpec, spp: int, seed: int = 0, dof: bool = True, *, depth_pass: bool = False,
          unbiased: bool = True, threads: int = 0):
    """Replace Blender's data with the Cycles scene of ``spec``; returns the bpy scene.

    ``dof`` False is the artist's sharp render; ``depth_pass`` adds the Z pass (render
    it at 1 spp with ``unbiased`` False: Z comes from sample 0 at the pixel centre)."""
    from mpib_validate.blender import cycles

    bpy = cycles._bpy()
    spec.validate()
    lay = layout(spec)
    bl = cycles._reset(bpy)
    cycles.configure_render(bl, spec.width, spec.height, spp, seed, threads=threads,
                            unbiased=unbiased, transparent_bounces=16, film_transparent=False)
    cycles.configure_passes(bl, depth_pass)
    _camera_world(bpy, bl, lay["world"])
    c = lens(spec)
    cycles.camera_object(bpy, bl, c, dof, clip_end=1e3)
    if lay.get("sun", True):
        _sun(bpy, bl)
    for obj in lay["objects"]:
        _object(bpy, bl, obj)
    return bl


# --------------------------------------------------------------------------------------
# Renders, noise, files


def _render(spec, spp, seed, dof, tmp, name, **kw):
    from mpib_validate.blender import cycles

    t0 = time.perf_counter()
    bl = build(spec, spp, seed, dof, **kw)
    build_s = time.perf_counter() - t0
    path = Path(tmp) / f"{name}.exr"
    seconds = cycles.render_exr(bl, path)
    rgba, z = cycles.read_render(path)
    return rgba, z, {"seconds": seconds, "build_seconds": build_s}


def render_sharp(spec: SceneSpec, spp: int, threads: int = 0, tmp=None) -> dict:
    """The artist's passes: ``rgba`` (depth of field off, ``spp`` samples, unbiased
    subset, film opaque) and ``depth`` (Z pass of a 1-spp render: pixel centres)."""
    with tempfile.TemporaryDirectory(prefix="mpib-bl-") as t:
        d = tmp or t
        rgba, _, m1 = _render(spec, spp, 0, False, d, "sharp", threads=threads)
        _, z, m2 = _render(spec, 1, 0, False, d, "depth", depth_pass=True, unbiased=False,
                           threads=threads)
    return {"rgba": rgba, "depth": z, "seconds": m1["seconds"], "depth_seconds": m2["seconds"],
            "build_seconds": m1["build_seconds"] + m2["build_seconds"]}


#: Cycles seeds of the two truth renders (any third seed is independent of both).
TRUTH_SEEDS = (1, 2)


def render_truth(spec: SceneSpec, spp: int, seeds=TRUTH_SEEDS, threads: int = 0) -> dict:
    """Cycles' depth of field at ``spp`` samples for each seed: ``renders`` (K, H, W, 4)
    and the times."""
    imgs, secs, builds = [], [], []
    with tempfile.TemporaryDirectory(prefix="mpib-bl-") as tmp:
        for s in seeds:
            rgba, _, m = _render(spec, spp, int(s), True, tmp, f"truth{s}", threads=threads)
            imgs.append(rgba)
            secs.append(m["seconds"])
            builds.append(m["build_seconds"])
    return {"renders": np.stack(imgs), "seconds": secs, "build_seconds": builds}


def noise_figures(a: np.ndarray, b: np.ndarray) -> dict:
    """Noise of the mean of two independent renders ``a``, ``b`` (RGB).

    Per value the mean's variance is estimated by ``(a - b)^2 / 4`` (each render has
    variance ``sigma^2``, estimated by ``(a - b)^2 / 2``; the mean ``sigma^2 / 2``).
    ``rmse`` = ``sqrt(mean((a - b)^2) / 4)`` (linear radiance) and ``psnr`` =
    ``-20 log10(rmse)`` (peak 1); ``*_clipped`` the same on values clipped to [0, 1],
    as the accuracy metrics see them; ``single_*``: one render's (``sqrt 2`` more)."""
    a = np.asarray(a, np.float64)[..., :3]
    b = np.asarray(b, np.float64)[..., :3]
    out = {}
    for tag, x, y in (("", a, b), ("_clipped", np.clip(a, 0, 1), np.clip(b, 0, 1))):
        ms = float(((x - y) ** 2).mean())
        rm = math.sqrt(ms / 4.0)
        out[f"rmse{tag}"] = rm
        out[f"psnr{tag}"] = math.inf if rm == 0 else -20.0 * math.log10(rm)
        out[f"single_rmse{tag}"] = math.sqrt(ms / 2.0)
    return out


def passes_header(spec: SceneSpec) -> dict:
    """The ``mpib`` header attribute of ``passes.exr``: ``{"camera": ...}`` with the
    image-space camera (``Camera.to_dict()``) and the Blender lens settings under
    ``blender`` (the schema of :mod:`mpib_validate.runtime.io.camera_header`), so ``mpib refocus
    passes.exr`` needs no lens options."""
    c = lens(spec)
    blender = {k: c[k] for k in ("lens_mm", "sensor_width_mm", "sensor_fit", "fstop",
                                 "focus_distance", "unit_scale", "width", "height")}
    blender["sensor_height_mm"] = 24.0  # Blender's default; unused with fit HORIZONTAL
    if not spec.aperture.is_disk:
        blender.update({k: c[k] for k in ("aperture_blades", "aperture_rotation",
                                          "aperture_ratio")})
    return {"camera": {**camera(spec).to_dict(), "blender": blender},
            "engine": "cycles", "scene": spec.to_dict()}


def write_passes(path, rgba, depth, spec) -> None:
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    ch = channels_from_rgba(np.asarray(rgba, np.float32), "ViewLayer.Combined.")
    ch["ViewLayer.Depth.Z"] = np.asarray(depth, np.float32)
    write_exr(path, ch, attributes={"mpib": json.dumps(passes_header(spec))})


def write_truth(path, renders, spec, meta) -> None:
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    r = np.asarray(renders, np.float64)
    mean = r.mean(axis=0).astype(np.float32)
    ch = channels_from_rgba(mean)
    for k in range(r.shape[0]):
        ch.update(channels_from_rgba(r[k].astype(np.float32), f"Seed{k}."))
    var = ((r[0, ..., :3] - r[1, ..., :3]) ** 2 / 4.0).astype(np.float32)
    for i, c in enumerate("RGB"):
        ch[f"Variance.{c}"] = var[..., i]
    write_exr(path, ch, attributes={"mpib": json.dumps({"camera": passes_header(spec)["camera"],
                                                        "truth": meta}, default=float)})


@dataclass
class SuiteScene:
    """One rendered scene+focus folder, read back."""

    spec: SceneSpec
    folder: Path
    meta: dict
    colour: np.ndarray  # (H, W, 3) sharp Combined
    depth: np.ndarray  # (H, W) Z pass
    truth: np.ndarray  # (H, W, 3) mean of the two seeds
    seeds: np.ndarray  # (2, H, W, 3)
    variance: np.ndarray  # (H, W, 3) per-value variance of the mean


def load_scene(folder) -> SuiteScene:
    """Read a folder written by :func:`render_suite`."""
    from mpib_validate.runtime.io.exr import read_exr, rgba_from

    folder = Path(folder)
    meta = json.loads((folder / "meta.json").read_text())
    p = read_exr(folder / "passes.exr")
    t = read_exr(folder / "truth.exr")
    colour = rgba_from(p, "ViewLayer.Combined.")[..., :3]
    depth = np.asarray(p.channels["ViewLayer.Depth.Z"], np.float64)
    seeds = np.stack([rgba_from(t, f"Seed{k}.")[..., :3] for k in range(2)])
    var = np.stack([t.channels[f"Variance.{c}"] for c in "RGB"], axis=-1)
    return SuiteScene(SceneSpec(**meta["spec"]), folder, meta, colour, depth,
                      rgba_from(t)[..., :3], seeds, var)


def _complete(folder: Path, key: str) -> bool:
    m = folder / "meta.json"
    if not (m.is_file() and (folder / "passes.exr").is_file() and (folder / "truth.exr").is_file()):
        return False
    try:
        return json.loads(m.read_text()).get("key") == key
    except ValueError:
        return False


def folder_name(spec: SceneSpec, spp: int) -> str:
    return f"{spec.name}-{int(spp)}spp"


def render_suite(out_dir, specs, spp: int, sharp_spp: int | None = None, threads: int = 0,
                 log=print) -> list[Path]:
    """Render each spec into ``out_dir/<name>-<spp>spp/`` (``passes.exr``, ``truth.exr``,
    ``meta.json``) unless a folder with the same key is there already (a cache). Files
    are written atomically, ``meta.json`` last (its key marks the folder complete).

    ``spp`` is the truth's samples per seed, times the kind's ``spp_factor`` (4 for the
    bokeh scene, whose small emitters are the noisiest, and for the isolated emitters). The sharp passes do not depend
    on the focus: the two focus variants of a scene
    (same everything but ``focus``) share one sharp render. ``sharp_spp``: samples of
    the sharp Combined pass (default ``spp``). Returns the folders in ``specs`` order."""
    from mpib_validate.runtime.io.atomic import write_text

    out_dir = Path(out_dir)
    sharp_spp = int(sharp_spp or spp)
    folders, sharp_cache = [], {}
    for spec in specs:
        spec.validate()
        key = spec.key(spp, sharp_spp)
        folder = out_dir / folder_name(spec, spp)
        folders.append(folder)
        if _complete(folder, key):
            continue
        sk = replace(spec, focus="far", fstop=None)
        if sk not in sharp_cache:
            log(f"blender scenes: {spec.name}: sharp passes ({sharp_spp} spp) ...")
            sharp_cache = {sk: render_sharp(spec, sharp_spp, threads)}  # keep one at a time
        sharp = sharp_cache[sk]
        t_spp = truth_spp(spec, spp)
        log(f"blender scenes: {spec.name}: truth (depth of field, {t_spp} spp x 2 seeds) ...")
        truth = render_truth(spec, t_spp, threads=threads)
        noise = noise_figures(truth["renders"][0], truth["renders"][1])
        c = lens(spec)
        meta = {"key": key, "spec": spec.to_dict(), "builder_version": BUILDER_VERSION,
                "spp": int(spp), "truth_spp": t_spp, "sharp_spp": sharp_spp, "truth_seeds": list(TRUTH_SEEDS),
                "A": c["blur_parameter"], "d_f": c["focus_disparity"],
                "focus_distance": c["focus_distance"], "lens_mm": c["lens_mm"],
                "sensor_width_mm": c["sensor_width_mm"], "fstop": c["fstop"],
                "focal_length_px": c["focal_length_px"], "noise": noise,
                "seconds": {"sharp": sharp["seconds"], "depth": sharp["depth_seconds"],
                            "truth": truth["seconds"], "build_sharp": sharp["build_seconds"],
                            "build_truth": truth["build_seconds"]},
                "blender": _blender_version()}
        if folder.exists() and not (folder / "meta.json").is_file():
            shutil.rmtree(folder)  # an interrupted earlier attempt
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "meta.json").unlink(missing_ok=True)  # incomplete until rewritten
        write_passes(folder / "passes.exr", sharp["rgba"], sharp["depth"], spec)
        write_truth(folder / "truth.exr", truth["renders"], spec, meta)
        write_text(folder / "meta.json", json.dumps(meta, indent=2, default=float) + "\n")
    return folders


def _blender_version() -> str:
    from mpib_validate.blender import cycles

    return cycles._bpy().app.version_string
