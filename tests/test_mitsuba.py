"""Mitsuba 3 references (mitsuba_scenes): camera model, agreement with the ray tracer,
the stock path tracer and the XML export, and that the comparison catches real faults.

Agreement is judged by :func:`mitsuba_scenes.agreement`: per-pixel z-scores from the
per-sample variances of both renders, with a floor of 4 samples' worth of the pixel's
value bound (rare events), outliers at |z| > 4 and an allowed outlier count whose
Poisson tail is 1e-6 (derived in ``mitsuba_scenes/compare.py``). Every other
tolerance is derived where it is used.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from mpib_validate.runtime.compositor import backend as _backend
from mpib_validate.runtime import samples
from mpib_validate.cards import trace
from mpib_validate.runtime.camera import Camera
from mpib_validate.cards.generate import FAMILIES, HARD_CASES, GeneratorSettings, generate
from mpib_validate.cards.scene import Card, Plane, Scene

import mitsuba_scenes as ms
from mitsuba_scenes import build, geometry, variants
from mitsuba_scenes.compare import poisson_isf

from conftest import opaque_card

pytestmark = pytest.mark.skipif(not variants.mitsuba_installed(),
                                reason="Mitsuba 3 is not installed (pip install mitsuba==3.9.1)")

U32 = 2.0 ** -24  # float32 unit roundoff
SMALL = GeneratorSettings(width=48, height=40)
# Mitsuba side of the tracer comparison: K renders of SPP samples (n = 1024 per pixel);
# the tracer: two scrambled-Sobol runs of TRACE_N (16384 per pixel together).
K, SPP, TRACE_N = 4, 256, 8192


@pytest.fixture(scope="module")
def variant():
    try:
        return ms.choose_variant()
    except ms.MitsubaUnavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def fast_variant(variant):
    """The comparisons below render millions of samples: too slow for scalar_rgb."""
    if variant.name == "scalar_rgb":
        pytest.skip("only scalar_rgb runs here; the comparison tests need a JIT variant")
    return variant


def _mitsuba(scene, k=K, spp=SPP, fault=None, seed0=100):
    """Mean of k renders, pooled per-sample variance, samples per pixel, the renders."""
    imgs, vars_ = [], []
    for i in range(k):
        img, var, _ = ms.render_with_variance(scene, spp, seed=seed0 + i, fault=fault)
        imgs.append(img.astype(np.float64))
        vars_.append(var)
    return np.mean(imgs, 0), np.mean(vars_, 0), k * spp, imgs


_TRACER_CACHE: dict = {}


def _tracer(family):
    """The tracer reference for a generated family: two Sobol seeds, their mean."""
    if family not in _TRACER_CACHE:
        scene = generate(0, family, settings=SMALL)
        runs = [trace.trace(scene, samples.stratified(TRACE_N, seed=s), notices=False)[0]
                for s in (1, 2)]
        _TRACER_CACHE[family] = (scene, runs)
    return _TRACER_CACHE[family]


# --------------------------------------------------------------------------------------
# Geometry (numpy only)


def test_card_quads_project_onto_their_texture_extent():
    """Back-projected corners project (pinhole) back onto the extent, for a tilted card;
    float64 round trip, so 1e-9 px."""
    cam = Camera(48, 40, blur_parameter=12.0, focus_disparity=0.45)
    card = opaque_card("t", 30, 36, [1, 1, 1], Plane.from_gradient(0.6, 0.012, -0.004), (5, 4))
    v, uv = geometry.quad(card, cam)
    f = cam.focal_length_px
    x0, x1, y0, y1 = card.extent(cam)
    np.testing.assert_allclose(f * v[:, 0] / v[:, 2], [x0, x1, x1, x0], atol=1e-9)
    np.testing.assert_allclose(f * v[:, 1] / v[:, 2], [y0, y0, y1, y1], atol=1e-9)
    # depth is the plane's: Z = 1 / d(x, y)
    np.testing.assert_allclose(v[:, 2], 1.0 / card.plane.disparity(
        np.array([x0, x1, x1, x0]), np.array([y0, y0, y1, y1])), rtol=1e-12)
    # the triangles face the camera (normal towards -Z)
    for a, b, c in geometry.QUAD_FACES:
        assert np.cross(v[b] - v[a], v[c] - v[a])[2] < 0
    verts, tuv, faces = geometry.texel_grid(card, cam)
    assert faces.shape == (2 * 30 * 36, 3) and verts.shape == (31 * 37, 3)
    np.testing.assert_allclose(f * verts[:, 0] / verts[:, 2], x0 + tuv[:, 0] * 36, atol=1e-9)
    np.testing.assert_allclose(f * verts[:, 1] / verts[:, 2], y0 + tuv[:, 1] * 30, atol=1e-9)
    for a, b, c in faces[[0, -1]]:
        assert np.cross(verts[b] - verts[a], verts[c] - verts[a])[2] < 0


def test_poisson_tail():
    """Against the Poisson cdf: for mu = 1, P(X > 8) = 1.1e-6 and P(X > 9) = 1.0e-7, so
    9; for mu = 0, 0."""
    assert poisson_isf(1e-6, 1.0) == 9 and poisson_isf(1e-6, 0.0) == 0
    assert poisson_isf(0.5, 10.0) == 10  # the median of Poisson(10)


def test_value_bound_covers_every_card_in_reach():
    cam = Camera(20, 16, blur_parameter=10.0, focus_disparity=0.5)
    rgba = np.zeros((4, 4, 4), np.float32)
    rgba[1, 2] = [7.0, 2.0, 0.5, 0.25]  # straight colour 7 at frame pixel (6 + 1, 5 + 2)
    scene = Scene(cam, [Card("c", rgba, Plane.fronto(0.8), (5, 6))])
    bound = ms.value_bound(scene)
    reach = 3 + 2  # A |d - d_f| = 3 px displacement, + pixel and texel
    assert bound[7, 7].tolist() == [7.0, 2.0, 0.5, 1.0]
    assert bound[7, 7 + reach, 0] == 7.0 and bound[7, 7 + reach + 1, 0] == 0.0


# --------------------------------------------------------------------------------------
# Variant and basic behaviour


def test_variant_is_chosen_by_probing_and_reported(variant):
    """The preference order cuda > llvm > scalar, each one probed in a subprocess."""
    if os.environ.get("MPIB_NO_CUDA") != "1" and _backend.probe_cuda().name == "cuda":
        expected = "cuda_ad_rgb"
    elif _backend.probe_llvm().name == "llvm":
        expected = "llvm_ad_rgb"
    else:
        expected = "scalar_rgb"
    assert variant.name == expected, variant.reason
    assert variant.reason.startswith(expected)
    scene = Scene(Camera(8, 6, 2.0, 0.5), [opaque_card("c", 6, 8, [1, 2, 3], Plane.fronto(0.5),
                                                       (0, 0))])
    img, meta = ms.render(scene, 4)
    assert img.shape == (6, 8, 4) and img.dtype == np.float32
    assert meta["variant"] == variant.name and meta["variant_reason"] == variant.reason
    assert meta["engine"] == "mitsuba" and meta["spp"] == 4 and meta["seconds"] > 0
    with pytest.raises(ValueError, match="variant"):
        ms.choose_variant("opencl_rgb")


def test_integrator_is_a_registered_plugin(variant):
    mi, _ = variants.set_variant(variant.name)
    build.compositor_class(mi)
    integ = mi.load_dict({"type": build.INTEGRATOR_NAME})
    assert isinstance(integ, mi.SamplingIntegrator)
    assert list(integ.aov_names()) == list(build.AOV_NAMES)


def test_bad_arguments_are_refused(variant):
    scene = Scene(Camera(8, 6, 2.0, 0.5), [opaque_card("c", 6, 8, [1, 1, 1], Plane.fronto(0.5),
                                                       (0, 0))])
    with pytest.raises(ValueError, match="square"):
        ms.render(scene, 10, sampler="stratified")  # Mitsuba would silently use 9 or 16
    with pytest.raises(ValueError, match="fault"):
        ms.render_with_variance(scene, 4, fault="gamma")
    with pytest.raises(ValueError, match="spp"):
        ms.render(scene, 0)


def test_same_seed_same_image(fast_variant, three_card_scene):
    """Same seed, same samples; a film pixel sums spp float32 values, so any difference
    in summation order is bounded by spp * u relative (exactly equal on LLVM here)."""
    a, _ = ms.render(three_card_scene, 64, seed=5)
    b, _ = ms.render(three_card_scene, 64, seed=5)
    c, _ = ms.render(three_card_scene, 64, seed=6)
    np.testing.assert_allclose(a, b, rtol=64 * U32, atol=0)
    assert not np.array_equal(a, c)


def test_card_in_focus_is_reproduced(variant):
    """At d = d_f every sample of a pixel hits that pixel's texel, so the image is the
    premultiplied texture, up to the float32 rounding of the hit's projection.

    That rounding is a few ulps of the pixel coordinate, at most delta = 8 W u pixels
    (W = 40: 1.9e-5 px; 1.5e-5 measured). A sample within delta of a pixel edge can land
    in the neighbouring texel: at most 4 delta per sample, so the number of affected
    pixels is at most Poisson with mean N_samples 4 delta, and the allowed count is its
    1e-6 tail. An affected pixel differs by at most 2 samples' worth (two edges) of the
    largest texel contrast, 2 * max / spp.
    """
    rng = np.random.default_rng(0)
    cam = Camera(40, 30, blur_parameter=25.0, focus_disparity=0.4)
    rgba = rng.random((30, 40, 4)).astype(np.float32)
    rgba[..., :3] *= 8.0  # HDR
    spp = 16 if variant.name == "scalar_rgb" else 64
    scene = Scene(cam, [Card("sharp", rgba, Plane.fronto(0.4), (0, 0))])
    img, _ = ms.render(scene, spp, seed=1)
    expected = np.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], axis=-1)
    diff = np.abs(img - expected)
    delta = 8 * cam.width * U32
    allowed = poisson_isf(1e-6, 40 * 30 * spp * 4 * delta)
    # where all samples agree: the film's float32 average of spp equal values (spp u
    # relative) and the coverage 1 - (1 - a) (one rounding of 1 - a: u absolute)
    exact = (diff <= spp * U32 * np.abs(expected) + U32).all(axis=-1)
    assert (~exact).sum() <= allowed, ((~exact).sum(), allowed)
    assert diff.max() <= 2 * 8.0 / spp


# --------------------------------------------------------------------------------------
# The camera model, as a sceptic would check it


def _square(k, size, disparity, radiance, offset):
    rgba = np.zeros((size, size, 4), np.float32)
    c = size // 2 - k // 2
    rgba[c:c + k, c:c + k] = [radiance, radiance, radiance, 1.0]
    return Card("dot", rgba, Plane.fronto(disparity), offset)


@pytest.mark.parametrize("focus, disparity", [(0.5, 0.5 + 12.3 / 20), (0.5, 0.5 - 4.0 / 20),
                                              (0.0, 0.6)])
def test_square_blurs_into_disk_of_radius_A_delta_d(fast_variant, focus, disparity):
    """A k x k emissive square at disparity d spreads into a disk of radius
    r = A |d - d_f| (also with focus at infinity, d_f = 0), centred on its pinhole
    projection, conserving its energy.

    Second moment about the centroid: the disk gives r^2/2; the square's own extent
    k^2/12 per axis; the rounding of each sample to its pixel centre 1/12 per axis (the
    blurred positions' fractional parts are uniform for r >> 1). So
    E[rho^2] = r^2/2 + (k^2 + 1)/6 and r = sqrt(2 (E[rho^2] - (k^2 + 1)/6)).

    Noise: the per-pixel variances give the standard errors of the moments by the delta
    method (pixels are independent); the spp is chosen so that 4 sigma_r is below the
    0.5 % tolerance (asserted, so the tolerance is never noise).
    """
    k, spp, L = 6, 16384, 5.0
    cam = Camera(40, 40, blur_parameter=20.0, focus_disparity=focus)
    # texels 14..19 of a 34-texel card at offset 3: frame pixels 17..22, centre 20.0
    scene = Scene(cam, [_square(k, 34, disparity, L, (3, 3))])
    img, var, _ = ms.render_with_variance(scene, spp, seed=0)
    lum = img[..., 0].astype(np.float64)
    v = var[..., 0] / spp  # variance of each pixel value
    ys, xs = np.mgrid[0:40, 0:40] + 0.5
    total = lum.sum()
    cx, cy = (lum * xs).sum() / total, (lum * ys).sum() / total
    rho2 = (xs - cx) ** 2 + (ys - cy) ** 2
    m2 = (lum * rho2).sum() / total
    r_true = cam.blur_radius(disparity)
    r_est = math.sqrt(2.0 * (m2 - (k * k + 1) / 6.0))
    sigma_r = math.sqrt((v * (rho2 - m2) ** 2).sum()) / total / r_est  # dr = dm2 / r
    sigma_c = math.sqrt((v * (xs - cx) ** 2).sum()) / total
    sigma_total = math.sqrt(v.sum())
    assert 4 * sigma_r <= 0.005 * r_true, "not enough samples for a 0.5 % radius test"
    assert abs(r_est - r_true) <= 0.005 * r_true, (r_est, r_true, sigma_r)
    # the pinhole projection of the square's centre, (20, 20); 4 sigma_c ~ 0.04 px,
    # so a half-pixel error would fail by > 40 sigma
    assert abs(cx - 20.0) <= 4 * sigma_c and abs(cy - 20.0) <= 4 * sigma_c, (cx, cy, sigma_c)
    assert abs(total - k * k * L) <= 4 * sigma_total, (total, sigma_total)
    # nothing lands beyond the disk grown by the square's half-diagonal and one pixel
    far = np.hypot(xs - 20.0, ys - 20.0) > r_true + k / math.sqrt(2) + math.sqrt(2)
    assert lum[far].max() == 0.0


# --------------------------------------------------------------------------------------
# Agreement with the ray tracer, and the faults it must catch


@pytest.mark.parametrize("family", FAMILIES)
def test_mitsuba_agrees_with_the_ray_tracer(fast_variant, family):
    scene, (t1, t2) = _tracer(family)
    ref = 0.5 * (t1.astype(np.float64) + t2)
    mean, var, n, imgs = _mitsuba(scene)
    bound = ms.value_bound(scene)
    # The tracer's error enters as var / (2 TRACE_N): the Monte Carlo error of as many
    # independent samples. Check that assumption: the difference of its two Sobol runs
    # must be no larger than that of two independent runs of TRACE_N samples
    # (measured: 1-6 % of it).
    assert ((t1.astype(np.float64) - t2) ** 2 / 2).sum() <= (var / TRACE_N).sum()
    # Mitsuba's variance estimate (film means of v and v^2) against two seeds: the
    # squared difference of two renders has expectation 2 var / spp per pixel; its sum
    # over pixels has relative standard deviation sqrt(2 / N_eff), N_eff = (sum w)^2 /
    # sum w^2 with w = var / spp (Gaussian pixels; heavy tails make it noisier, hence 4
    # sigma)
    w = var / SPP
    n_eff = w.sum() ** 2 / (w ** 2).sum()
    ratio = ((imgs[0] - imgs[1]) ** 2 / 2).sum() / w.sum()
    assert abs(ratio - 1.0) <= 4 * math.sqrt(2.0 / n_eff), (ratio, n_eff)
    # two Mitsuba seeds agree with each other by the same statistic
    other = ms.render_with_variance(scene, n, seed=7)
    assert ms.agreement(other[0], other[1], n, mean, var, n, bound).passed
    ag = ms.agreement(mean, var, n, ref, var, 2 * TRACE_N, bound)
    assert ag.passed, ag.summary()


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("fault", build.FAULTS)
def test_agreement_rejects_injected_faults(fast_variant, family, fault):
    """A half-pixel shift, a mirrored y axis, a 1.5x aperture, straight colour used as
    premultiplied: each one must fail the same statistic the correct renderer passes."""
    scene, (t1, t2) = _tracer(family)
    ref = 0.5 * (t1.astype(np.float64) + t2)
    mean, var, n, _ = _mitsuba(scene, fault=fault)
    ag = ms.agreement(mean, var, n, ref, var, 2 * TRACE_N, ms.value_bound(scene))
    assert not ag.passed, ag.summary()
    # not by a hair: at least 10x the allowed outliers (measured: 21-98 % of the pixels,
    # 50-240x the allowed count)
    assert ag.outlier_pixels >= 10 * ag.allowed_outliers, ag.summary()


# --------------------------------------------------------------------------------------
# The stock path tracer (mask BSDF) through the XML files, and the mitsuba command


def test_xml_files_with_stock_path_tracer_agree_with_compositor(fast_variant, three_card_scene,
                                                               tmp_path):
    """The to_xml files (a tilted card as a per-texel mesh, semi-transparent rows, HDR),
    rendered by the stock path integrator, against the compositing integrator."""
    path = ms.to_xml(three_card_scene, tmp_path)
    root = ET.parse(path).getroot()
    assert [s.get("id") for s in root.iter("shape")] == ["card_bg", "card_tilt", "card_fg",
                                                         "backstop"]
    assert (tmp_path / "coverage.xml").exists()
    for card in three_card_scene.cards:
        for suffix in (".ply", "_rgb.exr", "_alpha.exr"):
            assert (tmp_path / "cards" / f"{card.name}{suffix}").exists()
    stock, stock_var, meta = ms.render_stock_with_variance(three_card_scene, 256, seed=3)
    assert meta["integrator"].startswith("path")
    comp, comp_var, _ = ms.render_with_variance(three_card_scene, 2048, seed=4)
    ag = ms.agreement(stock, stock_var, 256, comp, comp_var, 2048,
                      ms.value_bound(three_card_scene))
    assert ag.passed, ag.summary()


def test_mitsuba_command_renders_the_xml(fast_variant, three_card_scene, tmp_path):
    """The ``mitsuba`` executable renders scene.xml (LLVM library from the probe, in the
    environment) and gives the image that mi.render gives with the same seed (0), up
    to the float32 summation order of spp samples (spp * u relative)."""
    mitsuba_cmd = os.path.join(os.path.dirname(sys.executable), "mitsuba")
    if not os.path.exists(mitsuba_cmd):
        pytest.skip("no mitsuba executable beside the interpreter")
    from mpib_validate.runtime.io.exr import read_exr

    path = ms.to_xml(three_card_scene, tmp_path, spp=16)
    out = tmp_path / "out.exr"
    r = subprocess.run([mitsuba_cmd, "-m", fast_variant.name, "-D", "spp=16", "-o", str(out),
                        str(path)], capture_output=True, text=True, env=dict(os.environ),
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    exr = read_exr(out)
    cli = np.stack([exr.channels[c] for c in "RGB"], axis=-1)
    mi, _ = variants.set_variant(fast_variant.name)
    py = np.array(mi.render(mi.load_file(str(path), spp=16), spp=16, seed=0))
    np.testing.assert_allclose(cli, py, rtol=16 * U32, atol=0)


def test_render_result_feeds_the_cli_writer(fast_variant, three_card_scene, tmp_path):
    """render_result gives a TraceResult that mpib_validate.cards.render_io writes unchanged
    (the planned ``mpib render --engine mitsuba``); its all-in-focus pass is exact."""
    from mpib_validate.runtime.io.exr import read_exr
    from mpib_validate.cards.render_io import write_render

    res = ms.render_result(three_card_scene, 16, seed=2)
    img, _ = ms.render(three_card_scene, 16, seed=2)
    np.testing.assert_array_equal(res.bokeh, img)
    aif, _ = trace.trace(three_card_scene, samples.pinhole(4), notices=False)
    np.testing.assert_array_equal(res.all_in_focus, aif)
    written = write_render(tmp_path / "m.exr", res, three_card_scene, preview=False)
    assert written == [tmp_path / "m.exr"]
    assert '"engine": "mitsuba"' in read_exr(written[0]).header["mpib"]


# --------------------------------------------------------------------------------------
# Other variants, noise and time


def test_scalar_variant_agrees_with_jit(fast_variant):
    """The scalar fallback runs the same integrator per sample in Python (slow): a tiny
    scene, judged by the same statistic against the JIT variant."""
    scene = generate(0, "varying", settings=GeneratorSettings(width=16, height=12))
    a, va, meta = ms.render_with_variance(scene, 64, seed=0, variant="scalar_rgb")
    assert meta["variant"] == "scalar_rgb"
    b, vb, _ = ms.render_with_variance(scene, 1024, seed=0, variant=fast_variant.name)
    ag = ms.agreement(a, va, 64, b, vb, 1024, ms.value_bound(scene))
    assert ag.passed, ag.summary()


def test_noise_vs_spp_matches_the_variance_estimate(fast_variant, three_card_scene):
    """RMSE from two seeds against the prediction sqrt(mean(var) / spp) from the film's
    moments, at each spp; tolerance 4 sqrt(1 / (2 N_eff)) on the RMSE (half the
    relative standard deviation of a mean of squares, sqrt(2 / N_eff))."""
    spps = [16, 64]
    rows = ms.noise_vs_spp(three_card_scene, spps)
    _, var, _ = ms.render_with_variance(three_card_scene, 1024, seed=9)
    w = var[..., :3]
    n_eff = w.sum() ** 2 / (w ** 2).sum()
    for row, spp in zip(rows, spps):
        assert row["spp"] == spp and row["seconds"] > 0 and row["variant"] == fast_variant.name
        predicted = math.sqrt(w.mean() / spp)
        assert abs(row["rmse"] / predicted - 1.0) <= 4 * math.sqrt(1.0 / (2.0 * n_eff)), (
            row, predicted, n_eff)


# --------------------------------------------------------------------------------------
# Longer runs


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_agreement_at_128px(fast_variant, family):
    """The tracer comparison on larger generated scenes (several seeds)."""
    settings = GeneratorSettings(width=128, height=96)
    for seed in (1, 2):
        scene = generate(seed, family, settings=settings)
        runs = [trace.trace(scene, samples.stratified(4096, seed=s), notices=False)[0]
                for s in (1, 2)]
        ref = 0.5 * (runs[0].astype(np.float64) + runs[1])
        mean, var, n, _ = _mitsuba(scene, k=4, spp=256)
        ag = ms.agreement(mean, var, n, ref, var, 8192, ms.value_bound(scene))
        assert ag.passed, (seed, ag.summary())


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_agreement_on_the_hard_cases(fast_variant, family):
    """Thin and hair-like masks, soft edges, HDR bokeh, near focus, a grazing plane, a
    large blur, focus on the fore- or background: 64x48, one seed each."""
    failures = []
    for case in HARD_CASES:
        scene = generate(0, family, case=case, settings=GeneratorSettings(width=64, height=48))
        runs = [trace.trace(scene, samples.stratified(TRACE_N, seed=s), notices=False)[0]
                for s in (1, 2)]
        ref = 0.5 * (runs[0].astype(np.float64) + runs[1])
        mean, var, n, _ = _mitsuba(scene)
        ag = ms.agreement(mean, var, n, ref, var, 2 * TRACE_N, ms.value_bound(scene))
        if not ag.passed:
            failures.append(f"{case}: {ag.summary()}")
    assert not failures, failures


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_stock_path_tracer_on_generated_scenes(fast_variant, family):
    scene = generate(3, family, settings=SMALL)
    stock, stock_var, _ = ms.render_stock_with_variance(scene, 1024, seed=1)
    comp, comp_var, _ = ms.render_with_variance(scene, 4096, seed=2)
    ag = ms.agreement(stock, stock_var, 1024, comp, comp_var, 4096, ms.value_bound(scene))
    assert ag.passed, ag.summary()
