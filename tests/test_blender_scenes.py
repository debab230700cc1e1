"""The Blender scene suite (bpy 5.0.1, Cycles on the CPU): builder, Z pass, truth, noise.

Real bpy and real EXR files, tiny sizes (96x72) and few samples so the default run stays
well under a minute. Every tolerance comes from float32 rounding, the measured Monte
Carlo noise or the pixel model, as commented where it is used.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("bpy")

from mpib_validate.blender import scenes as B
from mpib_validate.blender import cycles
from mpib_validate import metrics
from mpib_validate.bench import blender as BB  # noqa: E402

W, H = 96, 72
#: Relative tolerance on Z against an analytic plane depth: Cycles intersects in
#: float32 (a few hundred ulps on oblique planes, see DEPTH_TOL in test_cycles.py);
#: a Z taken anywhere but at the pixel centre would be off by ~1 % on the ground rows.
DEPTH_TOL = 1e-4


def _spec(kind, focus="far", **kw):
    return B.SceneSpec(kind, 0, W, H, focus, **kw)


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    """Suzanne (focus on the wall) through render_suite, 64 spp truth, in a cache."""
    out = tmp_path_factory.mktemp("blender-suite")
    spec = _spec("suzanne", "far")
    folders = B.render_suite(out, [spec], 64, sharp_spp=32, log=lambda *_: None)
    return out, spec, folders[0]


def test_layouts_are_deterministic_per_seed_and_differ_between_seeds():
    for kind in B.KINDS:
        a = json.dumps(B.layout(_spec(kind)))
        assert a == json.dumps(B.layout(_spec(kind))), kind
        if kind != "emitters":  # its grid jitter is seeded too, but compared below
            assert a != json.dumps(B.layout(B.SceneSpec(kind, 1, W, H))), kind
    e0, _ = B.emitter_grid(_spec("emitters"))
    e1, _ = B.emitter_grid(B.SceneSpec("emitters", 1, W, H))
    assert e0 != e1


def test_bad_spec_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="kind"):
        B.SceneSpec("teapot").validate()
    with pytest.raises(ValueError, match="focus"):
        B.SceneSpec("suzanne", focus="middle").validate()
    with pytest.raises(ValueError, match="f-stop"):
        B.SceneSpec("suzanne", fstop=0.0).validate()


def test_builder_renders_the_same_image_twice():
    """Same spec, same Cycles seed: identical passes (the builder has no hidden state)."""
    spec = _spec("fence")
    a = B.render_sharp(spec, 4)
    b = B.render_sharp(spec, 4)
    assert np.array_equal(a["rgba"], b["rgba"]) and np.array_equal(a["depth"], b["depth"])
    assert np.all(a["rgba"][..., 3] == 1.0)  # film opaque


def test_z_pass_is_the_analytic_depth_at_pixel_centres():
    """Wall: Z = 2.2 m wherever the wall is seen. Ground plane Y = h: the pixel-centre ray
    (x, y, f) / f meets it at Z = h f / y_c, y_c the row centre below the horizon."""
    z = B.render_sharp(_spec("suzanne"), 1)["depth"]
    wall = z > 1.5
    assert wall.mean() > 0.5
    assert np.allclose(z[wall], 2.2, rtol=DEPTH_TOL, atol=0)

    spec = _spec("ground")
    z = B.render_sharp(spec, 1)["depth"]
    lay = B.layout(spec)
    h = lay["objects"][0]["y"]
    f = B.lens(spec)["focal_length_px"]
    # an object point (Y <= h, Z >= its front depth) is seen at y = f Y / Z <= h f / Z_front:
    # rows below the nearest object's front are ground only
    front = min(o["loc"][2] - o["radius"] if o["shape"] == "sphere" else
                o["centre"][2] - o["half"][2] for o in lay["objects"][1:])
    yc = (np.arange(H) + 0.5 - H / 2)[:, None] * np.ones((1, W))
    ground = yc > h * f / front
    assert ground.sum() >= 4 * W
    expect = h * f / yc[ground]
    assert np.abs(z[ground] / expect - 1).max() <= DEPTH_TOL
    # a sample anywhere in the pixel would be off by up to 0.5 / y_c: far beyond DEPTH_TOL
    assert (0.5 / yc[ground]).min() > 100 * DEPTH_TOL


def test_truth_blurs_isolated_emitters_to_the_thin_lens_radius():
    """Second moment of each emitter's window: r^2 = 2 (E_truth - E_sharp) (the sharp
    render's moment holds the disk's own size and the pixel box; convolution adds
    moments). It must equal A |d - d_f| in front of and behind the focus plane."""
    spec = _spec("emitters", "near", fstop=0.6)
    dots, step = B.emitter_grid(spec)
    centres = [(e["row"], e["col"]) for e in dots]
    sharp = B.render_sharp(spec, 64)["rgba"]
    truth = B.render_truth(spec, 512)["renders"]
    c = B.lens(spec)
    r0 = cycles.dot_radii(sharp, centres, step, boxes=0)
    for side in ("front", "behind"):
        sel = np.array([(1 / e["z"] > c["focus_disparity"]) == (side == "front") for e in dots])
        expect = c["blur_parameter"] * abs(1 / dots[int(np.argmax(sel))]["z"] - c["focus_disparity"])
        assert expect > 3.0  # a radius worth measuring
        radii = np.concatenate([
            np.sqrt(cycles.dot_radii(t, centres, step, boxes=0) ** 2 - r0 ** 2)[sel]
            for t in truth])
        # emitters and seeds are independent noise: the standard error of the mean
        se = radii.std(ddof=1) / math.sqrt(radii.size)
        assert 5 * se < 0.03 * expect  # the test tells a 3 % radius error from noise
        assert abs(radii.mean() - expect) <= 5 * se, (side, radii.mean(), expect, se)


def test_two_seed_noise_estimate_predicts_a_third_seed():
    """With a, b the truth's seeds and m their mean, a third seed c has
    E[(c - m)^2] = sigma^2 + sigma^2 / 2, and (a - b)^2 / 2 estimates sigma^2: the ratio
    is 1 up to the chi^2 spread of both sums, sqrt(2 / n_eff) each (n_eff over pixels,
    RGB averaged per pixel as the channels share samples; from single-pair estimates,
    which makes n_eff smaller, so the tolerance is conservative)."""
    spec = _spec("spheres", "near")
    r = B.render_truth(spec, 16, seeds=(*B.TRUTH_SEEDS, 3))["renders"][..., :3].astype(np.float64)
    a, b, c = r
    m = 0.5 * (a + b)
    v = ((a - b) ** 2 / 2).mean(-1)  # per-pixel sigma^2 estimate
    dev = ((c - m) ** 2).mean(-1)
    ratio = dev.mean() / (1.5 * v.mean())
    n_eff = v.sum() ** 2 / (v ** 2).sum()
    tol = 5 * math.sqrt(2 / n_eff + 2 / n_eff)
    assert tol < 0.3  # a factor-2 error in the variance (ratio 1.67 or 0.67) fails
    assert abs(ratio - 1) <= tol, (ratio, tol, n_eff)
    nf = B.noise_figures(a, b)
    assert math.isclose(nf["rmse"] ** 2, ((a - b) ** 2).mean() / 4, rel_tol=1e-9)


def test_render_suite_writes_the_folder_and_reuses_it(suite):
    out, spec, folder = suite
    meta = json.loads((folder / "meta.json").read_text())
    c = B.lens(spec)
    assert math.isclose(meta["A"], c["blur_parameter"]) and math.isclose(meta["d_f"], 1 / 2.2)
    assert meta["noise"]["psnr"] > 30 and len(meta["seconds"]["truth"]) == 2
    stamp = (folder / "truth.exr").stat().st_mtime_ns
    again = B.render_suite(out, [spec], 64, sharp_spp=32, log=lambda *_: pytest.fail("rendered"))
    assert again == [folder] and (folder / "truth.exr").stat().st_mtime_ns == stamp
    # the passes carry the camera as `mpib render` does, so `mpib refocus` needs no lens options
    from mpib_validate.runtime.refocus import load_passes

    from mpib_validate.runtime.io.camera_header import resolve

    p = load_passes(folder / "passes.exr")
    assert math.isclose(p.camera.image["blur_parameter"], c["blur_parameter"], rel_tol=1e-12)
    assert p.camera.blender["fstop"] == c["fstop"]
    assert p.camera.blender["sensor_fit"] == "HORIZONTAL"
    # the Blender form alone gives the same camera (the header's two forms agree)
    only_lens = type(p.camera)(p.camera.source, p.camera.blender, {})
    cam = resolve(only_lens, {}, spec.width, spec.height, folder / "passes.exr").camera
    assert math.isclose(cam.blur_parameter, c["blur_parameter"], rel_tol=1e-9)
    assert math.isclose(cam.focus_disparity, c["focus_disparity"], rel_tol=1e-9)
    sc = B.load_scene(folder)
    assert np.allclose(sc.truth, sc.seeds.mean(0), atol=1e-6)


def test_default_preset_beats_the_sharp_input_at_boundaries(suite):
    """PSNR_ob against Cycles' depth of field: the refocused EXR (as written) is far
    closer than the sharp input, by more than the truth's own noise could move it."""
    from mpib_validate.runtime.refocus import load_passes, refocus
    from mpib_validate.runtime.request import RefocusRequest

    _, spec, folder = suite
    sc = B.load_scene(folder)
    p = load_passes(folder / "passes.exr")
    out = BB.premultiplied(refocus(RefocusRequest(p, p.camera.image["blur_parameter"], p.camera.image["focus_disparity"])).image)
    mask = BB.boundary_mask(sc.depth, sc.meta["A"], sc.meta["d_f"])
    assert 0.05 < mask.mean() < 0.9
    t = np.clip(sc.truth, 0, 1)
    ob_default = metrics.psnr(t, np.clip(out, 0, 1), mask)
    ob_sharp = metrics.psnr(t, np.clip(sc.colour, 0, 1), mask)
    a, b = np.clip(sc.seeds, 0, 1)
    floor = metrics.psnr(a, b, mask) + 20 * math.log10(2)  # the mean's noise
    assert ob_default - ob_sharp >= 3.0, (ob_default, ob_sharp)
    # the truth's noise (MSE 10^(-floor/10)) is under a third of the default's error
    assert floor >= ob_default + 5.0, (floor, ob_default)


