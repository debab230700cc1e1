"""The MPIB Refocus node group follows the camera's aperture: blades (0, 3 to 16), rotation
and ratio (issue 29; docs/aperture.md for Cycles' conventions, the ``_ApertureOps`` of
``mpib_validate.runtime.blender.nodegroup`` for the Bokeh Image's and Convolve's).

Real bpy 5.0.1 (Cycles on the CPU): the extension's operator makes the group for a camera
with 6 blades rotated 15 degrees (and 5 blades, whose footprint turns over between the
sides of the focus; and ratio 1.5), the compositor renders it and the numpy model of the
same description must give the same image; point emitters refocused by the group match
Cycles' own depth of field in shape (the lens helper's footprint measurement)."""

from __future__ import annotations

import hashlib
import math
import sys

import numpy as np
import pytest

from mpib_validate.blender.nodegroup_run import run_on_passes
from mpib_validate.runtime.blender import nodegroup as ng
from mpib_validate.runtime.camera import DISK, Aperture

HEX = Aperture(6, math.radians(15))
PENTA = Aperture(5, math.radians(10))

#: sha256 (first 16 hex) of the ops of a disk camera's graphs, per (fill, blur), as the
#: builder made them before it knew apertures (commit 7640842).
DISK_GRAPHS = {("inpaint", "bokeh"): "46998ae42375451c", ("inpaint", "convolve"): "cfdf7bb2fc54b92f",
               ("off", "bokeh"): "45a38411c0bbfb99", ("off", "convolve"): "9a9b1d7819ee1508"}


def _digest(spec) -> str:
    return hashlib.sha256(repr(ng.describe(spec).ops).encode()).hexdigest()[:16]


@pytest.mark.parametrize("fill, blur", sorted(DISK_GRAPHS))
def test_a_disk_camera_keeps_the_group(fill, blur):
    """A disk of ratio 1 (any rotation) gives the same nodes as before, and no aperture
    inputs."""
    for ap in (None, DISK, Aperture(0, 0.7, 1.0)):
        spec = ng.make_spec((0.1, 0.3, 0.55, 1.0), 20.0, fill=fill, blur=blur,
                            focus_disparity=0.3, aperture=ap)
        assert _digest(spec) == DISK_GRAPHS[(fill, blur)]
        assert not spec.shaped and ng.interface_inputs(spec) == ng.INPUTS


def _corners(ap: Aperture, sign: int) -> np.ndarray:
    """Cycles' polygon corners (unit circumradius, y up), point-reflected for sign -1."""
    phi = ap.rotation + (2 * np.arange(ap.blades) + 1) * math.pi / ap.blades
    return sign * np.stack([np.cos(phi), np.sin(phi)], -1)


@pytest.mark.parametrize("ap", [HEX, PENTA, Aperture(3, math.radians(-40))])
def test_the_bokeh_image_draws_the_aperture_of_cycles(ap):
    """The model of Blender's Bokeh Image at the Angle the group gives it (behind the
    focus ``pi/2 - pi/n - theta``, in front ``+ pi``) is the polygon of Cycles: 1 at 97 %
    of the way to each of Cycles' corners, 0 at 97 % of the circumradius half-way between
    two (beyond the apothem cos(pi/n) <= 0.866); for odd blades the two sides differ."""
    n = ap.blades
    R = ng.BOKEH_IMAGE_SIZE / 2
    images = {}
    for sign, turn in ((1, 0.0), (-1, math.pi)):
        img = ng.bokeh_polygon_image(n, math.pi / 2 - math.pi / n - ap.rotation + turn)
        images[sign] = img
        c = _corners(ap, sign)
        mid = c + np.roll(c, -1, axis=0)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        for pts, want in ((c, 1.0), (mid, 0.0)):
            for x, y in pts * 0.97 * R + R:  # texel centres at i + 1/2, row 0 at the bottom
                assert img[int(y), int(x)] == want, (sign, x, y)
    differ = np.abs(images[1] - images[-1]).mean()
    assert (differ > 0.05) if n % 2 else (differ < 1e-3), differ


