"""The thin-lens camera shared by the ray tracer, Mitsuba 3 and Cycles.

Conventions (``docs/camera.md`` states them for users):

- Image coordinates ``(x, y)`` are in pixels from the image centre, x to the right
  and y *down* (OpenCV). Pixel column ``j`` covers ``x in [j - W/2, j + 1 - W/2)``.
- Disparity ``d = 1/Z`` in 1/scene-unit, Z the depth along the optical axis.
- Pinhole projection ``x = f_px X / Z``; the sensor distance of the paper is
  ``z_s = f_px`` (Eq. 8).
- A thin lens of aperture radius ``R`` (scene units) focused at depth ``z_f``
  (``d_f = 1/z_f``) blurs a point at disparity d into a disk of radius
  ``r = A |d - d_f|`` pixels, with the blur parameter ``A = R f_px`` (Eq. 14,
  ``A = R z_s``).

The :class:`Camera` holds the image-space form (size, ``A``, ``d_f``) plus the focal
length in pixels, which fixes the physical form; :meth:`Camera.thin_lens` and
:meth:`Camera.from_thin_lens` convert both ways. Blender and Mitsuba settings are
derived from the physical form only here, so each conversion is written once.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

#: Default horizontal field of view used when a scene does not give a focal length:
#: a 50 mm lens on a 36 mm sensor (fov_x = 39.6 degrees).
DEFAULT_LENS_MM = 50.0
DEFAULT_SENSOR_MM = 36.0


@dataclass(frozen=True)
class ThinLens:
    """Physical thin lens, in scene units.

    Attributes:
        focal_length_px: focal length in pixels (``f_px``, the paper's ``z_s``).
        aperture_radius: lens aperture radius ``R`` in scene units.
        focus_distance: depth of the plane in focus ``z_f`` in scene units
            (``math.inf`` for focus at infinity).
    """

    focal_length_px: float
    aperture_radius: float
    focus_distance: float


#: Blender's largest blade count (``CameraDOFSettings.aperture_blades``: 0, or 3 to 16).
MAX_BLADES = 16


class ApertureError(ValueError):
    """An aperture that cannot be used: one line naming the field."""


@dataclass(frozen=True)
class Aperture:
    """The shape of the lens aperture, with Cycles' conventions (``camera_sample_aperture``
    in ``kernel/camera/camera.h``, ``regular_polygon_sample`` in ``kernel/sample/mapping.h``;
    ``docs/aperture.md``).

    The aperture radius ``R`` (``A = R f_px``) is the disk's radius, and a polygon's
    circumradius (its corners lie on the circle of radius ``R``). In the image axes
    (x right, y down) the unit aperture point ``(mu, nu)`` (a pixel at ``x`` sees
    ``x + A (d - d_f) (mu, nu)``, Eq. 15) is Cycles' lens point ``(ax, -ay)``.

    Attributes:
        blades: 0 for a disk, else 3 to 16: a regular polygon whose corners lie at
            angles ``rotation + (2k + 1) pi / blades`` (counter-clockwise as seen on
            screen; at rotation 0 an edge's midpoint, at ``cos(pi / blades)``, lies on +x).
        rotation: the polygon's rotation in **radians** (Blender's ``aperture_rotation``),
            counter-clockwise as seen on screen.
        ratio: the anamorphic ratio (Blender's ``aperture_ratio``): the aperture's
            horizontal axis is divided by it (1.5: a 1.5 times taller than wide aperture),
            finite and > 0.
    A point behind the focus spreads into the aperture as seen on screen, one in front
    of it into the aperture turned 180 degrees.
    """

    blades: int = 0
    rotation: float = 0.0
    ratio: float = 1.0

    def __post_init__(self) -> None:
        b = self.blades
        if isinstance(b, bool) or not isinstance(b, numbers.Integral) or not (
                b == 0 or 3 <= b <= MAX_BLADES):
            raise ApertureError(f"blades must be 0 (a disk) or 3 to {MAX_BLADES}, got {b!r}")
        r = self.rotation
        if isinstance(r, bool) or not isinstance(r, numbers.Real) or not math.isfinite(r):
            raise ApertureError(f"rotation must be a finite angle in radians, got {r!r}")
        q = self.ratio
        if isinstance(q, bool) or not isinstance(q, numbers.Real) or not (
                math.isfinite(q) and q > 0):
            raise ApertureError(f"ratio must be finite and > 0, got {q!r}")
        object.__setattr__(self, "blades", int(b))
        object.__setattr__(self, "rotation", float(r))
        object.__setattr__(self, "ratio", float(q))

    @property
    def is_disk(self) -> bool:
        """Round, of radius R (a disk's rotation changes nothing)."""
        return self.blades == 0 and self.ratio == 1.0

    @property
    def symmetric(self) -> bool:
        """Centrally symmetric (a disk, an ellipse, an even polygon): the blur of a point
        in front of the focus is then the same shape as behind it."""
        return self.blades % 2 == 0

    @property
    def extent(self) -> float:
        """The shape's largest reach from its centre along x or y, in units of R:
        ``max(1, 1 / ratio)`` (a polygon's corners lie on the unit circle)."""
        return max(1.0, 1.0 / self.ratio)

    @property
    def apothem(self) -> float:
        """Distance from the centre to the edges of the unit shape before the ratio:
        ``cos(pi / blades)``, 1 for a disk."""
        return 1.0 if self.blades == 0 else math.cos(math.pi / self.blades)

    @property
    def area(self) -> float:
        """Area of the unit aperture (R = 1): ``pi / ratio`` for a disk,
        ``(n / 2) sin(2 pi / n) / ratio`` for ``n`` blades."""
        n = self.blades
        return (math.pi if n == 0 else 0.5 * n * math.sin(2.0 * math.pi / n)) / self.ratio

    def contains(self, mu, nu):
        """Whether the image-axes points ``(mu, nu)`` (numpy arrays) lie in the unit
        aperture (boundary included)."""
        import numpy as np

        x = np.asarray(mu, np.float64) * self.ratio
        y = -np.asarray(nu, np.float64)  # Cycles' y points up
        if self.blades == 0:
            return x * x + y * y <= 1.0
        a = self.apothem
        inside = np.ones(np.broadcast(x, y).shape, bool)
        for k in range(self.blades):  # edge k's outward normal at rotation + 2 pi k / n
            t = self.rotation + 2.0 * math.pi * k / self.blades
            inside &= x * math.cos(t) + y * math.sin(t) <= a
        return inside

    def to_dict(self) -> dict:
        return {"blades": self.blades, "rotation": self.rotation, "ratio": self.ratio}

    def describe(self) -> str:
        """A short text: ``disk``, ``6 blades at 15 deg``, ``, ratio 1.5``."""
        text = "disk" if self.blades == 0 else (
            f"{self.blades} blades at {math.degrees(self.rotation):g} deg")
        return text + (f", ratio {self.ratio:g}" if self.ratio != 1.0 else "")


#: The round aperture (Blender's default: 0 blades, rotation 0, ratio 1).
DISK = Aperture()


def blender_aperture(blades: int, rotation: float, ratio: float) -> Aperture:
    """The :class:`Aperture` a Blender camera renders with: Cycles renders 1 or 2 blades
    as a disk (``kcam->blades = (blades < 3) ? 0 : blades`` in ``scene/camera.cpp``)."""
    return Aperture(0 if blades < 3 else int(blades), float(rotation), float(ratio))


@dataclass(frozen=True)
class Camera:
    """Image-space thin-lens camera.

    Attributes:
        width, height: image size in pixels.
        blur_parameter: ``A`` in pixels per unit disparity (``A = R f_px``).
        focus_disparity: ``d_f = 1/z_f`` in 1/scene-unit (0 = focus at infinity).
        focal_length_px: ``f_px``; only the physical form (Mitsuba, Cycles) depends
            on it. Defaults to a 50 mm lens on a 36 mm wide sensor.
        aperture: the aperture's shape (:class:`Aperture`; default a disk). A point's
            blur is that shape scaled by ``A |d - d_f|`` (its circumradius).
    """

    width: int
    height: int
    blur_parameter: float
    focus_disparity: float
    focal_length_px: float | None = None
    aperture: Aperture = DISK

    def __post_init__(self) -> None:
        if self.focal_length_px is None:
            object.__setattr__(
                self, "focal_length_px", DEFAULT_LENS_MM / DEFAULT_SENSOR_MM * self.width
            )

    # -- blur -------------------------------------------------------------------------
    def blur_radius(self, disparity: float) -> float:
        """Circle-of-confusion radius ``A |d - d_f|`` in pixels for disparity ``d``."""
        return self.blur_parameter * abs(disparity - self.focus_disparity)

    # -- physical form ------------------------------------------------------------------
    def thin_lens(self) -> ThinLens:
        """The physical lens: ``R = A / f_px``, ``z_f = 1 / d_f``."""
        f = float(self.focal_length_px)
        z_f = math.inf if self.focus_disparity == 0 else 1.0 / self.focus_disparity
        return ThinLens(f, self.blur_parameter / f, z_f)

    @classmethod
    def from_thin_lens(cls, width: int, height: int, lens: ThinLens) -> "Camera":
        """Inverse of :meth:`thin_lens`: ``A = R f_px``, ``d_f = 1 / z_f``."""
        d_f = 0.0 if math.isinf(lens.focus_distance) else 1.0 / lens.focus_distance
        return cls(width, height, lens.aperture_radius * lens.focal_length_px, d_f,
                   lens.focal_length_px)

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view in degrees: ``fov_x = 2 atan(W / (2 f_px))``."""
        return math.degrees(2.0 * math.atan(0.5 * self.width / float(self.focal_length_px)))

    # -- Cycles ------------------------------------------------------------------------------
    def cycles_settings(self, sensor_width_mm: float = DEFAULT_SENSOR_MM,
                        scene_unit_m: float = 1.0) -> dict:
        """Blender camera settings that reproduce this camera (sensor fit horizontal).

        ``f_px = lens_mm / sensor_mm * W`` and ``R = lens / (2 N)``, so
        ``N = lens / (2 R)`` with the focal length converted to scene units.
        """
        lens_mm = float(self.focal_length_px) / self.width * sensor_width_mm
        lens = self.thin_lens()
        lens_units = lens_mm * 1e-3 / scene_unit_m
        fstop = math.inf if lens.aperture_radius == 0 else lens_units / (2.0 * lens.aperture_radius)
        return {
            "lens_mm": lens_mm,
            "sensor_width_mm": sensor_width_mm,
            "sensor_fit": "HORIZONTAL",
            "fstop": fstop,
            "focus_distance": lens.focus_distance,
            "aperture_blades": self.aperture.blades,
            "aperture_rotation": self.aperture.rotation,
            "aperture_ratio": self.aperture.ratio,
        }

    # -- Mitsuba -----------------------------------------------------------------------------
    def mitsuba_settings(self) -> dict:
        """Mitsuba ``thinlens`` parameters: ``fov`` along x, ``aperture_radius``, ``focus_distance``.
        Mitsuba 3's ``thinlens`` samples a disk only: a camera with blades or a ratio is
        refused (the Mitsuba cross-checks cover disks; the tracer and Cycles the shapes)."""
        if not self.aperture.is_disk:
            raise ValueError(f"Mitsuba's thinlens sensor has a disk aperture only; this "
                             f"camera has {self.aperture.describe()}")
        lens = self.thin_lens()
        return {
            "fov": self.fov_x_deg,
            "fov_axis": "x",
            "aperture_radius": lens.aperture_radius,
            "focus_distance": lens.focus_distance,
        }

    # -- geometry ------------------------------------------------------------------------------
    def pixel_centres(self) -> tuple:
        """Centred coordinates of the pixel centres: ``x_j = j + 0.5 - W/2`` (1-D arrays)."""
        import numpy as np

        xs = np.arange(self.width, dtype=np.float64) + 0.5 - 0.5 * self.width
        ys = np.arange(self.height, dtype=np.float64) + 0.5 - 0.5 * self.height
        return xs, ys

    def to_dict(self) -> dict:
        return {
            "width": int(self.width),
            "height": int(self.height),
            "blur_parameter": float(self.blur_parameter),
            "focus_disparity": float(self.focus_disparity),
            "focal_length_px": float(self.focal_length_px),
            **({} if self.aperture.is_disk else {"aperture": self.aperture.to_dict()}),
        }


#: Blender's sensor fits (``Camera.sensor_fit``) and its default sensor (36 x 24 mm, AUTO).
SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")
DEFAULT_SENSOR_HEIGHT_MM = 24.0
DEFAULT_SENSOR_FIT = "AUTO"


def blender_focal_length_px(lens_mm: float, sensor_width_mm: float, sensor_height_mm: float,
                            sensor_fit: str, width: int, height: int) -> float:
    """Focal length in pixels of a Blender camera: ``f_px = lens / sensor * pixels``.

    Blender's rule (``BKE_camera_sensor_fit`` and ``BKE_camera_sensor_size``, which
    Cycles' viewplane follows): ``HORIZONTAL`` puts the sensor *width* across the image
    width, ``VERTICAL`` the sensor *height* across the image height, and ``AUTO`` the
    sensor *width* across the larger image side (the width when ``width >= height``).
    Square pixels. For a 1080x1920 portrait frame at 50 mm on the default 36 x 24 mm
    sensor: AUTO 2666.7 px, HORIZONTAL 1500 px, VERTICAL 4000 px.
    """
    fit = str(sensor_fit).upper()
    if fit not in SENSOR_FITS:
        raise ValueError(f"unknown sensor fit {sensor_fit!r} (one of {', '.join(SENSOR_FITS)})")
    if fit == "VERTICAL":
        return lens_mm / sensor_height_mm * height
    if fit == "HORIZONTAL" or width >= height:
        return lens_mm / sensor_width_mm * width
    return lens_mm / sensor_width_mm * height  # AUTO on a portrait frame


def blender_camera(lens_mm: float, sensor_width_mm: float, sensor_height_mm: float,
                   sensor_fit: str, width: int, height: int, fstop: float,
                   focus_distance: float, unit_scale: float = 1.0,
                   aperture_blades: int = 0, aperture_rotation: float = 0.0,
                   aperture_ratio: float = 1.0) -> Camera:
    """The :class:`Camera` that a Blender perspective camera renders with: the one
    conversion from Blender's lens settings (the add-on, ``mpib refocus`` and the EXR
    header camera all call it).

    ``f_px`` by the sensor fit (:func:`blender_focal_length_px`); the aperture radius
    ``R = lens / (2 N)`` with the lens converted from mm to scene units
    (``lens * 1e-3 / unit_scale``); ``A = R f_px`` pixels per unit disparity and
    ``d_f = 1 / focus_distance`` (planar depth in scene units; ``inf`` gives 0).

    ``unit_scale``: metres per unit of depth *as the lens sees it*. Cycles takes the
    lens in mm as 1e-3 Blender units whatever the scene's Unit Scale (a Cycles depth of
    field render does not change with ``unit_settings.scale_length``, checked in the
    tests), so a Blender render has 1; another value is for depth in other units.
    ``aperture_blades``, ``aperture_rotation`` (radians), ``aperture_ratio``: the
    camera's Depth of Field > Aperture (:func:`blender_aperture`: 1 or 2 blades are a
    disk, as Cycles renders them).
    """
    for name, value in (("lens", lens_mm), ("sensor width", sensor_width_mm),
                        ("sensor height", sensor_height_mm), ("unit scale", unit_scale)):
        if not (value > 0) or math.isinf(value):
            raise ValueError(f"the {name} must be finite and > 0, got {value}")
    if not (fstop > 0) or math.isinf(fstop):
        raise ValueError(f"f-stop must be finite and > 0, got {fstop}")
    if not (focus_distance > 0):
        raise ValueError(f"focus distance must be > 0, got {focus_distance}")
    f_px = blender_focal_length_px(lens_mm, sensor_width_mm, sensor_height_mm, sensor_fit,
                                   width, height)
    R = lens_mm * 1e-3 / unit_scale / (2.0 * fstop)
    return Camera(width, height, R * f_px, 1.0 / focus_distance, f_px,
                  blender_aperture(aperture_blades, aperture_rotation, aperture_ratio))


def blender_orthographic_camera(ortho_scale: float, sensor_fit: str, width: int, height: int,
                                fstop: float, focus_distance: float, far: float) -> Camera:
    """The :class:`Camera` of Cycles' depth of field for an orthographic camera, on the
    depth coordinate ``d = far - Z`` (linear in the planar depth Z; 0 at ``far``, larger
    nearer), in place of the disparity ``1/Z`` of a perspective camera.

    Cycles (``camera_sample_orthographic``) starts each ray at its pixel's point on the
    image plane moved by a lens offset ``u`` (``|u| <= R``, ``R = 1 / (2 N)`` scene
    units: Blender's aperture for orthographic cameras has no focal length) and aims it
    at the pixel's point at depth ``z_f``; at depth Z the ray is off by ``u (1 - Z /
    z_f)``, so a point blurs into a disk of radius ``R |Z - z_f| / z_f`` scene units, ``k``
    times that in pixels with ``k`` pixels per scene unit (``ortho_scale`` across the
    image width for the HORIZONTAL fit, the height for VERTICAL, the larger side for
    AUTO). Hence ``r = A |d - d_f|`` with ``A = k R / z_f`` and ``d_f = far - z_f``;
    ``far`` must be at least every depth refocused (the camera's clip end) and ``z_f``."""
    fit = str(sensor_fit).upper()
    if fit not in SENSOR_FITS:
        raise ValueError(f"unknown sensor fit {sensor_fit!r} (one of {', '.join(SENSOR_FITS)})")
    for name, value in (("orthographic scale", ortho_scale), ("f-stop", fstop),
                        ("focus distance", focus_distance)):
        if not (value > 0) or math.isinf(value):
            raise ValueError(f"the {name} must be finite and > 0, got {value}")
    if not far >= focus_distance:
        raise ValueError(f"the far depth {far} must be at least the focus distance {focus_distance}")
    side = height if fit == "VERTICAL" or (fit == "AUTO" and height > width) else width
    k = side / ortho_scale
    R = 1.0 / (2.0 * fstop)
    return Camera(width, height, k * R / focus_distance, far - focus_distance, k)


# --------------------------------------------------------------------------------------
# The MPIB paper's parameter convention (photographs with a normalised disparity map)

#: The official renderer's planes: ``d_i = (i + 0.5) / 32`` over the normalised [0, 1]
#: disparity (plane 0 the farthest); its ``increase_focus_range`` (used by its demo)
#: subtracts half a bin, ``0.5 / 32``, from every plane's defocus ``|d_i - d_f|``.
OFFICIAL_BINS = 32


def from_paper(K: float, disp_focus: float) -> tuple[float, float]:
    """The project's ``(A, d_f)`` for the paper's blur parameter ``K`` (pixels per unit of
    the normalised [0, 1] disparity) and focus ``disp_focus`` in [0, 1].

    The paper's blur radius is ``r = K |d - d_f|`` on the normalised disparity ``d``;
    the project's is ``r = A |d - d_f|`` on the MPI's disparity. With the normalised map
    used as the MPI's disparity directly (0 = infinitely far, 1 = the nearest the
    network saw), ``A = K`` and ``d_f = disp_focus``: the same radius for every ``d``.
    Raises ``ValueError`` naming the option for ``K <= 0`` or a focus outside [0, 1]."""
    if not (math.isfinite(K) and K > 0):
        raise ValueError(f"--K must be finite and > 0 (pixels of blur per unit of the "
                         f"[0, 1] disparity), got {K}")
    if not (math.isfinite(disp_focus) and 0.0 <= disp_focus <= 1.0):
        raise ValueError(f"--disp-focus must be in [0, 1] (the normalised disparity in "
                         f"focus), got {disp_focus}")
    return float(K), float(disp_focus)


def widen_focus(disparity, focus_disparity: float, half_width: float):
    """Disparity remapped so that ``A |d' - d_f| = A max(|d - d_f| - h, 0)``: everything
    within ``h`` of the focus is sharp and every other defocus is ``h`` smaller, as the
    official renderer's ``increase_focus_range`` does with ``h = 0.5 / 32``:
    ``d' = d_f + sign(d - d_f) max(|d - d_f| - h, 0)``. Numpy in, numpy out."""
    import numpy as np

    d = np.asarray(disparity, np.float64)
    off = d - focus_disparity
    return focus_disparity + np.sign(off) * np.maximum(np.abs(off) - half_width, 0.0)