def test_degraded_depth_methods_are_seeded_and_finite(suite):
    """The bench's degraded-depth methods: one image per method, finite, the same on a
    second run (the degradation is seeded per scene), and the degraded depth changes the
    output (the refocus does use it)."""
    from mpib_validate.runtime.refocus import load_passes

    _, spec, folder = suite
    sc = B.load_scene(folder)
    p = load_passes(folder / "passes.exr")
    A, d_f = p.camera.image["blur_parameter"], p.camera.image["focus_disparity"]
    a = BB.degraded_images(sc, p, A, d_f)
    b = BB.degraded_images(sc, p, A, d_f)
    from mpib_validate.bench.photos import ORACLES

    assert set(a) == {BB.DEGRADED, BB.DEGRADED_GUIDED, BB.DEGRADED_THIN, BB.NODE_DEGRADED,
                      *ORACLES.values()}
    for name in a:
        assert np.isfinite(a[name][0]).all()
        np.testing.assert_array_equal(a[name][0], b[name][0])
    from mpib_validate.runtime.refocus import refocus
    from mpib_validate.runtime.request import RefocusRequest

    exact = BB.premultiplied(refocus(RefocusRequest(p, A, d_f)).image)
    assert np.abs(a[BB.DEGRADED][0] - exact).max() > 0.05


