"""The scene camera as Cycles renders it, read once for every part of the extension.

:func:`read_camera` is the one place where the add-on's operators (Refocus Last Render,
Refocus EXR File, the focus pull, Refocus Animation, the render stamp) and the
compositor node's operator read the camera and the render settings that fix the blur:

- the lens (focal length, sensor and fit, f-stop) and the focus: the focus object's
  planar depth along the camera's view axis, else the focus distance; all as evaluated
  at the frame (animation, drivers, parents and constraints). During an animation
  render Blender evaluates the frame on its render copy only and the scene's own
  objects keep the first frame's state, so a read at a given frame sets the frame
  first (``scene.frame_set``);
- the full frame (resolution times percentage, rounded down as Blender does), which
  sets the focal length in pixels ``f_px = lens / sensor * W`` also when the render is
  a render region (:class:`RenderRegion`: cropped, the written image is the region
  only; uncropped, the frame with nothing outside the region);
- the pixel aspect ratio, the camera type (an orthographic camera's Orthographic Scale
  and clip end), whether the camera's own depth of field is on, and the film's
  transparency.

More of the camera (e.g. the aperture's blades, rotation and ratio) goes into
:class:`BlenderCamera` and :func:`read_camera`, so that every operator gets it.

Cycles takes the lens in mm as 1e-3 Blender units whatever the scene's Unit Scale (its
depth of field does not change with ``unit_settings.scale_length``), so the lens
carries ``unit_scale`` 1 and the scene's Unit Scale is not used.

:func:`refusal` says, in one line naming the setting, what the refocus cannot model.
``bpy`` is imported inside the functions only, so the package imports without it.
"""

from __future__ import annotations

from dataclasses import dataclass


class CameraError(ValueError):
    """A camera or render setting the refocus cannot model; the message names it."""


@dataclass(frozen=True)
class RenderRegion:
    """A render region (Output > Format > Render Region) in pixels of the full frame:
    columns ``[x0, x1)`` and rows ``[y0, y1)`` counted from the top left. ``crop``:
    Crop to Render Region (the written image is the region only)."""

    x0: int
    y0: int
    x1: int
    y1: int
    crop: bool

    @property
    def size(self) -> tuple[int, int]:
        return self.x1 - self.x0, self.y1 - self.y0


@dataclass(frozen=True)
class BlenderCamera:
    """The scene camera and the render settings that set the blur, at one frame."""

    name: str
    type: str  # "PERSP", "ORTHO" or "PANO"
    lens_mm: float
    sensor_width_mm: float
    sensor_height_mm: float
    sensor_fit: str
    fstop: float
    focus_distance: float  # planar depth in focus, scene units (inf: focus at infinity)
    focus_object: str | None
    width: int  # the full frame, pixels
    height: int
    pixel_aspect: float  # pixel width / pixel height
    region: RenderRegion | None
    use_dof: bool
    film_transparent: bool
    frame: int
    ortho_scale: float = 0.0  # an orthographic camera's view width (Orthographic Scale)
    clip_end: float = 0.0  # the camera's clip end: no visible depth lies beyond it
    #: Depth of Field > Aperture: blades (0, or Blender's 1 to 16; Cycles renders 1 and 2
    #: as a disk), rotation (radians), ratio (docs/aperture.md)
    aperture_blades: int = 0
    aperture_rotation: float = 0.0
    aperture_ratio: float = 1.0

    def lens(self) -> dict:
        """Keyword arguments of :func:`mpib_validate.runtime.camera.blender_camera` (and
        the header's ``camera.blender``): the full frame's size, ``unit_scale`` 1."""
        return {"lens_mm": self.lens_mm, "sensor_width_mm": self.sensor_width_mm,
                "sensor_height_mm": self.sensor_height_mm, "sensor_fit": self.sensor_fit,
                "fstop": self.fstop, "focus_distance": self.focus_distance,
                "unit_scale": 1.0, "width": self.width, "height": self.height,
                "aperture_blades": self.aperture_blades,
                "aperture_rotation": self.aperture_rotation,
                "aperture_ratio": self.aperture_ratio}

    def orthographic(self) -> dict:
        """Keyword arguments of
        :func:`mpib_validate.runtime.camera.blender_orthographic_camera` for an
        orthographic camera (``far``: the clip end, or the focus if farther)."""
        return {"ortho_scale": self.ortho_scale, "sensor_fit": self.sensor_fit,
                "width": self.width, "height": self.height, "fstop": self.fstop,
                "focus_distance": self.focus_distance,
                "far": max(self.clip_end, self.focus_distance)}

    @property
    def image_size(self) -> tuple[int, int]:
        """``(W, H)`` of the image the render writes (the region when cropped)."""
        if self.region is not None and self.region.crop:
            return self.region.size
        return self.width, self.height


