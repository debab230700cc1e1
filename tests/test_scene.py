"""Scene model, camera conversions and the on-disk format, with its errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mpib_validate.runtime import samples
from mpib_validate.cards import trace
from mpib_validate.runtime.camera import Camera, ThinLens
from mpib_validate.runtime.io.exr import write_exr, channels_from_rgba
from mpib_validate.cards.generate import generate
from mpib_validate.cards.scene import Plane, SceneError, load_scene, save_scene


def test_camera_round_trips_through_the_thin_lens():
    cam = Camera(640, 480, blur_parameter=33.0, focus_disparity=0.25, focal_length_px=800.0)
    lens = cam.thin_lens()
    assert lens.aperture_radius == pytest.approx(33.0 / 800.0)
    assert lens.focus_distance == pytest.approx(4.0)
    back = Camera.from_thin_lens(640, 480, lens)
    assert back.blur_parameter == pytest.approx(33.0) and back.focus_disparity == pytest.approx(0.25)
    inf = Camera.from_thin_lens(10, 10, ThinLens(100.0, 0.1, math.inf))
    assert inf.focus_disparity == 0.0 and inf.thin_lens().focus_distance == math.inf


def test_cycles_and_mitsuba_settings_reproduce_A():
    """A = R f_px with Cycles' f_px = lens/sensor * W, R = lens/(2 N); Mitsuba's
    f_px = (W/2)/tan(fov/2)."""
    cam = Camera(512, 256, blur_parameter=40.0, focus_disparity=0.5)
    cy = cam.cycles_settings()
    f_px = cy["lens_mm"] / cy["sensor_width_mm"] * 512
    R = cy["lens_mm"] * 1e-3 / (2 * cy["fstop"])
    assert R * f_px == pytest.approx(40.0)
    mi = cam.mitsuba_settings()
    f_px_mi = 256 / math.tan(math.radians(mi["fov"]) / 2)
    assert mi["aperture_radius"] * f_px_mi == pytest.approx(40.0)
    assert mi["focus_distance"] == pytest.approx(2.0)


def test_plane_from_gradient_and_disparity():
    p = Plane.from_gradient(0.5, 0.01, -0.002, at=(10.0, -5.0))
    assert p.disparity(10.0, -5.0) == pytest.approx(0.5)
    assert p.disparity(11.0, -5.0) - p.disparity(10.0, -5.0) == pytest.approx(0.01)
    with pytest.raises(SceneError, match="<= 0 at the image centre"):
        Plane.from_gradient(0.1, 0.01, 0.0, at=(20.0, 0.0))


@settings(max_examples=60, deadline=None)
@given(a=st.floats(-0.01, 0.01), b=st.floats(-0.01, 0.01), c=st.floats(0.8, 20.0),
       A=st.floats(0.5, 40.0), df=st.floats(0.0, 1.2),
       x=st.floats(-50, 50), y=st.floats(-50, 50), phi=st.floats(0, 2 * math.pi),
       rho=st.floats(0, 1))
def test_max_shift_bounds_the_eq15_displacement(a, b, c, A, df, x, y, phi, rho):
    """Property: Plane.max_shift over a box bounds |x_n - x| from Eq. 15 for every sensor
    point in the box and every aperture point."""
    p = Plane(a, b, c)
    if c - A * math.hypot(a, b) <= 1e-3:
        return
    mu, nu = rho * math.cos(phi), rho * math.sin(phi)
    t = (1 - a * x - b * y - c * df) / (a * A * mu + b * A * nu + c)
    shift = math.hypot(t * A * mu, t * A * nu)
    assert shift <= p.max_shift(A, df, -50, 50, -50, 50) * (1 + 1e-9) + 1e-9


def test_save_load_trace_round_trip(tmp_path):
    scene = generate(7, "varying", settings=None)
    save_scene(scene, tmp_path / "s")
    back = load_scene(tmp_path / "s")
    assert back.camera == scene.camera
    assert [c.name for c in back.cards] == [c.name for c in scene.cards]
    for a, b in zip(scene.cards, back.cards):
        np.testing.assert_array_equal(a.rgba, b.rgba)
        assert a.plane == b.plane and a.offset == b.offset
    smp = samples.stratified(16)
    small = dict(backend="numpy")
    img_a, _ = trace.trace(scene, smp, **small)
    img_b, _ = trace.trace(back, smp, **small)
    np.testing.assert_array_equal(img_a, img_b)


# -- a hand-written scene, and what goes wrong with it ------------------------------


def _hand_written(tmp_path, **card_changes):
    """A scene as a researcher would write it: a JSON file and one EXR texture."""
    rgba = np.ones((20, 30, 4), np.float32) * 0.5
    write_exr(tmp_path / "wall.exr", channels_from_rgba(rgba))
    card = {"name": "wall", "texture": "wall.exr", "disparity": 0.2, "offset": [-3, -4]}
    card.update(card_changes)
    card = {k: v for k, v in card.items() if v is not None}
    doc = {"camera": {"width": 24, "height": 12, "blur_parameter": 10.0, "focus_disparity": 0.3},
           "cards": [card]}
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    return tmp_path


def test_hand_written_scene_loads(tmp_path):
    scene = load_scene(_hand_written(tmp_path))
    assert scene.cards[0].plane == Plane(0.0, 0.0, 5.0)
    assert scene.cards[0].offset == (-3, -4)
    assert scene.camera.focal_length_px == pytest.approx(50 / 36 * 24)
    # offset defaults to centring the texture on the frame
    scene = load_scene(_hand_written(tmp_path, offset=None))
    assert scene.cards[0].offset == ((24 - 30) // 2, (12 - 20) // 2)


@pytest.mark.parametrize("change, message", [
    (dict(disparity=None, plane={"a": 0.0, "b": 0.0, "c": -1.0}), r"card 'wall' field 'plane.c': must be > 0"),
    (dict(disparity=None, plane={"a": 0.0, "b": 0.0, "c": 0.0}), r"card 'wall' field 'plane.c'"),
    (dict(disparity=None, plane={"a": 0.2, "b": 0.0, "c": 1.0}), r"card 'wall' field 'plane': disparity reaches"),
    (dict(disparity=None, plane={"a": 0.0, "b": float("nan"), "c": 1.0}), r"card 'wall' field 'plane.b': must be finite"),
    (dict(disparity=None, plane={"a": 0.0, "b": 0.0}), r"card 'wall' field 'plane': missing field 'c'"),
    (dict(disparity=-0.5), r"card 'wall' field 'disparity': must be > 0"),
    (dict(size=[31, 20]), r"card 'wall' field 'size': declared 31x20 but .*wall.exr' is 30x20"),
    (dict(texture="missing.exr"), r"card 'wall' field 'texture': file .*missing.exr' does not exist"),
    (dict(offset=[1.5, 0]), r"card 'wall' field 'offset': must be a pair of integers"),
    (dict(name="../evil"), r"field 'name': must match"),
])
def test_bad_card_gives_a_clear_error(tmp_path, change, message):
    with pytest.raises(SceneError, match=message) as err:
        load_scene(_hand_written(tmp_path, **change))
    assert "scene.json" in str(err.value)


def test_bad_texture_values(tmp_path):
    rgba = np.ones((20, 30, 4), np.float32)
    rgba[3, 4, 1] = np.nan
    root = _hand_written(tmp_path)
    write_exr(root / "wall.exr", channels_from_rgba(rgba))
    with pytest.raises(SceneError, match=r"card 'wall' field 'texture': NaN .*row 3, column 4, channel G"):
        load_scene(root)
    rgba[3, 4, 1] = 0.5
    rgba[0, 0, 3] = 1.5
    write_exr(root / "wall.exr", channels_from_rgba(rgba))
    with pytest.raises(SceneError, match=r"alpha outside \[0, 1\]"):
        load_scene(root)
    (root / "wall.exr").write_bytes(b"not an exr")
    with pytest.raises(SceneError, match=r"card 'wall' field 'texture': .*wall.exr"):
        load_scene(root)


@pytest.mark.parametrize("camera, message", [
    ({"width": 24, "height": 12, "blur_parameter": 0.0, "focus_disparity": 0.3}, "zero aperture"),
    ({"width": 24, "height": 12, "blur_parameter": 10.0, "focus_disparity": -1}, "'focus_disparity': must be >= 0"),
    ({"width": 0, "height": 12, "blur_parameter": 10.0, "focus_disparity": 0.3}, "'width': must be a positive integer"),
    ({"width": 24, "height": 12, "focus_disparity": 0.3}, "missing field 'blur_parameter'"),
    ({"width": 24, "height": 12, "blur_parameter": 10.0, "focus_disparity": 0.3, "fov": 3}, "unknown field"),
])
def test_bad_camera_gives_a_clear_error(tmp_path, camera, message):
    root = _hand_written(tmp_path)
    doc = json.loads((root / "scene.json").read_text())
    doc["camera"] = camera
    (root / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=message):
        load_scene(root)


def test_plane_through_the_lens(tmp_path):
    """A plane that stays in front of the camera over the card (d > 0) but crosses the
    aperture disk: Eq. 15's denominator changes sign there."""
    root = _hand_written(tmp_path, disparity=None, plane={"a": 0.0, "b": 0.09, "c": 1.0})
    doc = json.loads((root / "scene.json").read_text())
    doc["camera"]["blur_parameter"] = 100.0
    (root / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="card 'wall' field 'plane': the plane passes through the lens"):
        load_scene(root)


