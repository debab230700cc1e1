"""What ``refocus`` hands back: exposure and alpha of the output, and where a known
background is used."""

from __future__ import annotations

import numpy as np

from mpib_validate.runtime.compositor import composite as C
from mpib_validate.runtime.io.exr import read_exr, rgba_from
from mpib_validate.runtime.layers.passes import (PassesSettings, depth_to_disparity, known_background_mask,
                                  layers_from_passes)
from mpib_validate.runtime.layers import fill as _fill
from mpib_validate.runtime.refocus import Passes, refocus, write_result
from mpib_validate.runtime.request import RefocusRequest


def _ramp_passes(h=48, w=64, transparent_sky=False):
    """A receding textured ground (disparity falling linearly up the frame: continuous
    depth spanning many planes) with an opaque box in front of it; above the ground's
    horizon, sky at infinity."""
    rng = np.random.default_rng(4)
    colour = (0.2 + 0.6 * rng.random((h, w, 3))).astype(np.float32)
    rows = np.arange(h, dtype=np.float64)[:, None] * np.ones((1, w))
    depth = 1.0 / (0.05 + 0.6 * rows / h)
    depth[: h // 6] = 1e10  # sky
    colour[: h // 6] = [0.3, 0.5, 0.9]
    depth[20:34, 24:40] = 1.0 / 0.9  # the box
    colour[20:34, 24:40] = [0.9, 0.3, 0.1]
    alpha = np.ones((h, w), np.float32)
    if transparent_sky:
        colour[: h // 6] = 0.0
        alpha[: h // 6] = 0.0
    return Passes(colour, depth.astype(np.float64), "ramp", "ramp", None, alpha)


def test_an_opaque_input_gives_an_opaque_correctly_exposed_output(tmp_path):
    """Content spanning planes is shared between two of them, and once blurred the
    composited coverage ``1 - prod(1 - a_i K_i)`` of such a pair is below 1: the output
    once carried it as alpha and was premultiplied by it (darker EXR than its preview).
    An opaque render must come back opaque: alpha exactly 1, the EXR colour the
    normalised colour (float32 round trip: exact)."""
    passes = _ramp_passes()
    A, df = 12.0, 0.9
    # the case is real: the composited coverage of these layers falls below 1
    mpi, _ = layers_from_passes(passes.colour, depth_to_disparity(passes.depth), A)
    coverage = C.composite(mpi, A, df)[..., 3]
    assert coverage.min() < 0.99
    res = refocus(RefocusRequest(passes, A, df))
    assert np.all(res.image[..., 3] == 1.0)
    assert np.isfinite(res.image).all()
    write_result(tmp_path / "out.exr", res)
    written = rgba_from(read_exr(tmp_path / "out.exr"))
    np.testing.assert_array_equal(written[..., 3], 1.0)
    np.testing.assert_array_equal(written[..., :3], res.image[..., :3])


def test_a_transparent_film_keeps_its_alpha():
    """Film transparent: the sky is no surface (alpha 0). The film alpha travels as a
    premultiplied channel, so the output is transparent where only sky is seen, opaque
    inside the ground and box, and in between at the blurred horizon; the refocused
    coverage conserves the input's, as a blur of content over nothing does (the sum of
    alpha changes only through the frame border: 2 % measured at this size, so 5 %)."""
    passes = _ramp_passes(transparent_sky=True)
    A, df = 12.0, 0.15  # the horizon nearly sharp (0.6 px), the box blurred by 9 px
    res = refocus(RefocusRequest(passes, A, df))
    a = res.image[..., 3]
    assert a[:5].max() < 1e-3  # sky, farther from the horizon than the blur reaches
    assert np.all(a[30:] > 0.999)
    horizon = a[5:12]
    assert horizon.min() < 0.5 < horizon.max()
    assert abs(a.sum() / passes.alpha.sum() - 1.0) < 0.05
    opaque = refocus(RefocusRequest(_ramp_passes(), A, df))
    # below the horizon's blur the two agree: the sky's alpha changes nothing there
    np.testing.assert_allclose(res.image[30:, :, :3], opaque.image[30:, :, :3], atol=1e-5)


def _self_occluding():
    """A wall (blue, d = 0.2) and an object (red brow at d = 0.5) with a recess (green,
    d = 0.4) inside it: the recess is hidden behind the brow, the wall behind the
    object's outline."""
    h, w = 40, 48
    D = np.full((h, w), 0.2)
    rgb = np.zeros((h, w, 3))
    rgb[:] = [0.1, 0.2, 0.9]
    D[8:32, 8:40] = 0.5
    rgb[8:32, 8:40] = [0.9, 0.2, 0.1]
    D[16:24, 18:30] = 0.4
    rgb[16:24, 18:30] = [0.1, 0.8, 0.2]
    wall = np.zeros((h, w, 3))
    wall[:] = [0.1, 0.2, 0.9]
    return rgb, D, wall


def test_a_known_background_is_used_only_where_it_shows_the_hidden_surface():
    """A render without the object shows the wall everywhere; behind the brow, though,
    the hidden surface is the recess. With the known render's depth, and without it
    (then the known render must agree with the visible far side of the edge), the wall
    is used behind the outline and not behind the brow."""
    rgb, D, wall = _self_occluding()
    A = 40.0
    thr = 1.0 / A  # the default jump of 1 px
    jumps = _fill.disparity_jumps(D, thr)
    region, far_field = _fill.occlusion_region(D, A, thr, jumps=jumps)
    known = np.ones(D.shape, bool)
    behind_brow = region & (np.abs(far_field - 0.4) < 1e-9)
    behind_outline = region & (np.abs(far_field - 0.2) < 1e-9)
    assert behind_brow.sum() > 10 and behind_outline.sum() > 10
    for known_d in (np.full(D.shape, 0.2), None):
        use = known_background_mask(rgb, D, far_field, jumps[2], wall, known, known_d)
        assert not use[behind_brow].any()
        assert use[behind_outline].all()


def test_self_occlusion_keeps_the_fill_end_to_end():
    """The same, through ``layers_from_passes``: behind the brow the layers hold the
    fill of the recess (green-dominant), never the wall's blue."""
    rgb, D, wall = _self_occluding()
    A = 40.0
    mpi_fill, _ = layers_from_passes(rgb, D, A)
    mpi_known, info = layers_from_passes(rgb, D, A, background=(wall, np.ones(D.shape, bool)))
    assert 0.0 < info.extra["background_used"] < 1.0
    for mpi in (mpi_fill, mpi_known):
        near_recess = [l for l in mpi.layers if abs(l.disparity - 0.4) < 1e-6]
        assert near_recess, "the recess has its own plane"
    # the recess plane (and the hidden content behind the brow on it) is the same with
    # and without the known background
    a = [l for l in mpi_fill.layers if abs(l.disparity - 0.4) < 1e-6][0]
    b = [l for l in mpi_known.layers if abs(l.disparity - 0.4) < 1e-6][0]
    assert a.box == b.box
    np.testing.assert_array_equal(a.rgba, b.rgba)
    # while the wall plane behind the outline takes the known colour
    wa = [l for l in mpi_known.layers if abs(l.disparity - 0.2) < 1e-6][0]
    prem = wa.rgba[..., :3]
    alpha = wa.rgba[..., 3:4]
    straight = np.divide(prem, alpha, out=np.zeros_like(prem), where=alpha > 0)
    inside = alpha[..., 0] > 0.99
    np.testing.assert_allclose(straight[inside], np.broadcast_to([0.1, 0.2, 0.9],
                                                                 straight[inside].shape),
                               atol=1e-5)
    _ = PassesSettings  # the defaults are what refocus uses


def _tiny_curved_emitter():
    """A 5x5 px emitter (radiance 50) whose depth is a small dome (disparity 0.64 to
    0.66, so it spans planes) over a dark wall at disparity 0.2."""
    H = W = 96
    yy, xx = np.mgrid[:5, :5] - 2.0
    dome = 0.64 + 0.02 * np.sqrt(np.maximum(0.0, 6.25 - yy ** 2 - xx ** 2)) / 2.5
    rgb = np.full((H, W, 3), 0.01)
    D = np.full((H, W), 0.2)
    rgb[46:51, 46:51] = 50.0
    D[46:51, 46:51] = dome
    return rgb, D


def test_additive_interval_groups_conserve_a_small_highlights_energy():
    """Content between two planes shared by the over split (opaque backing on the far
    plane, ``w`` on the near one) is counted up to ``1 + w`` times once blurred with
    Eq. 1: measured 1.48 to 1.50 here. The additive split with interval groups sums the
    two blurred shares instead: measured 0.989 to 0.994 (the rest is the dark wall's
    own weight under the highlight); we require 2 % (the issue's energy target)."""
    rgb, D = _tiny_curved_emitter()
    A = 40.0
    for df in (0.3, 0.9):  # behind and in front of the focus plane
        energy = {}
        for split in ("linear", "additive"):
            mpi, _ = layers_from_passes(rgb, D, A, PassesSettings(split=split))
            out = C.composite(mpi, A, df)
            energy[split] = (out[..., 0] - 0.01).sum() / (25 * (50.0 - 0.01))
        assert abs(energy["additive"] - 1.0) < 0.02, energy
        assert energy["linear"] > 1.3, energy  # the defect the groups remove


def test_additive_groups_change_nothing_for_content_on_planes():
    """Content exactly on its planes (fronto surfaces: no pixel strictly between two
    planes) forms one group per plane, and grouped compositing is then Eq. 1 itself."""
    rgb, D, _ = _self_occluding()
    A, df = 40.0, 0.3
    lin, _ = layers_from_passes(rgb, D, A, PassesSettings(split="linear"))
    add, _ = layers_from_passes(rgb, D, A, PassesSettings(split="additive"))
    assert add.grouped and not lin.grouped
    np.testing.assert_allclose(C.composite(add, A, df), C.composite(lin, A, df), atol=1e-6)


def _wire(H=48, W=48, width=0.8, d_wall=0.2, d_wire=1.0, wall=0.8, wire=0.05):
    """A slanted dark wire 0.8 px wide before an in-focus wall, rendered as a renderer
    does: box-filtered colour (coverage mix) and the depth of the surface at each pixel
    centre; returns the passes and the wire's coverage."""
    ys = np.arange(H) + 0.5
    x0 = 20.0 + 6.0 * ys / H
    j = np.arange(W)[None, :]
    lo = np.maximum(j, x0[:, None] - width / 2)
    hi = np.minimum(j + 1, x0[:, None] + width / 2)
    cov = np.clip(hi - lo, 0.0, 1.0)
    centre = np.abs(j + 0.5 - x0[:, None]) < width / 2
    colour = (cov * wire + (1 - cov) * wall)[..., None] * np.ones(3)
    depth = np.where(centre, 1 / d_wire, 1 / d_wall)
    return Passes(colour.astype(np.float32), depth, "wire", "wire", None, None), cov


def test_a_thin_wire_blurs_away_instead_of_leaving_sharp_remnants():
    """Focus on the wall, the wire 16 px out of focus: the truth is the wall with the
    wire's coverage blurred over it. Pixels the wire crosses without covering their
    centre carry the wall's depth and part of the wire's colour; they used to stay sharp
    (dark remnants: worst pixel 0.33 below the truth, measured). Unmixed with the
    wire's own mixed pixels as its colour they go with it: measured 0.24 worst (the rest
    is rows where no pixel centre is covered at all) and mean error 0.008 against 0.013.
    Required: worst below 0.28 and mean below 0.011, between the two."""
    from scipy import signal
    from mpib_validate.runtime.compositor.kernels import disk_kernel

    A, df = 20.0, 0.2
    passes, cov = _wire()
    K = disk_kernel(A * (1.0 - df))
    blurred = signal.fftconvolve(np.pad(cov, 40, mode="edge"), K, mode="same")[40:-40, 40:-40]
    truth = (1 - blurred) * 0.8 + blurred * 0.05
    out = refocus(RefocusRequest(passes, A, df)).image[..., 0]
    err = np.abs(out - truth)[8:-8, 8:-8]
    assert err.max() < 0.28 and err.mean() < 0.011, (err.max(), err.mean())


def test_slabs_merge_consecutive_groups_within_their_span():
    from mpib_validate.runtime.compositor.composite import _slabs
    from mpib_validate.runtime.layers.mpi import Layer

    z = np.zeros((1, 1, 4), np.float32)
    layers = [Layer(d, z, 0, 0, g) for d, g in
              ((0.10, 0), (0.10, 1), (0.12, 1), (0.12, 2), (0.12, 3), (0.20, 3), (0.30, 5))]
    assert _slabs(layers, 0.0) == [0, 1, 1, 2, 3, 3, 4]  # one slab per group
    assert _slabs(layers, 0.05) == [0, 0, 0, 0, 1, 1, 2]
    assert _slabs([Layer(0.1, z, 0, 0)], 1.0) == [None]


def test_slabs_close_the_seams_of_a_continuous_surface():
    """A smooth ramp (blur radius sweeping 4 px over 64 px) cut into additive groups: where
    two groups of the one surface meet, each group's blurred edge lets the other through
    ("over" of two half-covered edges) and the coverage dips. Mean coverage deficit in
    the frame's interior, measured: 0.096 with one slab per group, 0.027 with 2 px slabs
    (fewer seams), 0 with 4 px slabs (the whole ramp one slab); the over split's backing
    gives 0.014. Required: 2 px slabs at least halve the deficit."""
    H, W, A = 40, 64, 30.0
    x = np.arange(W)[None, :] * np.ones((H, 1))
    D = 1.0 + 0.002 * x
    rgb = np.stack([0.2 + 0.004 * x] * 3, -1)
    add, _ = layers_from_passes(rgb, D, A, PassesSettings(split="additive"))
    deficit = {}
    for sl in (None, 2.0):
        cov = C.composite(add, A, 1.2, C.CompositeSettings(slab_px=sl))[5:-5, 10:-10, 3]
        deficit[sl] = float((1.0 - np.minimum(cov, 1.0)).mean())
    assert deficit[2.0] < 0.5 * deficit[None], deficit