def test_anamorphic_groups_use_convolve_and_size_the_kernel_for_the_extent():
    """A ratio other than 1 puts every slice on Convolve (Bokeh Blur's image is square),
    refuses Bokeh Blur, and sizes the kernel for the wider axis (ratio 0.5: twice)."""
    d = (0.1, 0.3, 0.55, 1.0)
    plain = ng.make_spec(d, 20.0, blur="convolve", focus_disparity=0.3)
    wide = ng.make_spec(d, 20.0, blur="convolve", focus_disparity=0.3,
                        aperture=[Aperture(6, 0.2, 0.5), Aperture(6, 0.2, 1.0)])
    assert plain.bokeh_slices and not wide.bokeh_slices and wide.anamorphic
    assert wide.kernel_radius_px - 1 == 2 * (plain.kernel_radius_px - 1)
    with pytest.raises(ValueError, match="anamorphic"):
        ng.make_spec(d, 20.0, blur="bokeh", aperture=Aperture(0, 0.0, 1.5))
    with pytest.raises(ValueError, match="blades change"):
        ng.make_spec(d, 20.0, blur="convolve", aperture=[HEX, PENTA])


# --------------------------------------------------------------------------------------
# Real Blender: the operator, the group against its model

from tests.test_nodegroup import (ROOT, _assert_equals_the_model, _render_args,  # noqa: E402
                                  _session)


@pytest.fixture(scope="module")
def shaped(tmp_path_factory):
    """The cards scene (checker wall at 6 m, card at 1.5 m; focus keyed 6 m then 1.5 m, so
    the card's slice is in front of the focus, then the wall's behind it) with a shaped
    camera: 6 blades at 15 deg on Convolve and on Bokeh Blur, 5 blades at 10 deg (the
    footprint turns over with the side) on both, and 6 blades with ratio 1.5 (Convolve)."""
    pytest.importorskip("bpy")
    runs = {}
    for key, ap, blur in (("hex-conv", HEX, "CONVOLVE"), ("hex-bokeh", HEX, "BOKEH"),
                          ("penta-conv", PENTA, "CONVOLVE"), ("penta-bokeh", PENTA, "BOKEH"),
                          ("hex-ratio", Aperture(6, math.radians(15), 1.5), "CONVOLVE")):
        work = tmp_path_factory.mktemp(f"nodelens_{key}")
        runs[key] = _session(sys.executable, "render", _render_args(
            work, frames=[1, 2], keys={"focus": [[1, 6.0], [2, 1.5]]}, blur=blur,
            aperture=[ap.blades, ap.rotation, ap.ratio]))
    return runs


def test_shaped_group_equals_the_numpy_model(shaped):
    """6 blades at 15 deg (and 5 at 10 deg, ratio 1.5): the group the operator makes has
    the camera's blades, its rotation (and ratio) driven from the camera, and the
    compositor's output is the model's to MODEL_TOL on both keyed frames."""
    for key, res in shaped.items():
        assert res["operator"] == ["FINISHED"], (key, res["message"])
        spec = res["spec"]
        assert spec["blades"] == (5 if key.startswith("penta") else 6), key
        assert spec["anamorphic"] == (key == "hex-ratio")
        assert spec["blur"] == ("bokeh" if key.endswith("bokeh") else "convolve")
        drivers = res["drivers"]  # the lens's seven, rotation and ratio: simple and valid
        assert len(drivers) == len(ng.DRIVEN_INPUTS) + len(ng.SHAPE_INPUTS), drivers
        assert all(simple and valid for _, simple, valid in drivers.values()), drivers
        v = res["frames"]["1"]["values"]
        want = PENTA.rotation if key.startswith("penta") else HEX.rotation
        assert v["Aperture Rotation"] == pytest.approx(want, rel=1e-6)
        assert v["Aperture Ratio"] == pytest.approx(1.5 if key == "hex-ratio" else 1.0)
        _assert_equals_the_model(((res, "1"), (res, "2")))


