"""The camera in an EXR header and Blender's sensor fit: ``mpib refocus`` takes a Blender
camera from the render it refocuses, and agrees with the extension.

The first tests write real EXR files by hand; the others run real bpy (Cycles on the
CPU) with the extension's handlers registered from this checkout
(tests/blender/camera_session.py) and refocus what Blender wrote.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpib_validate.runtime.camera import blender_camera
from mpib_validate.runtime.io.camera_header import (NOTE_MARKER, camera_from_header, camera_json,
                                          resolve)
from mpib_validate.cli import main
from mpib_validate.runtime.io.exr import channels_from_rgba, read_exr, rgba_from, write_exr

ROOT = Path(__file__).resolve().parent.parent
LENS = {"lens_mm": 50.0, "sensor_width_mm": 36.0, "sensor_height_mm": 24.0, "sensor_fit": "AUTO",
        "fstop": 2.0, "focus_distance": 3.0, "unit_scale": 1.0, "width": 27, "height": 48}


def passes_exr(path, attributes=None, size=(27, 48)):
    """A small opaque colour + depth EXR (depth 1 to 4 m) with the given header attributes."""
    W, H = size
    rng = np.random.default_rng(0)
    rgba = np.ones((H, W, 4), np.float32)
    rgba[..., :3] = rng.random((H, W, 3))
    depth = np.full((H, W), 4.0, np.float32)
    depth[H // 4: H // 2, W // 4: W // 2] = 1.0
    write_exr(path, {**channels_from_rgba(rgba), "Depth.Z": depth}, attributes=attributes or {})
    return path


def refocus_cli(capsys, *args):
    """``mpib refocus`` in this process: (exit status, stdout, stderr)."""
    rc = main(["refocus", *map(str, args), "--no-preview"])
    out = capsys.readouterr()
    return rc, out.out, out.err


def used_camera(path) -> dict:
    return json.loads(read_exr(path).header["mpib"])["camera"]


# -- sensor fit: one conversion --------------------------------------------------------------

@pytest.mark.parametrize("fit, A", [("AUTO", 100 / 3), ("HORIZONTAL", 18.75), ("VERTICAL", 50.0)])
def test_portrait_frame_blur_parameter_follows_blenders_sensor_fit(fit, A):
    """1080x1920 at f/2, 50 mm, 36 x 24 mm sensor: R = 12.5 mm and f_px = 50/36*1920
    (AUTO: the sensor width across the larger side), 50/36*1080 or 50/24*1920, so
    A = 33.3, 18.75 and 50 px. The CLI's options and the extension both go through
    ``resolve``/``blender_camera``; before, the CLI gave 18.75 px for every fit."""
    lens = {**LENS, "sensor_fit": fit, "width": 1080, "height": 1920}
    assert blender_camera(**lens).blur_parameter == pytest.approx(A, rel=1e-12)
    given = {"fstop": 2.0, "lens_mm": 50.0, "sensor_fit": fit, "focus_distance": 3.0}
    assert resolve(None, given, 1080, 1920, "x.exr").camera.blur_parameter == pytest.approx(A, rel=1e-12)


@pytest.mark.parametrize("fit", ["AUTO", "HORIZONTAL", "VERTICAL"])
def test_cli_sensor_fit_option(tmp_path, capsys, fit):
    """The same portrait ratios at 27x48 (1080x1920 / 40): A is 1/40 of the above."""
    src = passes_exr(tmp_path / "in.exr")
    rc, out, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr", "--fstop", 2, "--focal-mm", 50,
                               "--focus-depth", 3, "--sensor-fit", fit.lower())
    assert rc == 0, err
    A = {"AUTO": 100 / 3, "HORIZONTAL": 18.75, "VERTICAL": 50.0}[fit] / 40
    cam = used_camera(tmp_path / "o.exr")
    assert cam["blur_parameter"] == pytest.approx(A, rel=1e-12)
    assert cam["lens"]["sensor_fit"] == fit and cam["from"]["sensor_fit"] == "--sensor-fit"
    assert cam["from"]["sensor_width_mm"] == "default"


# -- the header --------------------------------------------------------------------------------

@pytest.mark.parametrize("where", ["mpib", "Note"])
def test_header_camera_needs_no_lens_options(tmp_path, capsys, where):
    """The camera in the ``mpib`` attribute, or in Blender's stamp note after the
    artist's own text: no options needed, and the output says each field came from it."""
    text = camera_json(LENS)
    attrs = {"mpib": text} if where == "mpib" else {"Note": f"shot 12 {NOTE_MARKER}{text}"}
    src = passes_exr(tmp_path / "in.exr", attrs)
    rc, out, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr")
    assert rc == 0, err
    want = blender_camera(**LENS)
    cam = used_camera(tmp_path / "o.exr")
    assert cam["blur_parameter"] == want.blur_parameter
    assert cam["focus_disparity"] == want.focus_disparity
    assert cam["lens"] == {k: LENS[k] for k in cam["lens"]}
    assert set(cam["from"]) == {"lens_mm", "sensor_width_mm", "sensor_height_mm", "sensor_fit",
                                "fstop", "unit_scale", "focus_distance"}
    assert all(where in v and "in.exr" in v for v in cam["from"].values()), cam["from"]