def render_size(scene) -> tuple[int, int]:
    """``(W, H)`` of the full frame: the resolution times its percentage, rounded down as
    Blender does."""
    r = scene.render
    return (r.resolution_x * r.resolution_percentage // 100,
            r.resolution_y * r.resolution_percentage // 100)


def render_region(scene, width: int, height: int) -> RenderRegion | None:
    """The render region in pixels (None without one, or when it is empty or the whole
    frame). Blender truncates ``border * size`` to whole pixels; its y runs up."""
    r = scene.render
    if not r.use_border:
        return None
    x0, x1 = int(r.border_min_x * width), int(r.border_max_x * width)
    y0, y1 = int(r.border_min_y * height), int(r.border_max_y * height)
    if x1 <= x0 or y1 <= y0 or (x0, y0, x1, y1) == (0, 0, width, height):
        return None
    return RenderRegion(x0, height - y1, x1, height - y0, bool(r.use_crop_to_border))


def _depsgraph_at(scene, frame):
    """The evaluated depsgraph of ``scene`` (None for a scene that is not the context's:
    its own objects are then read), evaluated at ``frame`` when one is given.

    During an animation render Blender evaluates each frame on its render copy only: the
    scene's own depsgraph and objects stay at the first frame. A value keyed after the
    last evaluation is not applied either until the frame is set again. So a read at a
    given frame sets it (``scene.frame_set``: animation, drivers, parents and
    constraints evaluated as for the render); a read without one takes the scene as it
    is evaluated now (an operator run by the artist). The frame is set on Python's main
    thread only (in background mode render handlers run there): Blender's interface runs
    render jobs on a thread of their own, where evaluating the scene would race with the
    interface, so a handler there reads the scene as it is (and :func:`read_camera` the
    camera's own keyed values from their F-curves)."""
    import bpy

    if frame is not None and _main_thread():
        scene.frame_set(int(frame))
    ctx = bpy.context
    if getattr(ctx, "scene", None) != scene:
        return None
    return ctx.evaluated_depsgraph_get()


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def focus_depth(cam_obj, target=None) -> float:
    """Planar depth (scene units) of the camera's focus as Cycles takes it
    (``blender_camera_focal_distance``): the focus object ``target``'s distance from the
    camera along the camera's view axis, ``|z . (o - c)|`` with ``z`` the normalised local
    Z axis (a scaled camera measures as unscaled), else ``dof.focus_distance``."""
    if target is None:
        return float(cam_obj.data.dof.focus_distance)
    m = cam_obj.matrix_world
    view = -m.col[2].xyz.normalized()
    return abs(float(view.dot(target.matrix_world.translation - m.translation)))


def read_camera(scene, frame=None) -> BlenderCamera:
    """The scene camera at ``frame`` (default: the current frame), as evaluated there
    (:func:`_depsgraph_at`). Raises :class:`CameraError` when the scene has no camera
    object."""
    depsgraph = _depsgraph_at(scene, frame)
    cam_obj = scene.camera
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise CameraError("the scene has no camera: set one in Scene properties > Camera")
    target = cam_obj.data.dof.focus_object

    def evaluated(ob):
        return ob if ob is None or depsgraph is None else ob.evaluated_get(depsgraph)

    cam_obj, target = evaluated(cam_obj), evaluated(target)
    cam = cam_obj.data
    lens, fstop = float(cam.lens), float(cam.dof.aperture_fstop)
    dof = cam.dof
    blades, rotation = int(dof.aperture_blades), float(dof.aperture_rotation)
    ratio = float(dof.aperture_ratio)
    focus = focus_depth(cam_obj, target)
    if frame is not None and not _main_thread():  # a render job's thread: the keys
        from mpib_validate.runtime.blender.compat import fcurve_value

        data = scene.camera.data
        lens = float(fcurve_value(data, "lens", frame, lens))
        fstop = float(fcurve_value(data, "dof.aperture_fstop", frame, fstop))
        blades = int(round(fcurve_value(data, "dof.aperture_blades", frame, blades)))
        rotation = float(fcurve_value(data, "dof.aperture_rotation", frame, rotation))
        ratio = float(fcurve_value(data, "dof.aperture_ratio", frame, ratio))
        if target is None:
            focus = float(fcurve_value(data, "dof.focus_distance", frame, focus))
    W, H = render_size(scene)
    r = scene.render
    return BlenderCamera(
        name=cam_obj.name, type=cam.type, lens_mm=lens,
        sensor_width_mm=float(cam.sensor_width), sensor_height_mm=float(cam.sensor_height),
        sensor_fit=cam.sensor_fit, fstop=fstop,
        focus_distance=focus,
        focus_object=None if target is None else target.name, width=W, height=H,
        pixel_aspect=float(r.pixel_aspect_x) / float(r.pixel_aspect_y),
        region=render_region(scene, W, H), use_dof=bool(cam.dof.use_dof),
        film_transparent=bool(r.film_transparent), frame=int(scene.frame_current),
        ortho_scale=float(cam.ortho_scale), clip_end=float(cam.clip_end),
        aperture_blades=blades, aperture_rotation=rotation, aperture_ratio=ratio)


def refusal(cam: BlenderCamera, *, focus: bool = True, dof: bool = True,
            orthographic: bool = True) -> str | None:
    """One line naming the setting the refocus cannot model for ``cam``, or None.

    ``focus``: the camera's focus is used (else the panel's); ``dof``: the camera's own
    depth of field is refused (a render with it on is already blurred; the compositor
    node's operator warns instead, since the node blurs later renders);
    ``orthographic``: orthographic cameras are refocused (on a depth linear in Z,
    :func:`mpib_validate.runtime.camera.blender_orthographic_camera`); the compositor
    node, whose slices are in 1/Z, refuses them."""
    if cam.type == "ORTHO" and not orthographic:
        return (f"the camera '{cam.name}' is orthographic: Cycles blurs its depth of field "
                f"linearly in depth, not in 1/depth as the node's slices are; use Refocus "
                f"Last Render, or set Camera > Type to Perspective")
    if cam.type not in ("PERSP", "ORTHO"):
        kind = {"PANO": "panoramic"}.get(cam.type, cam.type.lower())
        return (f"the camera '{cam.name}' is {kind}: the refocus models perspective and "
                f"orthographic cameras only (Camera > Type)")
    if dof and cam.use_dof:
        return (f"the camera '{cam.name}' has Depth of Field on, so the render is already "
                f"blurred and would be blurred twice: turn off Camera > Depth of Field and "
                f"render again (its f-stop and focus still set the refocus)")
    if focus and not cam.focus_distance > 0:
        where = (f"the focus object '{cam.focus_object}' lies in the camera's plane"
                 if cam.focus_object else "the focus distance is 0")
        return (f"the camera '{cam.name}' focuses at depth 0 ({where}): set Camera > Depth "
                f"of Field > Focus")
    return None


#: A pixel aspect ratio within this of a whole number is taken as that number (Blender
#: stores Pixel Aspect X and Y as floats; 2:1 anamorphic is exact).
ASPECT_TOLERANCE = 1e-4


def square_pixels(cam: BlenderCamera) -> tuple[int, int]:
    """``(mx, my)``: how many times to repeat each column and each row of the render so
    that its pixels are square (Pixel Aspect X:Y = 2:1 gives ``(2, 1)``, 1:2 gives
    ``(1, 2)``). On the repeated image the thin lens is round and its focal length in
    pixels is Blender's on the repeated size (the sensor fit compares ``W aspect_x``
    with ``H aspect_y``, as :func:`~mpib_validate.runtime.camera.blender_focal_length_px`
    does with the repeated size); averaging each ``mx x my`` block gives the result back
    at the render's pixels. Raises :class:`CameraError` naming the setting for a ratio
    that is not a whole number."""
    a = cam.pixel_aspect
    m = a if a >= 1.0 else 1.0 / a
    n = round(m)
    if abs(m - n) > ASPECT_TOLERANCE * m:
        raise CameraError(f"Pixel Aspect X:Y is {a:.4g}:1; the refocus takes whole-number "
                          f"ratios (1:1, 2:1, 1:2 ...): set Output > Format > Pixel Aspect "
                          f"X and Y accordingly")
    return (n, 1) if a >= 1.0 else (1, n)
