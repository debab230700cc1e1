"""The MPI compositor (Eq. 1), its fast paths, the exact and middle renderers.

Tolerances are derived in the comments: float32 rounding, the FFT noise floor
(kernels.FFT_FLOOR), or a measured level stated with the measurement.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from mpib_validate.runtime.compositor import composite as C
from mpib_validate.runtime.compositor import kernels as K
from mpib_validate.runtime.layers import mpi as M
from mpib_validate.cards import mpi as CM
from mpib_validate.runtime import samples
from mpib_validate.cards import trace
from mpib_validate.runtime.camera import Camera
from mpib_validate.runtime.compositor.composite import PLAIN, CompositeSettings
from mpib_validate.cards.generate import GeneratorSettings, generate
from mpib_validate.metrics import psnr
from mpib_validate.cards.scene import Scene

from conftest import dot_card

FAST = CompositeSettings()  # auto direct/FFT + crop
SETTINGS = {
    "plain": PLAIN,
    "fft": CompositeSettings(conv="fft", crop=False, reduce_above=None),
    "crop": CompositeSettings(conv="direct", crop=True, reduce_above=None),
    "reduced": CompositeSettings(conv="fft", crop=False, reduce_above=4.0),
    "fast": FAST,
    "fast-reduced": CompositeSettings(reduce_above=8.0),
}
F32 = np.finfo(np.float32).eps


def _random_mpi(rng, n, h, w, d, alpha_max=1.0):
    rgba = np.zeros((n, h, w, 4), np.float32)
    a = rng.random((n, h, w)).astype(np.float32) * alpha_max
    rgba[..., 3] = a
    rgba[..., :3] = rng.random((n, h, w, 3)).astype(np.float32) * a[..., None]
    return M.MPI.from_dense(d, rgba)


# -- kernels --------------------------------------------------------------------------


@pytest.mark.parametrize("rho", [0.0, 0.4, 1.0, 2.5, 7.3, -3.5])
def test_canonical_kernel_is_the_tracers_point_response(rho):
    """The kernel equals the ray tracer's image of a single texel, which is what the
    canonical pixel model defines. The tracer's 4096-point Sobol estimate of each tap has
    standard error below sqrt(K (1 - K) / 4096) <= 0.008; we allow 0.01 absolute."""
    cam = Camera(41, 41, blur_parameter=10.0, focus_disparity=0.5)
    d = 0.5 + rho / 10.0
    scene = Scene(cam, [dot_card("dot", 41, d)])
    img, _ = trace.trace(scene, samples.stratified(4096, seed=5), backend="numpy")
    k = K.disk_kernel(rho)
    R = K.kernel_radius(k)
    # dot at frame pixel (20, 20); out(p) = sum_q K[q] L(p + q): the response at p is K[-(p - 20)]
    got = img[20 - R:21 + R, 20 - R:21 + R, 0][::-1, ::-1]
    assert np.abs(got - k).max() < 0.01
    assert img[..., 0].sum() == pytest.approx(1.0, rel=1e-5)
    assert k.sum() == pytest.approx(1.0, abs=1e-12)


def test_kernel_is_no_larger_than_the_blur():
    for r in (0.0, 0.3, 1.0, 4.2, 30.0):
        assert K.kernel_radius(K.disk_kernel(r)) == int(np.ceil(r - 1e-9))


# -- identities ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SETTINGS))
def test_in_focus_mpi_returns_the_image(name):
    """All layers at d_f: every kernel is the identity, so Eq. 1 is the plain "over"
    composite, normalised by its alpha. float32: a few ulps of the largest value."""
    rng = np.random.default_rng(0)
    mpi = _random_mpi(rng, 4, 23, 31, [0.4] * 4)
    out = C.composite(mpi, 30.0, 0.4, SETTINGS[name])
    dense = mpi.dense()
    acc = np.zeros((23, 31, 4), np.float64)
    for layer in dense:
        acc = acc * (1 - layer[..., 3:4]) + layer
    expect = acc[..., :3] / acc[..., 3:4]
    np.testing.assert_allclose(out[..., :3], expect, rtol=0, atol=8 * F32)
    np.testing.assert_allclose(out[..., 3], acc[..., 3], rtol=0, atol=8 * F32)


@pytest.mark.parametrize("name", ["plain", "fft", "crop", "fast"])
def test_single_opaque_layer_is_a_plain_disk_blur(name):
    """One opaque layer: Eq. 1 reduces to correlating the colour with the disk kernel,
    with replication past the image border. The FFT leaves float32 rounding noise of
    ~1e-6 of the peak; 1e-5 absolute covers it (colours are in [0, 1])."""
    rng = np.random.default_rng(1)
    h, w = 37, 45
    rgba = np.ones((1, h, w, 4), np.float32)
    rgba[0, ..., :3] = rng.random((h, w, 3))
    mpi = M.MPI.from_dense([0.2], rgba)
    A, df = 20.0, 0.5  # radius 6 px
    out = C.composite(mpi, A, df, SETTINGS[name])
    k = K.disk_kernel(A * (0.2 - df))
    expect = np.stack([ndimage.correlate(rgba[0, ..., c].astype(np.float64), k, mode="nearest")
                       for c in range(3)], axis=-1)
    np.testing.assert_allclose(out[..., :3], expect, atol=1e-5)
    np.testing.assert_allclose(out[..., 3], 1.0, atol=1e-6)


@pytest.mark.parametrize("name", list(SETTINGS))
def test_energy_is_conserved(name):
    """A bright dot layer over an opaque black layer: the normaliser is exactly 1, so
    the image total is the dot's energy (the kernel sums to one). For the reduced path
    the bilinear up-sampling of a box-averaged grid also preserves the total away from
    borders. float32 sums: 1e-5 relative."""
    h = w = 64
    rgba = np.zeros((2, h, w, 4), np.float32)
    rgba[0, ..., 3] = 1.0
    rgba[1, 30, 33] = [7.0, 7.0, 7.0, 1.0]
    mpi = M.MPI.from_dense([0.1, 0.9], rgba)
    out = C.composite(mpi, 25.0, 0.4, SETTINGS[name])  # dot radius 12.5 px
    assert out[..., 0].sum(dtype=np.float64) == pytest.approx(7.0, rel=1e-5)


# -- the exact renderer and the middle setting ----------------------------------------------


def test_exact_renderer_equals_the_tracer_on_constant_scenes():
    """Fronto-parallel cards become layers at their own disparity, and the exact
    renderer traces those layers with the same samples: bit-identical to the tracer."""
    scene = generate(0, "constant", settings=GeneratorSettings(width=64, height=48))
    smp = samples.stratified(128, seed=4)
    ref, _ = trace.trace(scene, smp, backend="numpy")
    mpi = CM.layers_from_cards(scene)
    ex = CM.render_exact(mpi, scene.camera, smp, backend="numpy")
    np.testing.assert_array_equal(ex[..., :3] * ex[..., 3:], ref[..., :3] * ref[..., 3:])


def test_eq1_gap_shrinks_with_subapertures():
    """Eq. 1 is not exact; the sub-aperture renderer approaches the exact one as k grows.
    Measured on this scene (128x128, seed 0): Eq. 1 46.0 dB, k=2 54.6 dB, k=3 59.2 dB,
    k=4 61.1 dB against the exact renderer (1,024 samples), whose own noise floor, from
    two sample sets, is 59.7 dB (a deterministic image compared with one noisy render can
    sit up to 3 dB above it). Each step must gain 3 dB until it reaches that floor."""
    scene = generate(0, "constant", settings=GeneratorSettings(width=128, height=128))
    cam = scene.camera
    mpi = CM.layers_from_cards(scene)
    ex = np.clip(CM.render_exact(mpi, cam, samples.stratified(1024, seed=0)), 0, 1)
    ex2 = np.clip(CM.render_exact(mpi, cam, samples.stratified(1024, seed=1)), 0, 1)
    noise_floor = psnr(ex, ex2)
    gaps = [psnr(ex, np.clip(C.render_subapertures(mpi, cam.blur_parameter,
                                                   cam.focus_disparity, k), 0, 1))
            for k in (1, 2, 3)]
    assert gaps[0] + 3 < gaps[1], (gaps, noise_floor)
    assert gaps[2] > min(gaps[1] + 3, noise_floor - 1), (gaps, noise_floor)


# -- fast paths against the plain path -----------------------------------------------------


@pytest.mark.parametrize("family", ["constant", "varying"])
def test_fast_paths_agree_with_the_plain_path(family):
    """FFT and crop change only rounding: the float32 FFT's noise is below 3e-8 of the
    peak (measured, kernels.FFT_DTYPE) and the result is stored in float32 (eps 6e-8
    relative); 120 dB allows an RMS error of 1e-6 of the peak, 30x that noise."""
    scene = generate(1, family, case="large-blur", settings=GeneratorSettings(width=96, height=96))
    cam = scene.camera
    mpi = CM.layers_from_cards(scene)
    plain = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, PLAIN)
    for name in ("fft", "crop", "fast"):
        out = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, SETTINGS[name])
        assert psnr(plain, out, peak=float(plain.max())) > 120.0, name


def test_reduced_resolution_error_is_bounded_on_ldr_content():
    """Blurring a layer of radius r at 1/s resolution smears the disk's edge over ~s px.
    On LDR content (values <= 1, no highlights) the measured error at reduce_above=8
    (s = 3 here) is 55.6 dB (seed 1) and 129 dB (seed 2, whose layers barely exceed
    8 px) against the plain path; we require 50 dB.
    HDR highlights make the smeared edge visible (measured 29 dB with 200x highlights at
    s = 2), which is why the path is off by default."""
    for seed in (1, 2):
        scene = generate(seed, "constant", case="large-blur",
                         settings=GeneratorSettings(width=96, height=96, hdr_probability=0.0))
        cam = scene.camera
        mpi = CM.layers_from_cards(scene)
        plain = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, SETTINGS["fft"])
        out = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, SETTINGS["fast-reduced"])
        assert psnr(np.clip(plain, 0, 1), np.clip(out, 0, 1)) > 50.0


# -- numerical hard cases -------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SETTINGS))
def test_all_zero_alpha_gives_zeros_not_nan(name):
    mpi = M.MPI(20, 30, 0, [M.Layer(0.5, np.zeros((20, 30, 4), np.float32), 0, 0)])
    out = C.composite(mpi, 10.0, 0.1, SETTINGS[name])
    assert np.isfinite(out).all() and (out == 0).all()
    empty = M.MPI.from_dense([0.5], np.zeros((1, 20, 30, 4), np.float32))
    assert empty.layers == []  # empty planes are not stored
    assert (C.composite(empty, 10.0, 0.1, SETTINGS[name]) == 0).all()


@pytest.mark.parametrize("name", list(SETTINGS))
def test_tiny_alpha_keeps_its_colour(name):
    """alpha = 1e-6 everywhere: Eq. 1 normalises it away, so the colour comes back.
    The FFT's rounding is relative to each layer's own peak, so 1e-6 relative holds."""
    rgba = np.zeros((2, 25, 25, 4), np.float32)
    rgba[..., 3] = 1e-6
    rgba[0, ..., :3] = np.float32(0.3e-6)
    rgba[1, ..., :3] = np.float32(0.3e-6)
    out = C.composite(M.MPI.from_dense([0.2, 0.7], rgba), 10.0, 0.4, SETTINGS[name])
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[..., :3], 0.3, rtol=1e-4)


@pytest.mark.parametrize("name", list(SETTINGS))
def test_radius_zero_and_radius_larger_than_the_image(name):
    rng = np.random.default_rng(3)
    mpi = _random_mpi(rng, 2, 9, 13, [0.3, 0.5])
    for A, df in ((1e-9, 0.5), (400.0, 0.0)):  # radius ~0, and 200 px on a 13 px image
        out = C.composite(mpi, A, df, SETTINGS[name])
        assert np.isfinite(out).all() and out.min() >= 0


def test_hdr_next_to_zero_has_no_ringing_or_negatives():
    """A 1e4 highlight next to 0: the FFT path may not ring into negative values or
    leave noise above its floor outside the blur's reach."""
    rgba = np.zeros((2, 64, 64, 4), np.float32)
    rgba[0, ..., 3] = 1.0  # black opaque background
    rgba[1, 30:34, 30:34] = [1e4, 1e4, 1e4, 1.0]
    mpi = M.MPI.from_dense([0.1, 0.6], rgba)
    for name in ("fft", "fast", "plain"):
        out = C.composite(mpi, 20.0, 0.2, SETTINGS[name])  # radius 8 px
        assert out.min() >= 0
        ys, xs = np.mgrid[0:64, 0:64]
        far = np.hypot(ys - 31.5, xs - 31.5) > 8 + 2 + 3  # beyond kernel + dot size
        if name != "fast":
            assert out[far, :3].max() == 0.0, name
        plain = C.composite(mpi, 20.0, 0.2, PLAIN)
        assert np.abs(out - plain).max() < 1e4 * 1e-5