def test_options_override_the_header_field_by_field(tmp_path, capsys):
    src = passes_exr(tmp_path / "in.exr", {"mpib": camera_json(LENS)})
    rc, _, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr", "--fstop", 4,
                             "--sensor-fit", "VERTICAL", "--focus-depth", 2)
    assert rc == 0, err
    cam = used_camera(tmp_path / "o.exr")
    want = blender_camera(**{**LENS, "fstop": 4.0, "sensor_fit": "VERTICAL", "focus_distance": 2.0})
    assert cam["blur_parameter"] == want.blur_parameter and cam["focus_disparity"] == 0.5
    assert cam["from"]["fstop"] == "--fstop" and cam["from"]["sensor_fit"] == "--sensor-fit"
    assert cam["from"]["focus_distance"] == "--focus-depth"
    assert "'mpib'" in cam["from"]["lens_mm"] and "'mpib'" in cam["from"]["sensor_height_mm"]
    # A given directly keeps the header's focus
    rc, _, err = refocus_cli(capsys, src, "-o", tmp_path / "p.exr", "--blur-parameter", 3)
    assert rc == 0, err
    cam = used_camera(tmp_path / "p.exr")
    assert cam["blur_parameter"] == 3.0 and cam["focus_disparity"] == 1 / 3.0
    assert "lens" not in cam and cam["from"]["blur_parameter"] == "--blur-parameter"


def test_blenders_lens_stamp_gives_the_focal_length_only(tmp_path, capsys):
    """Without the extension, Blender's Lens stamp (Metadata > Lens) is all there is:
    the f-stop and focus must be given, and the message says so."""
    src = passes_exr(tmp_path / "in.exr", {"Lens": "85.00 mm"})
    rc, _, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr", "--focus-depth", 3)
    assert rc == 2 and "no f-stop: give --fstop" in err and "in.exr" in err and "Lens" in err
    rc, _, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr", "--focus-depth", 3, "--fstop", 2)
    assert rc == 0, err
    cam = used_camera(tmp_path / "o.exr")
    assert cam["lens"]["lens_mm"] == 85.0 and "Lens" in cam["from"]["lens_mm"]
    assert cam["blur_parameter"] == pytest.approx(85e-3 / 4 * 85 / 36 * 48, rel=1e-12)


def _bad(case):
    lens = dict(LENS)
    if case == "not-json":
        return {"mpib": "{camera: 1"}, "'mpib'"
    if case == "fstop":
        lens["fstop"] = -1
        return {"mpib": json.dumps({"camera": {"blender": lens}})}, "camera.blender.fstop"
    if case == "missing":
        del lens["lens_mm"]
        return {"mpib": json.dumps({"camera": {"blender": lens}})}, "lens_mm"
    if case == "fit":
        lens["sensor_fit"] = "DIAGONAL"
        return {"mpib": json.dumps({"camera": {"blender": lens}})}, "camera.blender.sensor_fit"
    if case == "width-type":
        lens["width"] = 27.5
        return {"mpib": json.dumps({"camera": {"blender": lens}})}, "camera.blender.width"
    if case == "size":
        lens["width"], lens["height"] = 54, 96
        return {"mpib": json.dumps({"camera": {"blender": lens}})}, "camera.blender.width is 54"
    if case == "camera-type":
        return {"mpib": json.dumps({"camera": [1, 2]})}, "field camera"
    if case == "image-space":
        return {"mpib": json.dumps({"camera": {"blur_parameter": "big"}})}, "camera.blur_parameter"
    if case == "note-truncated":
        return {"Note": NOTE_MARKER + camera_json(LENS)[:-20]}, "'Note'"
    if case == "lens-stamp":
        return {"Lens": "fifty"}, "'Lens'"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["not-json", "fstop", "missing", "fit", "width-type", "size",
                                  "camera-type", "image-space", "note-truncated", "lens-stamp"])
