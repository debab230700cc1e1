"""The Eq. 15 ray tracer: blur radius, focus, energy, backends, depth order.

Every tolerance below is derived in its comment, from float32 rounding or from the
sampling error of the sample set used.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mpib_validate.runtime import samples
from mpib_validate.cards import trace
from mpib_validate.runtime.camera import Camera
from mpib_validate.cards.scene import Card, Plane, Scene

from conftest import dot_card, jit_backends, opaque_card

BACKENDS = ["numpy"] + jit_backends()


def _moments(img):
    """Total, centroid and mean squared distance from the centroid of a (H, W) image,
    with pixel centres at integer + 0.5."""
    h, w = img.shape
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    total = img.sum(dtype=np.float64)
    cx = (img * xs).sum(dtype=np.float64) / total
    cy = (img * ys).sum(dtype=np.float64) / total
    m2 = (img * ((xs - cx) ** 2 + (ys - cy) ** 2)).sum(dtype=np.float64) / total
    return total, cx, cy, m2


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("disparity", [0.5 + 1.5 / 20, 0.5 - 4.0 / 20, 0.5 + 12.3 / 20])
def test_point_blurs_into_disk_of_radius_A_delta_d(backend, disparity):
    """A texel at disparity d spreads into a disk of radius r = A |d - d_f|, centred on its
    pinhole projection, conserving its energy.

    With pixel-box sampling, each sample lands in exactly one pixel, and the rounding to
    that pixel adds variance f(1 - f) per axis, 1/6 on average over the shift's
    fractional part f; the texel's own box adds 1/12 + the pixel box's 1/12 in the same
    way. So E[rho^2] = r^2 / 2 + 1/3 and r = sqrt(2 (E[rho^2] - 1/3)).
    """
    cam = Camera(64, 64, blur_parameter=20.0, focus_disparity=0.5)
    card = dot_card("dot", 33, disparity, radiance=5.0, offset=(15, 16))
    scene = Scene(cam, [card])
    img, _ = trace.trace(scene, samples.stratified(4096, seed=3), backend=backend)
    lum = img[..., 0]
    total, cx, cy, m2 = _moments(lum)
    r_true = cam.blur_radius(disparity)
    r_est = np.sqrt(2.0 * (m2 - 1.0 / 3.0))
    # the tolerance: 0.05 px or 0.5 %; the 4096-point Sobol set's own second
    # moment of the disk is within 2e-4 of 1/2 (measured), far inside it.
    assert abs(r_est - r_true) <= max(0.05, 0.005 * r_true), (r_est, r_true)
    # centre: the texel (15 + 16, 16 + 16) covers [31, 32) x [32, 33): centre (31.5, 32.5)
    # (pixel coordinates from the top-left corner). The mean rounding offset is 0 in
    # expectation; 0.02 px covers the Sobol set's imbalance (measured < 0.005 px).
    assert abs(cx - 31.5) < 0.02 and abs(cy - 32.5) < 0.02, (cx, cy)
    # energy: one texel of radiance 5 (area 1 px^2) -> image total 5; the float32 sum
    # of <= 4096 identical-weight samples, averaged in float64, is exact to ~1e-6.
    assert total == pytest.approx(5.0, rel=1e-5)
    # the disk has radius r: nothing lands beyond r + 2 px (texel + pixel boxes)
    ys, xs = np.mgrid[0:64, 0:64] + 0.5
    far = np.hypot(xs - 31.5, ys - 32.5) > r_true + 2.0
    assert lum[far].max() == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_card_at_focus_is_reproduced_exactly(backend):
    """At d = d_f every sample of a pixel hits the same texel, so the image is the
    premultiplied texture exactly; coverage 1 - (1 - a) is a within one float32 rounding."""
    rng = np.random.default_rng(0)
    cam = Camera(40, 30, blur_parameter=25.0, focus_disparity=0.4)
    rgba = rng.random((30, 40, 4)).astype(np.float32)
    rgba[..., :3] *= 8.0  # HDR
    scene = Scene(cam, [Card("sharp", rgba, Plane.fronto(0.4), (0, 0))])
    img, _ = trace.trace(scene, samples.stratified(512, seed=1), backend=backend)
    np.testing.assert_array_equal(img[..., :3], rgba[..., :3] * rgba[..., 3:])
    np.testing.assert_allclose(img[..., 3], rgba[..., 3], rtol=0, atol=np.finfo(np.float32).eps)


@pytest.mark.parametrize("backend", BACKENDS)
def test_constant_opaque_background_stays_constant(backend):
    """Every sample of every pixel hits the background (it covers frame + blur), so each
    pixel is exactly its colour, however strong the blur."""
    cam = Camera(32, 24, blur_parameter=40.0, focus_disparity=0.9)
    margin = int(np.ceil(cam.blur_radius(0.05))) + 2
    colour = np.array([0.25, 3.0, 0.125], np.float32)
    bg = opaque_card("bg", 24 + 2 * margin, 32 + 2 * margin, colour, Plane.fronto(0.05),
                     (-margin, -margin))
    img, _ = trace.trace(Scene(cam, [bg]), samples.stratified(256), backend=backend)
    np.testing.assert_array_equal(img[..., :3], np.broadcast_to(colour, (24, 32, 3)))
    np.testing.assert_array_equal(img[..., 3], 1.0)


@pytest.mark.skipif(len(BACKENDS) < 2, reason="no Dr.Jit backend runs here")
@pytest.mark.parametrize("lookup", trace.LOOKUPS)
@pytest.mark.parametrize("order", trace.ORDERS)
def test_numpy_and_drjit_agree(three_card_scene, lookup, order):
    """Both backends run the same float32 operations in the same order (one shared
    routine) and accumulate in float64, so they agree bit for bit; any difference means
    an operation was reordered or contracted (e.g. into an FMA)."""
    smp = samples.stratified(64, seed=2)
    ref, _ = trace.trace(three_card_scene, smp, backend="numpy", lookup=lookup, order=order)
    for be in BACKENDS[1:]:
        img, meta = trace.trace(three_card_scene, smp, backend=be, lookup=lookup, order=order)
        assert meta["backend"] == be
        np.testing.assert_array_equal(img, ref)


def _crossing_scene():
    """Two opaque tilted cards that cross at x = 0: red is nearer on the left, blue on
    the right. No fixed order of the two can be right everywhere."""
    cam = Camera(40, 16, blur_parameter=4.0, focus_disparity=0.5)
    red = opaque_card("red", 16, 40, [1, 0, 0], Plane.from_gradient(0.5, -0.01, 0.0), (0, 0))
    blue = opaque_card("blue", 16, 40, [0, 0, 1], Plane.from_gradient(0.5, 0.01, 0.0), (0, 0))
    return Scene(cam, [red, blue]).validate()


def _crossing_matches_truth(img):
    """Left half red, right half blue (pinhole view, pixel centres never at x = 0)."""
    left, right = img[:, :20], img[:, 20:]
    return bool((left[..., 0] == 1).all() and (left[..., 2] == 0).all()
                and (right[..., 2] == 1).all() and (right[..., 0] == 0).all())


@pytest.mark.parametrize("backend", BACKENDS)
def test_per_ray_depth_sort_handles_interleaved_cards(backend):
    scene = _crossing_scene()
    img, _ = trace.trace(scene, samples.pinhole(4), backend=backend, order="depth")
    assert _crossing_matches_truth(img)
    # The official generator's fixed order fails the same check: this test catches it.
    wrong, _ = trace.trace(scene, samples.pinhole(4), backend=backend, order="fixed")
    assert not _crossing_matches_truth(wrong)


def test_depth_groups_skip_sorting_only_where_ranges_do_not_overlap(three_card_scene):
    groups = trace.depth_groups(three_card_scene)
    # tilt [~0.3, ~0.9] overlaps fg at 0.62; the background at 0.1 is behind both
    assert groups == ((1, 2), (0,))
    assert trace.depth_groups(_crossing_scene()) == ((0, 1),)


def test_render_passes(three_card_scene):
    res = trace.render(three_card_scene, samples.stratified(64), backend="numpy")
    h, w = 40, 48
    assert res.bokeh.shape == res.all_in_focus.shape == (h, w, 4)
    assert res.card_alpha.shape == (3, h, w)
    # background everywhere -> coverage 1, depth finite
    np.testing.assert_allclose(res.all_in_focus[..., 3], 1.0, atol=1e-6)
    assert (res.layer >= 0).all() and (res.depth < 1e10).all()
    # where the fronto fg card is opaque at the pixel centre and nothing nearer is
    # solid, the layer is fg and the disparity is its own
    fg = res.layer == 2
    assert fg.any()
    np.testing.assert_allclose(res.disparity[fg], 0.62, rtol=1e-6)
    np.testing.assert_allclose(res.depth[fg], 1 / 0.62, rtol=1e-6)


def test_trace_rejects_bad_options(three_card_scene):
    with pytest.raises(ValueError, match="lookup"):
        trace.trace(three_card_scene, samples.pinhole(1), lookup="cubic")
    with pytest.raises(ValueError, match="order"):
        trace.trace(three_card_scene, samples.pinhole(1), order="random")
    with pytest.raises(ValueError, match="backend"):
        trace.trace(three_card_scene, samples.pinhole(1), backend="opencl")


@settings(max_examples=25, deadline=None)
@given(d=st.floats(0.05, 1.0), df=st.floats(0.0, 1.0), A=st.floats(1.0, 20.0),
       radiance=st.floats(0.01, 1e4), ox=st.integers(8, 12), oy=st.integers(8, 12))
def test_energy_is_conserved_for_any_fronto_card(d, df, A, radiance, ox, oy):
    """Property: a small card fully inside the frame after blur keeps its total energy
    (each sample lands in exactly one pixel). Relative float32 rounding of the
    per-sample radiance, averaged in float64: 1e-6."""
    cam = Camera(48, 48, blur_parameter=A, focus_disparity=df)
    if cam.blur_radius(d) > 7.0:
        d = df + 7.0 / A * np.sign(d - df or 1.0)
        if d <= 0.01:
            d = df + 7.0 / A
    rgba = np.zeros((24, 24, 4), np.float32)
    rgba[6:18, 6:18] = [radiance, radiance / 2, 0.0, 1.0]
    scene = Scene(cam, [Card("c", rgba, Plane.fronto(d), (ox, oy))])
    img, _ = trace.trace(scene, samples.stratified(32), backend="numpy")
    expected = 144 * np.float32(radiance)
    assert img[..., 0].sum(dtype=np.float64) == pytest.approx(float(expected), rel=1e-6)
