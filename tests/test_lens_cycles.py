"""The aperture's shape against Cycles (bpy, CPU): the tracer's polygon and ratio against
Cycles' own at the noise floor, and the refocused footprints of point emitters against
Cycles' depth of field (issue 29). Real bpy, Cycles, EXR files; small scenes, few samples."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from mpib_validate.blender import cycles  # noqa: E402
from mpib_validate.blender.footprints import compare, emitter_scene  # noqa: E402
from mpib_validate.cards import trace  # noqa: E402
from mpib_validate.cards.generate import GeneratorSettings, generate  # noqa: E402
from mpib_validate.runtime import samples  # noqa: E402
from mpib_validate.runtime.camera import DISK, Aperture  # noqa: E402
from mpib_validate.runtime.refocus import Passes, refocus  # noqa: E402
from mpib_validate.runtime.request import RefocusRequest  # noqa: E402

pytestmark = pytest.mark.blender

HEX = Aperture(6, math.radians(15), 1.5)
PENTA = Aperture(5, math.radians(10))
K_RENDERS = 8  # independent Cycles renders (t_7 statistics need K >= 6)
SPP = 64
REF_SAMPLES = 8192  # per tracer half


def _scene(aperture):
    """The 48x40 'constant' card scene of the disk tests, its blur radius scaled x3 so
    that the shape shows (radii up to ~8 px), with ``aperture``."""
    sc = generate(0, "constant", settings=GeneratorSettings(48, 40))
    return sc.with_camera(blur_parameter=3.0 * sc.camera.blur_parameter, aperture=aperture)


@pytest.mark.parametrize("aperture", [HEX, PENTA])
def test_cycles_matches_tracer_with_blades_and_ratio(aperture):
    """Cycles with the camera's blades, rotation and ratio against the tracer sampling
    the same polygon (two independent 8192-sample halves), at the noise floor (the
    6-sigma tolerances of :func:`cycles.agreement`); Cycles with another aperture (a
    disk; the polygon unrotated) must fail the same test."""
    sc = _scene(aperture)
    a, _ = trace.trace(sc, samples.stratified(REF_SAMPLES, seed=0, aperture=aperture),
                       notices=False)
    b, _ = trace.trace(sc, samples.stratified(REF_SAMPLES, seed=1, aperture=aperture),
                       notices=False)
    ref, ref_var = 0.5 * (a + b), (a.astype(np.float64) - b) ** 2 / 4.0
    res = cycles.agreement(cycles.render_many(sc, SPP, range(K_RENDERS), threads=2), ref,
                           ref_var)
    assert res["ok"], res
    for wrong in (DISK, dataclasses.replace(aperture, rotation=0.0)):
        bad = cycles.agreement(cycles.render_many(sc.with_camera(aperture=wrong), SPP,
                                                  range(100, 100 + K_RENDERS), threads=2),
                               ref, ref_var)
        assert not bad["ok"], (wrong, bad)


def _reference_spp() -> int:
    """Samples of Cycles' depth of field for the footprints: 1024 from Blender 5.0; Cycles
    4.x's sampler is noisier at the 1 px emitters' rims (measured on 4.2.23 at 1024 spp:
    IoU 0.896 and a 2.07 deg n-fold angle), so 4x the samples there."""
    from mpib_validate.runtime.blender import compat

    return 1024 if compat.version() >= (5, 0, 0) else 4096


def _footprints(aperture, side, refocus_aperture, spp=None):
    spp = _reference_spp() if spp is None else spp
    sc, centres, step, sizes = emitter_scene(aperture, side)
    dof, _, _ = cycles.render(sc, spp, 0, True, depth=False, threads=2)
    sharp, z, _ = cycles.render(sc, 1, 0, False, depth=True, threads=2)
    cam = sc.camera
    p = Passes(sharp[..., :3].copy(), z.astype(np.float64), "cycles", "cycles",
               alpha=sharp[..., 3].copy(), pixel_model="texel")
    img = refocus(RefocusRequest(p, cam.blur_parameter, cam.focus_disparity, "default",
                                 aperture=refocus_aperture)).image
    lum = lambda a: np.asarray(a[..., :3], np.float64).mean(-1)  # noqa: E731
    return compare(lum(img[..., :3] * img[..., 3:4]), lum(dof), centres, step, sizes,
                   aperture.blades)


@pytest.mark.parametrize("side", ["far", "near"])
@pytest.mark.parametrize("aperture", [HEX, Aperture(6, math.radians(40)), PENTA,
                                      Aperture(8, math.radians(-20), 1.5)])
def test_emitter_footprints_match_cycles(aperture, side):
    """Emitters 1, 2 and 3 px across, 12 px blur (circumradius), behind and in front of the
    focus: ``mpib``'s refocus of Cycles' sharp render against Cycles' own depth of field
    (1024 spp), for 5, 6 and 8 blades, two rotations of 6, ratio 1.5 or 1. Targets (issue
    29), from 2 px across: the principal axis within 2 degrees (where the ratio gives the
    covariance one: a regular polygon's is isotropic), the axis lengths within 2 %; the
    n-fold orientation (the rotation) within 2 degrees; IoU at half peak >= 0.9 at every
    size. Measured (1024 spp; 6 blades 15 deg ratio 1.5): axes within 1.0 %, principal
    axis within 0.7 degrees, 6-fold within 0.9 degrees, IoU 0.97-0.99 from 2 px
    (0.92-0.94 at 1 px, Cycles' noise dominating; 8192 spp: 0.23 %, 0.19 deg, 0.35 deg,
    IoU >= 0.988). A disk refocus of the same render fails it, an unrotated polygon too."""
    rows = _footprints(aperture, side, aperture)
    for r in rows:
        assert r["iou"] >= 0.9, r
        if r["size"] >= 2:
            if aperture.ratio != 1.0:
                assert abs(r["orientation_err_deg"]) < 2.0, r
            assert max(abs(e) for e in r["axis_err_pct"]) < 2.0, r
            assert abs(r["nfold_err_deg"]) < 2.0, r
    if aperture == HEX:  # the control: the disk the refocus used before
        bad = _footprints(HEX, side, DISK)
        assert max(max(abs(e) for e in r["axis_err_pct"]) for r in bad) > 5.0
        assert min(r["iou"] for r in bad) < 0.9
        # and the polygon unrotated: its 6-fold orientation is off (9.1 deg measured: the
        # ratio bends the harmonic; 15 deg apart in rotation)
        turned = _footprints(HEX, side, dataclasses.replace(HEX, rotation=0.0))
        assert min(abs(r["nfold_err_deg"]) for r in turned if r["size"] >= 2) > 5.0


def test_the_extension_reads_the_lens_from_the_scene_camera():
    """The extension's one camera reading path (runtime/blender/camera.read_camera) takes
    blades, rotation and ratio from the scene camera, keyed values at the frame
    included; the stamp note carries them to ``mpib refocus``; 1 or 2 blades read as a
    disk, as Cycles renders them."""
    from mpib_validate.runtime.blender.camera import read_camera
    from mpib_validate.runtime.camera import blender_camera
    from mpib_validate.runtime.io.camera_header import (LENS_FIELDS, read_camera as header_camera,
                                                        resolve, stamp_note)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = 64, 48
    data = bpy.data.cameras.new("Camera")
    obj = bpy.data.objects.new("Camera", data)
    sc.collection.objects.link(obj)
    sc.camera = obj
    dof = data.dof
    dof.use_dof = True
    dof.aperture_blades, dof.aperture_rotation = 6, math.radians(15)
    dof.aperture_ratio = 1.5
    dof.keyframe_insert("aperture_ratio", frame=1)
    dof.aperture_ratio = 2.0
    dof.keyframe_insert("aperture_ratio", frame=11)

    def lens(frame):
        fields = read_camera(sc, frame).lens()
        fields["focus_distance"] = 10.0
        return fields

    at1, at11 = (blender_camera(**lens(f)).aperture for f in (1, 11))
    assert (at1.blades, at1.ratio) == (6, 1.5)
    assert at1.rotation == pytest.approx(math.radians(15), rel=1e-7)  # Blender's float32
    assert at11.ratio == pytest.approx(2.0) and at11.blades == 6
    note = stamp_note(lens(1))
    assert note is not None
    got = resolve(header_camera({"Note": note}, "r.exr"), {}, 64, 48, "r.exr").camera.aperture
    assert got == at1
    assert set(LENS_FIELDS) <= set(lens(1))
    dof.aperture_blades = 2
    sc.frame_set(1)
    assert blender_camera(**lens(None)).aperture.blades == 0


def test_lens_bench_runs_tiny(tmp_path):
    """``mpib bench --suite lens`` on one kind at 64x48: a row per focus and lens, the
    lens read back from the passes' header, the summary's targets computed."""
    from mpib_validate.bench import lens as bench_lens

    res = bench_lens.run(tmp_path, config={"width": 64, "height": 48, "spp": 4,
                                           "sharp_spp": 4, "kinds": ("spheres",)})
    rows = res["rows"]
    assert len(rows) == 2 * len(bench_lens.LENSES)
    assert {r["lens"] for r in rows} == {"disk", "6 blades at 15 deg", "disk, ratio 1.5"}
    assert all(r["aperture_read"] == r["lens"] for r in rows)
    assert all(math.isfinite(r["default_psnr_ob"]) and math.isfinite(r["node_psnr_ob"])
               for r in rows)
    assert {"beats_node_everywhere", "within_half_db"} <= set(res["summary"])
    assert (tmp_path / "lens.md").is_file()