def test_header_errors_name_the_file_and_the_field(tmp_path, capsys, case):
    attrs, field = _bad(case)
    src = passes_exr(tmp_path / "in.exr", attrs)
    before = src.read_bytes()
    rc, out, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr")
    assert rc == 2, (out, err)
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "in.exr" in err and field in err, err
    assert src.read_bytes() == before and not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("options, names", [
    (["--fstop", 2], ["--fstop"]),
    (["--focal-mm", 35, "--sensor-fit", "AUTO"], ["--focal-mm", "--sensor-fit"]),
    (["--scene-unit-m", 0.01], ["--scene-unit-m"]),
])
def test_blur_parameter_with_lens_options_is_refused(tmp_path, capsys, options, names):
    src = passes_exr(tmp_path / "in.exr", {"mpib": camera_json(LENS)})
    rc, out, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr", "--blur-parameter", 2, *options)
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "--blur-parameter" in err and all(n in err for n in names), err
    assert not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("options, text", [
    (["--fstop", 0], "--fstop must be a finite number > 0"),
    (["--sensor-height-mm", -2], "--sensor-height-mm must be"),
    (["--scene-unit-m", 0], "--scene-unit-m must be"),
    (["--focal-mm", "nan"], "--focal-mm must be"),
    (["--focus-depth", 0], "--focus-depth must be"),
])
def test_bad_lens_options_name_the_option(tmp_path, capsys, options, text):
    src = passes_exr(tmp_path / "in.exr", {"mpib": camera_json(LENS)})
    rc, out, err = refocus_cli(capsys, src, "-o", tmp_path / "o.exr", *options)
    assert rc == 2 and text in err and len(err.strip().splitlines()) == 1, err


# -- real Blender --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blender(tmp_path_factory):
    pytest.importorskip("bpy")
    work = tmp_path_factory.mktemp("camera_session")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               BLENDER_USER_RESOURCES=str(work / "blender_user"))
    r = subprocess.run([sys.executable, str(ROOT / "tests" / "blender" / "camera_session.py"),
                        str(work)], capture_output=True, text=True, timeout=600, env=env, cwd=work)
    lines = [l for l in r.stdout.splitlines() if l.startswith("RESULT ")]
    assert r.returncode == 0 and lines, r.stdout[-3000:] + r.stderr[-3000:]
    return json.loads(lines[-1][7:]), work


def _header_free_copy(src, dst):
    """The same colour and depth without any header camera (a render from elsewhere)."""
    img = read_exr(src)
    rgba = rgba_from(img, "ViewLayer.Combined.")
    write_exr(dst, {**channels_from_rgba(rgba), "Depth.Z": img.channels["ViewLayer.Depth.Z"]})
    return dst


@pytest.mark.parametrize("fit", ["AUTO", "HORIZONTAL", "VERTICAL"])
def test_blender_portrait_render_cli_and_extension_agree(blender, capsys, tmp_path, fit):
    """A 27x48 render (1080x1920's ratio) of a 50 mm f/1 camera focused on an empty at
    planar depth 3 m, off the axis (distance 3.04 m). Blender's own projection matrix
    gives f_px = 66.7, 37.5 and 100 px for AUTO, HORIZONTAL and VERTICAL; the header's
    camera gives the same (to float32, 1e-6). The extension's refocus of the file and
    ``mpib refocus`` of it with no lens options use the same A and focus and give the
    same pixels; so does ``mpib refocus`` of a header-free copy with the lens options."""
    out, work = blender
    f = out["fits"][fit]
    assert f["operator"] == ["FINISHED"] and f["saved"], f["message"]
    want_f_px = {"AUTO": 50 / 36 * 48, "HORIZONTAL": 50 / 36 * 27, "VERTICAL": 50 / 24 * 48}[fit]
    assert f["f_px_blender"] == pytest.approx([want_f_px] * 2, rel=1e-6)
    assert f["header"]["blender"] == {**LENS, "fstop": 1.0, "sensor_fit": fit}
    assert "'Note'" in f["header"]["source"]

    rc, _, err = refocus_cli(capsys, f["render"], "-o", tmp_path / "cli.exr")
    assert rc == 0, err
    ours, theirs = used_camera(tmp_path / "cli.exr"), f["saved_mpib"]["camera"]
    assert ours["focal_length_px"] == pytest.approx(want_f_px, rel=1e-12)
    assert ours["blur_parameter"] == theirs["blur_parameter"] == pytest.approx(0.025 * want_f_px, rel=1e-12)
    assert ours["focus_disparity"] == theirs["focus_disparity"] == 1 / 3.0
    np.testing.assert_array_equal(rgba_from(read_exr(tmp_path / "cli.exr")),
                                  rgba_from(read_exr(f["saved"])))

    bare = _header_free_copy(f["render"], tmp_path / "bare.exr")
    rc, _, err = refocus_cli(capsys, bare, "-o", tmp_path / "opts.exr", "--fstop", 1, "--focal-mm", 50,
                             "--focus-depth", 3, "--sensor-fit", fit)
    assert rc == 0, err
    assert used_camera(tmp_path / "opts.exr")["blur_parameter"] == theirs["blur_parameter"]
    np.testing.assert_array_equal(rgba_from(read_exr(tmp_path / "opts.exr")),
                                  rgba_from(read_exr(f["saved"])))


