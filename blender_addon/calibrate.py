"""Focus and aperture from the scene camera (or the panel's overrides)."""



def animated_value(id_data, data_path: str, frame, default):
    """``data_path`` of ``id_data`` at ``frame`` from its keyframes (default if none).

    During an animation render Blender evaluates animation on its render copy only, so
    render handlers see the originals' un-animated values: read the F-curve instead.
    Works with slotted actions (Blender 4.4+) and plain ones (4.2, 4.3)."""
    ad = getattr(id_data, "animation_data", None)
    if frame is None or ad is None or ad.action is None:
        return default
    fcurves = None
    try:
        from bpy_extras import anim_utils

        bag = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
        fcurves = bag.fcurves if bag is not None else None
    except (ImportError, AttributeError):
        pass
    if fcurves is None:
        fcurves = getattr(ad.action, "fcurves", None)
    fc = fcurves.find(data_path) if fcurves is not None else None
    return fc.evaluate(frame) if fc is not None else default


class CalibrationError(ValueError):
    """A camera the refocus cannot model; the message says what to do."""


def focus_distance_of(cam_obj, frame=None) -> float:
    """Planar distance (scene units) the camera focuses at: its focus object's depth
    along the view axis, else its (possibly animated) focus distance. A focus object's
    own animation is not followed during an animation render."""
    dof = cam_obj.data.dof
    if dof.focus_object is not None:
        local = cam_obj.matrix_world.inverted() @ dof.focus_object.matrix_world.translation
        z = -local.z  # Blender cameras look down their local -Z
        if z <= 0:
            raise CalibrationError(f"the focus object '{dof.focus_object.name}' is behind the camera")
        return z
    return animated_value(cam_obj.data, "dof.focus_distance", frame, dof.focus_distance)


def render_size(scene) -> tuple:
    """``(width, height)`` in pixels that a render of ``scene`` has: the resolution
    times its percentage, rounded down as Blender does."""
    r = scene.render
    return (r.resolution_x * r.resolution_percentage // 100,
            r.resolution_y * r.resolution_percentage // 100)


def _perspective_camera(scene):
    cam_obj = scene.camera
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise CalibrationError("the scene has no camera: set one in Scene properties")
    if cam_obj.data.type != "PERSP":
        raise CalibrationError(f"the camera '{cam_obj.name}' is {cam_obj.data.type.lower()}: only "
                               f"perspective cameras have a thin-lens depth of field")
    return cam_obj


def _lens(cam_obj, width: int, height: int, frame) -> dict:
    cam = cam_obj.data
    return {"lens_mm": animated_value(cam, "lens", frame, cam.lens),
            "sensor_width_mm": cam.sensor_width, "sensor_height_mm": cam.sensor_height,
            "sensor_fit": cam.sensor_fit,
            "fstop": animated_value(cam, "dof.aperture_fstop", frame, cam.dof.aperture_fstop),
            "unit_scale": 1.0, "width": width, "height": height}


def blender_lens(scene, width: int, height: int, frame=None) -> dict:
    """The scene camera as it renders at ``frame``: the fields of
    :func:`mpib_validate.runtime.camera.blender_camera` and of the header's ``camera.blender``
    (lens, sensor and fit, f-stop, planar focus depth, ``unit_scale``, size).

    ``unit_scale`` is 1 whatever the scene's Unit Scale: Cycles takes the lens in mm as
    1e-3 Blender units (its depth of field does not change with the Unit Scale), and
    the Depth pass is in Blender units. Raises :class:`CalibrationError` with advice."""
    cam_obj = _perspective_camera(scene)
    return {**_lens(cam_obj, width, height, frame),
            "focus_distance": focus_distance_of(cam_obj, frame)}


def camera_settings(scene, settings, width: int, height: int, warnings=None, frame=None) -> dict:
    """Lens values for :func:`mpib_validate.runtime.camera.blender_camera`, from the scene camera
    (:func:`blender_lens`) and the panel's overrides. Raises :class:`CalibrationError`
    with advice for the artist; appends advice that does not stop the refocus to
    ``warnings``."""
    cam_obj = _perspective_camera(scene)
    cam = cam_obj.data
    needs_dof = settings.use_camera_fstop or settings.use_camera_focus
    if needs_dof and not cam.dof.use_dof and warnings is not None:
        # Passes are rendered with depth of field off; its settings still hold the lens.
        warnings.append(f"the camera '{cam_obj.name}' has depth of field off, so its f-stop "
                        f"(f/{cam.dof.aperture_fstop:g}) and focus settings may be defaults: "
                        f"set them under Camera > Depth of Field, or untick Camera F-Stop / "
                        f"Camera Focus and set them here")
    lens = _lens(cam_obj, width, height, frame)
    if not settings.use_camera_fstop:
        lens["fstop"] = settings.fstop
    lens["focus_distance"] = (focus_distance_of(cam_obj, frame) if settings.use_camera_focus
                              else settings.focus_distance)
    return lens


def camera_sources(settings, pixel=None) -> dict:
    """Where :func:`camera_settings` (and a focus pixel) took each field from, for the
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