def test_the_operator_refuses_a_ratio_bokeh_blur_cannot_draw(tmp_path):
    """Ratio 1.5 with Blur: Bokeh Blur: one line naming the limit, nothing built. Blender
    4.x (no Convolve; the Bokeh Image's Angle not a socket) refuses a ratio with the
    issue's line, and blades (not run here without a 4.2 environment: the refusal
    itself)."""
    bpy = pytest.importorskip("bpy")  # noqa: F841
    res = _session(sys.executable, "render", _render_args(
        tmp_path, blur="BOKEH", aperture=[0, 0.0, 1.5]))
    assert res["operator"] == ["CANCELLED"]
    assert res["message"].startswith("error: Bokeh Blur cannot draw an anamorphic aperture "
                                     "ratio"), res["message"]
    assert "\n" not in res["message"]
    sys.path.insert(0, str(ROOT))
    from blender_addon.nodegroup_ops import shape_refusal

    assert shape_refusal([Aperture(0, 0.0, 1.5)], True, "AUTO").startswith(
        "the node group cannot draw an anamorphic aperture ratio; use Refocus Last Render")
    assert shape_refusal([HEX], True, "AUTO") is None
    assert "blades change" in shape_refusal([HEX, PENTA], False, "AUTO")
    assert shape_refusal([HEX, Aperture(6, 0.1, 1.5)], False, "AUTO") is None
    assert shape_refusal([DISK], True, "BOKEH") is None


# --------------------------------------------------------------------------------------
# Against Cycles' depth of field: emitter footprints


def _node_footprints(aperture, side, group_aperture, blur="convolve", spp=1024):
    """Cycles' sharp render of the emitter card (lens helper's scene: 12 px circumradius)
    refocused by the group (numpy model and Blender's compositor) against Cycles' depth of
    field of the same scene; footprint figures (mpib_validate.blender.footprints)."""
    from mpib_validate.blender import cycles
    from mpib_validate.blender.footprints import compare, emitter_scene

    sc, centres, step, sizes = emitter_scene(aperture, side)
    dof, _, _ = cycles.render(sc, spp, 0, True, depth=False, threads=2)
    sharp, z, _ = cycles.render(sc, 1, 0, False, depth=True, threads=2)
    cam = sc.camera
    H, W = sharp.shape[:2]
    A = cam.blur_parameter
    f, sw = 50.0, 36.0
    values = {"Focus Distance": 1.0 / cam.focus_disparity, "Focal Length": f,
              "Sensor Width": sw, "Resolution X": W, "Resolution Y": H, "Unit Scale": 1.0,
              "F-Stop": f * 1e-3 * (f / sw * W) / (2.0 * A), "Film Transparent": 1.0,
              "Aperture Rotation": group_aperture.rotation,
              "Aperture Ratio": group_aperture.ratio}
    spec = ng.spec_from_render(z, A, fill="off", blur=blur, aperture=group_aperture)
    if not spec.shaped:  # a disk's group has no aperture inputs
        values = {k: v for k, v in values.items() if not k.startswith("Aperture")}
    graph = ng.describe(spec)
    out = run_on_passes(sharp, z, graph, values)["Image"]
    model = ng.evaluate(graph, sharp, z, values)["Image"]
    lum = lambda a: np.asarray(a[..., :3], np.float64).mean(-1)  # noqa: E731
    rows = compare(lum(out), lum(dof), centres, step, sizes, aperture.blades)
    return rows, float(np.abs(out - model).max())


def _convolve_or_skip():
    """The Convolve node exists from Blender 5.0 (the group's polygon kernels and its
    anamorphic ratio need it); before, those tests have nothing to run."""
    pytest.importorskip("bpy")
    if ng.is_legacy_api():
        pytest.skip("no Convolve node before Blender 5.0: the group refuses blur 'convolve'")


def _check(rows, gap, nfold_deg=2.0, iou=0.9):
    assert gap < 1e-3, gap
    for r in rows:
        assert r["iou"] >= iou, r
        if r["size"] >= 2:
            assert abs(r["nfold_err_deg"]) < nfold_deg, r


@pytest.mark.blender
@pytest.mark.parametrize("side", ["far", "near"])
def test_node_footprints_match_cycles_with_six_blades(side):
    """Emitters 1-3 px across, 12 px blur (circumradius), behind and in front of the
    focus, 6 blades at 15 deg: the group (Convolve) against Cycles' depth of field (1024
    spp): 6-fold orientation within 2 deg from 2 px across, IoU at half peak >= 0.9 at
    every size. A disk group of the same render fails the IoU."""
    _convolve_or_skip()
    rows, gap = _node_footprints(HEX, side, HEX)
    print(side, [(r["size"], round(r["nfold_err_deg"], 2), round(r["iou"], 3),
                  [round(e, 2) for e in r["axis_err_pct"]]) for r in rows])
    _check(rows, gap)
    bad, _ = _node_footprints(HEX, side, DISK)
    assert min(r["iou"] for r in bad) < 0.9


