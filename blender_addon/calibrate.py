"""Focus and aperture from the scene camera (or the panel's overrides)."""



class CalibrationError(ValueError):
    """A camera the refocus cannot model; the message says what to do."""


def focus_distance_of(cam_obj) -> float:
    """Planar distance (scene units) the camera focuses at: its focus object's depth
    along the view axis, else its focus distance."""
    dof = cam_obj.data.dof
    if dof.focus_object is not None:
        local = cam_obj.matrix_world.inverted() @ dof.focus_object.matrix_world.translation
        z = -local.z  # Blender cameras look down their local -Z
        if z <= 0:
            raise CalibrationError(f"the focus object '{dof.focus_object.name}' is behind the camera")
        return z
    return dof.focus_distance


def camera_settings(scene, settings, width: int, height: int, warnings=None) -> dict:
    """Lens values for :func:`mpib_validate.camera.blender_camera`, from the scene camera
    and the panel. Raises :class:`CalibrationError` with advice for the artist; appends
    advice that does not stop the refocus to ``warnings``."""
    cam_obj = scene.camera
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise CalibrationError("the scene has no camera: set one in Scene properties")
    cam = cam_obj.data
    if cam.type != "PERSP":
        raise CalibrationError(f"the camera '{cam_obj.name}' is {cam.type.lower()}: only "
                               f"perspective cameras have a thin-lens depth of field")
    needs_dof = settings.use_camera_fstop or settings.use_camera_focus
    if needs_dof and not cam.dof.use_dof and warnings is not None:
        # Passes are rendered with depth of field off; its settings still hold the lens.
        warnings.append(f"the camera '{cam_obj.name}' has depth of field off, so its f-stop "
                        f"(f/{cam.dof.aperture_fstop:g}) and focus settings may be defaults: "
                        f"set them under Camera > Depth of Field, or untick Camera F-Stop / "
                        f"Camera Focus and set them here")
    fstop = cam.dof.aperture_fstop if settings.use_camera_fstop else settings.fstop
    if settings.use_camera_focus:
        focus = focus_distance_of(cam_obj)
    else:
        focus = settings.focus_distance
    return {"lens_mm": cam.lens, "sensor_width_mm": cam.sensor_width,
            "sensor_height_mm": cam.sensor_height, "sensor_fit": cam.sensor_fit,
            "width": width, "height": height, "fstop": fstop, "focus_distance": focus,
            "unit_scale": scene.unit_settings.scale_length or 1.0}