def test_the_kept_passes_carry_the_camera(blender):
    out, _ = blender
    for fit, f in out["fits"].items():
        assert f["kept_passes_header"]["blender"] == f["header"]["blender"], fit


def test_cycles_blurs_an_emitter_as_the_header_camera_says(blender):
    """Physics: a 2 cm emitter at planar depth 0.5 m, focus 10 m, f/1, 27x48 AUTO, 1024
    samples. The header camera predicts r = A |1/0.5 - 1/10| = 3.17 px (HORIZONTAL would
    give 1.78 px, VERTICAL 4.75 px). Cycles' blur radius from the second moment of its
    image (a disk has variance r^2/4 per axis; the square's side s adds s^2/12 and the
    box pixel filter 1/12): measured 3.22 and 3.24 px (x, y), 2 % above; we allow 5 %."""
    out, work = blender
    img = read_exr(out["dot"])
    cam = camera_from_header(img.header, out["dot"], 27, 48)
    I = img.channels["ViewLayer.Combined.R"].astype(np.float64)
    ys, xs = np.mgrid[0:48, 0:27] + 0.5
    E = I.sum()
    assert E == pytest.approx((0.02 * cam.focal_length_px / 0.5) ** 2, rel=0.02)  # energy kept
    side = 0.02 * cam.focal_length_px / 0.5
    r_true = cam.blur_radius(2.0)
    for c in (xs, ys):
        mean = (I * c).sum() / E
        var = (I * (c - mean) ** 2).sum() / E
        r = 2.0 * np.sqrt(var - side ** 2 / 12 - 1 / 12)
        assert r == pytest.approx(r_true, rel=0.05), (r, r_true)


def test_animation_frames_carry_their_focus_and_keep_the_artists_note(blender):
    out, _ = blender
    anim = out["animation"]
    assert anim["1"]["camera"]["blender"]["focus_distance"] == pytest.approx(6.0)
    assert anim["2"]["camera"]["blender"]["focus_distance"] == pytest.approx(1.5)
    assert all(a["note"].startswith("shot 12 " + NOTE_MARKER) for a in anim.values())
    assert out["note_after_animation"] == [True, "shot 12"]  # the scene's note is restored


def test_burn_into_image_gets_no_note(blender):
    """A note would be drawn into the pixels: none is added, and the panel says why."""
    out, _ = blender
    assert out["burn_in"]["camera"] is None
    assert "Burn Into Image" in out["burn_in"]["message"]
    assert out["burn_in"]["note_after"] == [False, ""]


def test_unit_scale_does_not_change_cycles_depth_of_field(blender):
    """Cycles' lens is lens_mm * 1e-3 Blender units whatever the scene's Unit Scale:
    the same seed gives the very same depth-of-field image at scale 1 and 0.1, so the
    header records unit_scale 1 for both."""
    out, work = blender
    a, b = (np.load(work / f"unit_{s}.npy") for s in ("1.0", "0.1"))
    assert a.sum() > 1.0 and np.array_equal(a, b)
    assert [out["unit_scale"][s]["blender"]["unit_scale"] for s in ("1.0", "0.1")] == [1.0, 1.0]