@pytest.mark.blender
@pytest.mark.parametrize("side", ["far", "near"])
def test_node_footprints_turn_over_with_five_blades(side, request):
    """5 blades at 10 deg: a point in front of the focus spreads into the pentagon turned
    by 180 degrees, which for odd blades is another shape: Convolve and Bokeh Blur both
    follow the side (n-fold orientation within 2 deg, IoU >= 0.9; Bokeh Blur's whole-pixel
    radius draws the 12 px circumradius as 12.5 px)."""
    pytest.importorskip("bpy")
    blurs = ("bokeh",) if ng.is_legacy_api() else ("convolve", "bokeh")  # no Convolve on 4.x
    if ng.is_legacy_api():
        # measured on 4.2.23: IoU 0.75-0.81 at half peak, n-fold 1.6-2.8 deg, the group 0.013-0.015
        # from its numpy model: 4.2's Bokeh Blur weighs the pentagon's rim otherwise (known
        # limit, docs/blender.md); strict, so that a fix shows as an unexpected pass
        request.applymarker(pytest.mark.xfail(
            reason="Blender 4.x's Bokeh Blur draws the pentagon's rim unlike Cycles", strict=True))
    for blur in blurs:
        rows, gap = _node_footprints(PENTA, side, PENTA, blur=blur)
        print(side, blur, [(r["size"], round(r["nfold_err_deg"], 2), round(r["iou"], 3))
                           for r in rows])
        _check(rows, gap)
    # the control: the pentagon not turned over (the other side's shape) is 36 deg off
    rows, _ = _node_footprints(PENTA, side, Aperture(5, PENTA.rotation + math.pi),
                               blur=blurs[0])
    assert min(abs(r["nfold_err_deg"]) for r in rows if r["size"] >= 2) > 10.0


@pytest.mark.blender
@pytest.mark.parametrize("side", ["far", "near"])
def test_node_footprints_follow_the_ratio(side):
    """6 blades at 15 deg, ratio 1.5 (1.5 times taller than wide): the group's stretched
    Convolve kernels against Cycles, from 2 px across: the principal axis within 2 deg,
    the axis lengths within 2 %, the 6-fold orientation within 2 deg; IoU >= 0.9 at every
    size. Measured (1024 spp): 0.79 deg, 0.75 %, 1.06 deg, IoU 0.971-0.988 from 2 px
    (0.924-0.944 at 1 px). The ratio the other way round (x stretched) fails the axes."""
    _convolve_or_skip()
    ap = Aperture(6, math.radians(15), 1.5)
    rows, gap = _node_footprints(ap, side, ap)
    _check(rows, gap)
    for r in rows:
        if r["size"] >= 2:
            assert abs(r["orientation_err_deg"]) < 2.0, r
            assert max(abs(e) for e in r["axis_err_pct"]) < 2.0, r
    bad, _ = _node_footprints(ap, side, Aperture(6, math.radians(15), 1 / 1.5))
    assert min(max(abs(e) for e in r["axis_err_pct"]) for r in bad) > 10.0


# --------------------------------------------------------------------------------------
# The other Blender versions (environments as tests/test_nodegroup.py finds them)


def test_newest_shaped_group_equals_the_numpy_model(tmp_path):
    """The newest 5.x: 6 blades at 15 deg on Convolve and 5 blades at 10 deg on Bokeh Blur
    (the Bokeh Image's Angle switched per slice), both keyed frames, equal the model."""
    from tests.test_nodegroup import _bpy5x_python

    python = _bpy5x_python()
    if python is None:
        pytest.skip("no Blender 5.x Python 3.13 environment (MPIB_BPY5X_PYTHON); not run")
    for key, ap, blur in (("hex", HEX, "CONVOLVE"), ("penta", PENTA, "BOKEH")):
        (tmp_path / key).mkdir()
        res = _session(python, "render", _render_args(
            tmp_path / key, frames=[1, 2], keys={"focus": [[1, 6.0], [2, 1.5]]}, blur=blur,
            aperture=[ap.blades, ap.rotation, ap.ratio]))
        assert res["version"].startswith("5.") and res["spec"]["blades"] == ap.blades
        _assert_equals_the_model(((res, "1"), (res, "2")))