def test_float16_input():
    rng = np.random.default_rng(4)
    mpi = _random_mpi(rng, 3, 16, 16, [0.1, 0.5, 0.9])
    half = M.MPI(16, 16, 0, [M.Layer(l.disparity, l.rgba.astype(np.float16), l.y0, l.x0)
                             for l in mpi.layers])
    a = C.composite(mpi, 10.0, 0.5)
    b = C.composite(half, 10.0, 0.5)
    assert b.dtype == np.float32
    # float16 input rounding: relative 2^-11 of each value
    np.testing.assert_allclose(a, b, atol=2 * 2.0 ** -11)


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (7, 1), (5, 9)])
def test_tiny_and_odd_images(shape):
    rng = np.random.default_rng(5)
    mpi = _random_mpi(rng, 3, *shape, [0.1, 0.5, 0.9])
    for name, st in SETTINGS.items():
        out = C.composite(mpi, 15.0, 0.3, st)
        assert out.shape == shape + (4,) and np.isfinite(out).all(), name


def test_256_planes():
    rng = np.random.default_rng(6)
    d = M.uniform_planes(256)
    mpi = _random_mpi(rng, 256, 24, 24, d, alpha_max=0.05)
    a = C.composite(mpi, 20.0, 0.5, PLAIN)
    b = C.composite(mpi, 20.0, 0.5, FAST)
    assert np.isfinite(b).all()
    assert psnr(a, b) > 80


