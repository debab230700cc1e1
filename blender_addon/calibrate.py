"""Focus and aperture from the scene camera (or the panel's overrides).

The camera and the render settings are read by one function,
:func:`mpib_validate.runtime.blender.camera.read_camera`, for every operator; this module
adds the panel's overrides and fits the camera to the image being refocused (render
region, pixel aspect)."""

from mpib_validate.runtime.blender.camera import CameraError as CalibrationError  # noqa: F401


def camera_request(scene, settings, image_size, frame=None, purpose: str = "refocus") -> dict:
    """What a refocus of an image of ``image_size`` ``(W, H)`` takes from the scene at
    ``frame`` (default: as it is now), refused in one line naming the setting
    (:class:`CalibrationError`) where the refocus cannot model the camera:

    - ``camera``: keyword arguments of :func:`mpib_validate.runtime.camera.blender_camera`
      for the image as refocused (square pixels: see ``stretch``), with the panel's
      f-stop and focus distance where it overrides the camera's; None for an
      orthographic camera, which has ``ortho`` instead: those of
      :func:`mpib_validate.runtime.camera.blender_orthographic_camera`;
    - ``region``: ``(x0, y0, x1, y1)`` of an uncropped render region in the image (the
      refocus reads and writes only that box; outside it the render holds nothing), or
      None;
    - ``stretch``: ``(mx, my)`` whole-number repeats of each column and row that make the
      pixels square (Pixel Aspect X:Y = 2:1 gives (2, 1)); the result is averaged back.

    An image of another size than the render's (an EXR from elsewhere) is taken as the
    whole frame at its own size (``f_px`` scales with it)."""
    from mpib_validate.runtime.blender.camera import read_camera, refusal, square_pixels

    cam = read_camera(scene, frame)
    problem = refusal(cam, focus=settings.use_camera_focus)
    if problem:
        raise CalibrationError(problem)
    mx, my = square_pixels(cam)
    W, H = (int(v) for v in image_size)
    region = None
    frame_w, frame_h = cam.width, cam.height
    if cam.region is not None and (W, H) == cam.image_size:
        if not cam.region.crop:
            r = cam.region
            region = (r.x0, r.y0, r.x1, r.y1)
    elif (W, H) != (cam.width, cam.height):  # not this scene's render: the frame as it is
        frame_w, frame_h = W, H
    ortho = cam.type == "ORTHO"
    lens = cam.orthographic() if ortho else cam.lens()
    lens["width"], lens["height"] = frame_w * mx, frame_h * my
    if not settings.use_camera_fstop:
        lens["fstop"] = settings.fstop
    if not settings.use_camera_focus:
        lens["focus_distance"] = settings.focus_distance
    if ortho:
        lens["far"] = max(cam.clip_end, lens["focus_distance"])
    return {"camera": None if ortho else lens, "ortho": lens if ortho else None,
            "region": region, "stretch": (mx, my), "frame_size": (frame_w, frame_h)}


def camera_sources(settings, pixel=None) -> dict:
    """Where :func:`camera_request` (and a focus pixel) took each field from, for the
    ``from`` record of a saved refocus's header."""
    camera = "Blender camera"
    out = {k: camera for k in ("lens_mm", "sensor_width_mm", "sensor_height_mm", "sensor_fit")}
    out["unit_scale"] = "Blender (1 whatever the Unit Scale)"
    out["fstop"] = camera if settings.use_camera_fstop else "MPIB panel F-Stop"
    if pixel is not None:
        out["focus_disparity"] = "MPIB panel focus pixel {},{}".format(*pixel)
    else:
        out["focus_distance"] = camera if settings.use_camera_focus else "MPIB panel Focus Distance"
    return out