def test_legacy_draws_blades_through_drivers_and_refuses_a_ratio(tmp_path):
    """Blender 4.2 (Bokeh Blur; the Bokeh Image's angle a property, set by a driver from
    the camera): 6 blades at 15 deg and 5 at 10 deg with the focus keyed so that the
    card's slice is in front of the focus at frame 1 and the wall's behind it at frame 2:
    the group renders as the model does (the 4.x Bokeh Image: ``legacy``), within 4.2's
    Bokeh Blur rim weights (LEGACY_TOL); the model with the pentagon not turned over is
    further off; the saved .blend renders the same without the extension. A ratio is
    refused in one line."""
    from tests.test_nodegroup import _assert_reopens_identically, _bpy42_python, _model_gap

    python = _bpy42_python()
    if python is None:
        pytest.skip("no Blender 4.2 Python (MPIB_BPY42_PYTHON); the 4.2 checks did not run")
    for ap in (HEX, PENTA):
        work = tmp_path / str(ap.blades)
        work.mkdir()
        res = _session(python, "render", _render_args(
            work, frames=[1, 2], keys={"focus": [[1, 6.0], [2, 1.5]]}, fstop=0.8, fill="OFF",
            aperture=[ap.blades, ap.rotation, ap.ratio], save=str(work / "lens42.blend")))
        assert res["version"].startswith("4.2") and res["operator"] == ["FINISHED"]
        # the saved drivers (the Bokeh Images' angles) render frame 2 the same without
        # the extension
        _assert_reopens_identically(python, res, work)
        assert res["spec"]["blades"] == ap.blades and res["spec"]["blur"] == "bokeh"
        for frame in ("1", "2"):
            gap, _ = _model_gap(res, frame, legacy=True)
            print(ap.blades, frame, gap)
            assert gap < LEGACY_TOL, (ap, frame, gap)
            if ap.blades % 2:  # the control: the other side's pentagon
                v = res["frames"][frame]["values"]
                turned = dict(res, frames={frame: dict(res["frames"][frame], values=dict(
                    v, **{"Aperture Rotation": v["Aperture Rotation"] + math.pi}))})
                wrong, _ = _model_gap(turned, frame, legacy=True)
                print("turned", frame, wrong)
                assert wrong > 2.5 * LEGACY_TOL, (frame, wrong)
    work = tmp_path / "ratio"
    work.mkdir()
    res = _session(python, "render", _render_args(work, aperture=[0, 0.0, 1.5]))
    assert res["operator"] == ["CANCELLED"]
    assert "cannot draw an anamorphic aperture ratio" in res["message"], res["message"]


#: 4.2's Bokeh Blur weighs a few rim taps of a polygon differently from the model (as it
#: does the disk's at some radii; an impulse at 20 px: 12 of 560 taps): measured here 4e-7
#: (6 blades) and 7.5e-3, 4.3e-3 (5 blades, frames 1, 2; the pentagon not turned over:
#: 0.037, 0.027).
LEGACY_TOL = 1e-2


def test_regenerating_for_another_aperture_keeps_the_links():
    """The group made for a disk, linked to a node after it, regenerated for 6 blades and
    back: the aperture inputs come and go, the other sockets' links stay."""
    bpy = pytest.importorskip("bpy")
    from mpib_validate.runtime.blender.compat import compositor_tree

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    d = (0.1, 0.5)
    group = ng.build_group(ng.describe(ng.make_spec(d, 20.0, blur="convolve")))
    tree = compositor_tree(sc, create=True)
    node = tree.nodes.new("CompositorNodeGroup")
    node.node_tree = group
    after = tree.nodes.new("CompositorNodeBlur")
    tree.links.new(node.outputs["Image"], after.inputs["Image"])
    for ap, has in ((HEX, True), (DISK, False)):
        ng.build_group(ng.describe(ng.make_spec(d, 20.0, blur="convolve", aperture=ap)),
                       group=group)
        assert ("Aperture Rotation" in node.inputs) == has
        assert after.inputs["Image"].is_linked
        assert after.inputs["Image"].links[0].from_socket == node.outputs["Image"]