def test_zero_aperture_is_refused():
    mpi = _random_mpi(np.random.default_rng(7), 1, 4, 4, [0.5])
    with pytest.raises(ValueError, match="blur parameter"):
        C.composite(mpi, 0.0, 0.5)


# -- plane placement ------------------------------------------------------------------------


def test_adaptive_planes_model_only_what_is_there():
    """Planes only inside content intervals, spaced so the radius error is <= tol."""
    A, tol = 40.0, 0.25
    planes = M.adaptive_planes([(0.1, 0.1), (0.5, 0.62), (0.55, 0.7)], A, tol)
    assert 0.1 in planes and planes.min() == 0.1 and planes.max() == pytest.approx(0.7)
    assert not ((planes > 0.1) & (planes < 0.5)).any()  # nothing in the empty gap
    gaps = np.diff(planes[planes >= 0.5])
    assert (A * gaps <= 2 * tol + 1e-12).all()
    assert len(M.adaptive_planes([(0.3, 0.3)], A, tol)) == 1
    np.testing.assert_allclose(M.uniform_planes(32)[:2], [1 / 64, 3 / 64])


def test_split_between_planes_keeps_coverage_and_eq16():
    rng = np.random.default_rng(8)
    planes = np.array([0.1, 0.3, 0.35, 0.8])
    d = rng.uniform(0.1, 0.8, 1000)
    a = rng.uniform(0, 1, 1000)
    a[:100] = 1.0
    idx, a_lo, a_hi = M.split_between_planes(d, a, planes)
    np.testing.assert_allclose(a_hi + (1 - a_hi) * a_lo, a, atol=1e-12)
    recon = planes[idx + 1] * a_hi + planes[idx] * (1 - a_hi) * a_lo
    np.testing.assert_allclose(recon, d * a, atol=1e-12)