def test_missing_or_broken_scene_file(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nowhere")
    (tmp_path / "scene.json").write_text("{ not json")
    with pytest.raises(SceneError, match="cannot parse scene JSON"):
        load_scene(tmp_path)


def test_duplicate_card_names(tmp_path):
    root = _hand_written(tmp_path)
    doc = json.loads((root / "scene.json").read_text())
    doc["cards"].append(dict(doc["cards"][0]))
    (root / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="duplicate card name"):
        load_scene(root)


def test_blender_camera_sensor_fits():
    from mpib_validate.runtime.camera import blender_camera

    # 50 mm, f/2, 36x24 sensor, 640x480: f_px = 50/36*640, R = 0.05/4 m
    c = blender_camera(50, 36, 24, "HORIZONTAL", 640, 480, 2.0, 4.0)
    assert c.blur_parameter == pytest.approx(0.0125 * 50 / 36 * 640)
    assert c.focus_disparity == pytest.approx(0.25)
    # AUTO on a portrait image maps the sensor width to the height (the larger side)
    p = blender_camera(50, 36, 24, "AUTO", 480, 640, 2.0, 4.0)
    assert p.focal_length_px == pytest.approx(50 / 36 * 640)
    v = blender_camera(50, 36, 24, "VERTICAL", 640, 480, 2.0, 4.0)
    assert v.focal_length_px == pytest.approx(50 / 24 * 480)
    # the Cycles settings of a camera invert this conversion
    cam = Camera(320, 240, 12.0, 0.3)
    cy = cam.cycles_settings()
    back = blender_camera(cy["lens_mm"], cy["sensor_width_mm"], 24, "HORIZONTAL", 320, 240,
                          cy["fstop"], cy["focus_distance"])
    assert back.blur_parameter == pytest.approx(12.0) and back.focus_disparity == pytest.approx(0.3)
    with pytest.raises(ValueError, match="f-stop"):
        blender_camera(50, 36, 24, "AUTO", 10, 10, float("inf"), 1.0)