def test_degraded_part_scores_the_rescoped_targets_and_remnants(suite):
    """The degraded-depth part alone (``run(..., degraded_only=True)`` per scene): every
    row has the re-scoped PSNR_ob (on a part of the boundary mask) and the remnant counts
    within the must-blur pixels; the page states both targets and names the rows."""
    _, spec, folder = suite
    sc = B.load_scene(folder)
    images = BB.degraded_part_images(sc)
    assert {BB.DEFAULT, BB.NODE, BB.DEGRADED_GUIDED, BB.NODE_DEGRADED} <= set(images)
    rows = BB.scene_rows(sc, images)
    for r in rows:
        if r["method"] == "truth noise floor":
            continue
        assert math.isfinite(r["psnr_ob_scoped"]) and 0 < r["scoped_fraction"] <= 1
        assert 0 <= r["remnants"] <= r["must_blur_smooth"] <= r["must_blur"]
        # the photographs' region: where the degraded map and its refinement both blur;
        # against the unrefined output for the methods fed the same degraded map
        assert 0 <= r["remnants_maps"] <= r["must_blur_maps"]
        assert ("remnants_maps_off" in r) == (r["method"] in BB.VS_UNREFINED)
    assert {BB.DEGRADED_GUIDED, BB.NODE_DEGRADED} <= {r["method"] for r in rows
                                                      if "remnants_maps_off" in r}
    result = {"rows": rows, "emitters": [], "scenes": []}
    summary = BB._summarise(result)
    assert "within 3 dB: " in summary["scope"]["headline"]
    assert "against the unrefined output (target 0.02 % over the suite" in (
        summary["remnants"]["headline"])
    assert set(summary["remnants"]["methods"]) == {m for m in BB.REMNANT_METHODS if m in images}


@pytest.mark.slow
def test_blender_bench_writes_its_page(tmp_path):
    """The whole suite at a tiny size: page, JSON, crops, plots; every scene and method."""
    res = BB.run(tmp_path, config={"width": 96, "height": 72, "spp": 16, "sharp_spp": 8})
    for name in ("blender.md", "blender.json", "blender-crops.png", "pareto-blender-psnr_ob.png"):
        assert (tmp_path / name).stat().st_size > 1000
    scenes = {r["scene"] for r in res["rows"]}
    assert len(scenes) == 2 * len(B.SUITE_KINDS)
    methods = {r["method"] for r in res["rows"]}
    from mpib_validate.bench.photos import ORACLES

    for m in ("preset-default", "preset-draft", "preset-best", "blender-defocus-node",
              "sharp input", "exact-mpi", "truth noise floor", BB.DEGRADED,
              BB.DEGRADED_GUIDED, BB.DEGRADED_THIN, BB.NODE_DEGRADED, *ORACLES.values()):
        assert m in methods
    assert len(res["emitters"]) == 2
    page = (tmp_path / "blender.md").read_text()
    assert "## Degraded depth" in page and "Where the loss lies" in page
    assert "re-scoped degraded-depth targets" in page and "sharp remnants against" in page