@pytest.mark.parametrize("device", [b for b in ("llvm", "cuda") if b in __import__("conftest").jit_backends()])
def test_drjit_blur_agrees_with_numpy(device):
    """The Dr.Jit path writes each kernel row as boxes over float64 row prefix sums;
    box levels are merged within 1e-7 of the kernel's peak, so the result differs from
    the direct/FFT path by at most ~1e-7 of the largest value (plus float32 rounding):
    we allow 1e-6 of the peak."""
    scene = generate(2, "varying", settings=GeneratorSettings(width=64, height=48))
    cam = scene.camera
    mpi = CM.layers_from_cards(scene)
    a = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, FAST)
    b = C.composite(mpi, cam.blur_parameter, cam.focus_disparity,
                    CompositeSettings(backend=device))
    assert np.abs(a - b).max() <= 1e-6 * float(a.max())


@pytest.mark.parametrize("device", [b for b in ("llvm", "cuda") if b in __import__("conftest").jit_backends()])
@pytest.mark.parametrize("blades, rotation_deg, ratio", [(6, 15.0, 1.5), (5, 10.0, 1.0)])
def test_drjit_blur_agrees_with_numpy_for_a_shaped_aperture(device, blades, rotation_deg,
                                                            ratio):
    """The same with the lens's shape (:class:`Aperture`: a rotated anamorphic hexagon,
    and an odd-bladed one, which turns over with the sign of the defocus): the shaped
    kernels go through the same row boxes, so the same bound holds."""
    import math
    from dataclasses import replace

    from mpib_validate.runtime.camera import Aperture

    scene = generate(2, "varying", settings=GeneratorSettings(width=64, height=48))
    cam = scene.camera
    mpi = CM.layers_from_cards(scene)
    ap = Aperture(blades, math.radians(rotation_deg), ratio)
    a = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, replace(FAST, aperture=ap))
    b = C.composite(mpi, cam.blur_parameter, cam.focus_disparity,
                    CompositeSettings(backend=device, aperture=ap))
    disk = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, FAST)
    assert np.abs(a - disk).max() > 1e-3 * float(a.max())  # the shape is in use
    assert np.abs(a - b).max() <= 1e-6 * float(a.max())


def test_row_boxes_rebuild_the_kernel():
    for k in (K.disk_kernel(0.7), K.disk_kernel(9.2), K.soft_disk(6), K.disk_kernel(3.0, (0, 1, 2))):
        R = K.kernel_radius(k)
        rebuilt = np.zeros_like(k)
        for dy, a, b, h in K.row_boxes(k):
            rebuilt[dy + R, a + R:b + R + 1] += h
        assert np.abs(rebuilt - k).max() <= 1e-7 * k.max()


def test_separable_bilinear_equals_map_coordinates():
    """The reduced path's up-sampling gives ndimage.map_coordinates' bilinear values
    (order 1, edges clamped), to float32 rounding, also for points beyond the edges."""
    from scipy import ndimage

    from mpib_validate.runtime.resample import bilinear_separable

    rng = np.random.default_rng(3)
    a = rng.random((9, 13, 4)).astype(np.float32)
    ty = np.linspace(-1.7, 9.4, 23)
    tx = np.linspace(-0.6, 13.9, 31)
    yy, xx = np.meshgrid(ty, tx, indexing="ij")
    want = np.stack([ndimage.map_coordinates(a[..., c], [yy, xx], order=1, mode="nearest")
                     for c in range(4)], axis=-1)
    np.testing.assert_allclose(bilinear_separable(a, ty, tx), want, atol=2e-7)


def test_an_error_in_the_blur_thread_reaches_the_caller_and_no_thread_is_left():
    """The layers are blurred on a worker thread (composite._Prefetch): an error there
    is raised in the caller, and a caller that stops early (a cancelling progress)
    leaves no thread behind."""
    import threading

    rng = np.random.default_rng(3)
    mpi = _random_mpi(rng, 3, 20, 24, [0.2, 0.4, 0.6])
    before = threading.active_count()
    with pytest.raises(ValueError, match="kernel must be"):
        C.composite(mpi, 20.0, 0.4, CompositeSettings(kernel="bogus"))

    class Stop(Exception):
        pass

    def progress(f):
        if f > 0:
            raise Stop

    with pytest.raises(Stop):
        C.composite(mpi, 20.0, 0.4, FAST, progress=progress)
    assert threading.active_count() == before


def test_the_blur_threads_change_nothing(monkeypatch):
    """The layers' blur jobs run on several threads (composite._OrderedPool) and are
    laid in their order: the composite equals the one-thread composite to the bit, on
    layers that overlap everywhere (an "over" out of order would change it) and on an
    MPI of additive slabs from passes (group sums and the chain)."""
    from mpib_validate.runtime.layers.passes import PassesSettings, layers_from_passes

    rng = np.random.default_rng(11)
    dense = _random_mpi(rng, 10, 150, 210, list(np.linspace(0.1, 0.9, 10)))
    v, u = np.mgrid[0:120, 0:160]
    D = 0.2 + 0.6 * (u / 160.0) + 0.2 * (v > 60)
    colour = rng.random((120, 160, 3)).astype(np.float32)
    passes, _ = layers_from_passes(colour, D, 30.0, PassesSettings(split="additive"))
    cases = [(dense, 40.0, 0.45, FAST),
             (passes, 30.0, 0.5, CompositeSettings(chain_px=1.5))]
    for mpi, A, d_f, settings in cases:
        m = mpi.margin
        frame = (m, m + mpi.height, m, m + mpi.width)
        jobs = [k for k, _, _ in C._layer_parts(mpi.layers, A, d_f, settings, None,
                                                mpi.canvas_shape, frame, True)]
        assert jobs.count("parts") > 4  # more jobs than threads: several run at once
        monkeypatch.setattr(C, "MAX_BLUR_THREADS", 1)
        one = C.composite(mpi, A, d_f, settings)
        monkeypatch.setattr(C, "MAX_BLUR_THREADS", 4)
        monkeypatch.setattr(C, "_cores", lambda: 4)
        assert C.blur_threads() == 4
        many = C.composite(mpi, A, d_f, settings)
        monkeypatch.undo()
        assert np.array_equal(one, many)
