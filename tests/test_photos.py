"""Predicted-looking disparity: the seeded degradation, the guided refinement, and the
photos bench suite on a tiny run (the numbers come from `mpib bench --suite photos`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mpib_validate.cards.degrade import degrade_disparity
from mpib_validate.runtime.layers.passes import PassesSettings, layers_from_passes
from mpib_validate.runtime.layers.refine import guided_filter, refine_disparity


def _two_regions(seed=0, size=64, edge=32):
    """Left of column ``edge``: a near red surface (d = 0.5); right: a far blue one
    (d = 0.1); colour with 1 % seeded noise so the guide is not a perfect step."""
    rng = np.random.default_rng(seed)
    colour = np.empty((size, size, 3))
    colour[:, :edge] = (0.6, 0.15, 0.1)
    colour[:, edge:] = (0.1, 0.2, 0.5)
    colour *= 1.0 + 0.01 * rng.standard_normal(colour.shape)
    D = np.full((size, size), 0.1)
    D[:, :edge] = 0.5
    return colour, D


def test_degradation_is_seeded_and_deterministic():
    _, D = _two_regions()
    a, b = degrade_disparity(D, 3), degrade_disparity(D, 3)
    assert np.array_equal(a, b)  # bit for bit
    assert not np.array_equal(a, degrade_disparity(D, 4))  # the seed matters
    assert a.shape == D.shape and np.all(a >= 0) and np.all(np.isfinite(a))


def test_degradation_with_every_step_off_is_the_identity():
    _, D = _two_regions()
    assert np.array_equal(degrade_disparity(D, 0, blur_px=0, down=1, shift_px=0, noise=0), D)


def test_degradation_spreads_and_shifts_the_edge():
    """Blur + 4x down/up spread the step over several pixels; the shift moves its
    mid-crossing by shift_px * |cos(angle)| along x (angle drawn from the seed)."""
    _, D = _two_regions()
    g = degrade_disparity(D, 1, noise=0.0)
    ramp = (g > 0.11) & (g < 0.49)
    assert ramp[32].sum() >= 4  # sigma 2 px alone gives ~ +-2 sigma of ramp
    # the mid-crossing per row, against the true edge at x = 31.5 (between columns)
    rows = [np.interp(0.3, g[y, ::-1], np.arange(63, -1, -1)) for y in range(16, 48)]
    angle = np.random.default_rng(1).uniform(0.0, 2.0 * math.pi)
    # the shift moves the map by +1.5 cos(angle) px in x; the 4x grid aligns the step
    # to within its half-cell of 2 px and bilinear interpolation is exact on a ramp, so
    # the crossing is within 2 px of 31.5 + shift
    assert abs(np.mean(rows) - (31.5 + 1.5 * math.cos(angle))) <= 2.0


def test_guided_filter_with_a_flat_guide_is_the_box_mean_of_the_box_mean():
    """A constant guide has zero variance: a = 0, b = mean(p), q = box(box(p))."""
    from mpib_validate.runtime.layers.refine import box_mean

    rng = np.random.default_rng(0)
    p = rng.random((20, 24))
    q = guided_filter(np.full((20, 24, 3), 0.5), p, 2, 1e-3)
    # the filter computes in float32: values below 1 to a few of its ulps (6e-8 each)
    np.testing.assert_allclose(q, box_mean(box_mean(p, 2), 2), atol=1e-6)


def test_window_means_and_extremes_are_those_of_the_clipped_windows():
    """The refinement's box mean and its small-window extremes (written with shifted
    array operations) against the windows clipped to the array, pixel by pixel, on
    arrays smaller and larger than the window, and against scipy's filters (the
    extremes exactly: a minimum or maximum has no rounding)."""
    from scipy import ndimage

    from mpib_validate.runtime.layers.refine import _closing, _extreme, _opening, box_mean

    rng = np.random.default_rng(4)
    for shape in [(1, 1), (2, 7), (5, 3), (9, 13), (23, 17)]:
        for r in (1, 2, 3, 6):
            x = rng.random(shape)
            H, W = shape
            clipped = [[(y0, y1, x0, x1) for x0, x1 in
                        [(max(0, j - r), min(W, j + r + 1)) for j in range(W)]]
                       for y0, y1 in [(max(0, i - r), min(H, i + r + 1)) for i in range(H)]]
            mean = np.array([[x[a:b, c:d].mean() for a, b, c, d in row] for row in clipped])
            # float64 running sums: a few ulps of values below 1
            np.testing.assert_allclose(box_mean(x, r), mean, rtol=0, atol=1e-12)
            rgb = rng.random(shape + (3,)).astype(np.float32)
            np.testing.assert_allclose(box_mean(rgb, r)[..., 1], box_mean(rgb[..., 1], r),
                                       rtol=0, atol=0)
            for fn, extreme in ((np.maximum, np.max), (np.minimum, np.min)):
                want = np.array([[extreme(x[a:b, c:d]) for a, b, c, d in row]
                                 for row in clipped])
                assert np.array_equal(_extreme(x, 2 * r + 1, fn), want)
                b = x > 0.5
                assert np.array_equal(_extreme(b, 2 * r + 1, fn),
                                      (ndimage.maximum_filter if fn is np.maximum
                                       else ndimage.minimum_filter)(b, 2 * r + 1,
                                                                    mode="nearest"))
        assert np.array_equal(_opening(x), ndimage.grey_opening(x, (3, 3), mode="nearest"))
        assert np.array_equal(_closing(x), ndimage.grey_closing(x, (3, 3), mode="nearest"))


def test_half_and_double_keep_a_plane():
    """:func:`half` averages 2x2 groups, :func:`double` interpolates bilinearly between
    their centres: a plane comes back exactly (to float32 rounding) away from the first
    row and column and the last two (where the doubling clamps, and an odd side's padded
    group is not on the plane); odd sides are padded and cropped."""
    from mpib_validate.runtime.resample import bilinear_separable, double, half

    for H, W in ((8, 10), (9, 7), (2, 2), (1, 5)):
        y, x = np.mgrid[0:H, 0:W].astype(np.float32)
        plane = 0.5 + 0.01 * y - 0.02 * x
        h = half(plane)
        assert h.shape == (-(-H // 2), -(-W // 2))
        back = double(h, (H, W))
        assert back.shape == (H, W)
        inner = (slice(1, max(1, H - 2)), slice(1, max(1, W - 2)))
        np.testing.assert_allclose(back[inner], plane[inner], rtol=0, atol=1e-6)
        np.testing.assert_array_equal(double(np.full_like(h, 0.25), (H, W)), 0.25)
        # the doubling is the separable bilinear interpolation at the full pixels' centres
        ty, tx = (np.arange(H) + 0.5) / 2 - 0.5, (np.arange(W) + 0.5) / 2 - 0.5
        np.testing.assert_allclose(back, bilinear_separable(h, ty, tx), rtol=0, atol=1e-6)


def test_subsampled_guided_filter_finds_the_colour_edge_of_the_full_one():
    """The fast guided filter (statistics at half resolution, coefficients doubled and
    applied to the full-resolution guide) steps at the same colour edge as the full
    filter: a mask 3 px off a red-blue edge is pulled onto it, with ``q >= 1/2`` on
    the same columns (the edge is in the guide, which stays at full resolution)."""
    from mpib_validate.runtime.layers.refine import (guide_statistics, guided_apply,
                                                     guided_filter)
    from mpib_validate.runtime.resample import half

    colour, _ = _two_regions(size=64, edge=31)  # an odd edge: inside a 2x2 group
    guide = np.sqrt(colour).astype(np.float32)
    p = np.zeros((64, 64), np.float32)
    p[:, :34] = 1.0  # the mask, 3 px into the far side
    full = guided_filter(guide, p, 8, 1e-4) >= 0.5
    stats = guide_statistics(half(guide), 4, 1e-4)
    fast = guided_apply(stats, p, 4, [guide[..., k].copy() for k in range(3)]) >= 0.5
    rows = slice(16, 48)  # away from the top and bottom, where the windows are clipped
    assert np.all(_crossing(full[rows].astype(float), 0.5) == 31)
    assert np.array_equal(fast[rows], full[rows])
    # the part asked for is that part of the whole
    part = guided_apply(stats, p, 4, [guide[..., k].copy() for k in range(3)],
                        ((10, 41), (5, 60)))
    whole = guided_apply(stats, p, 4, [guide[..., k].copy() for k in range(3)])
    np.testing.assert_array_equal(part, whole[10:41, 5:60])


def _crossing(D, mid=0.3):
    """First column, per row, where the disparity drops below ``mid`` (the far side)."""
    return np.argmax(D < mid, axis=1)


def test_refinement_moves_a_blurred_edge_back_onto_the_colour_edge():
    colour, D = _two_regions()
    A = 40.0  # jump = 16 px of blur radius: an edge that matters
    # the prediction: blurred (sigma 2 px) and shifted 2 px into the far (blue) side
    pred = degrade_disparity(D, 0, blur_px=2.0, down=1, shift_px=0.0, noise=0.0)
    pred = np.roll(pred, 2, axis=1)
    pred[:, :2] = 0.5
    rows = slice(8, 56)
    # without the refinement the split follows the prediction: 2 px off the colour edge
    assert np.all(_crossing(pred)[rows] == 34)
    ref = refine_disparity(colour, pred, A)
    # the first blue column, exactly: the colour step is 0.4 against 1 % noise
    assert np.all(_crossing(ref)[rows] == 32)
    # and each side takes its surface's disparity: the ramp is gone (within keep_px of
    # blur radius = 0.5 px, i.e. 0.5 / A in disparity)
    tol = 0.5 / A
    assert np.all(np.abs(ref[rows, :32] - 0.5) <= tol)
    assert np.all(np.abs(ref[rows, 32:] - 0.1) <= tol)


def test_refinement_changes_only_its_uncertain_band():
    """The loss decomposition of the photos suite gives the exact disparity back on
    `uncertain_band`; that is where the refinement acts, and nowhere else."""
    from mpib_validate.runtime.layers.refine import uncertain_band

    colour, D = _two_regions()
    A = 40.0
    pred = degrade_disparity(D, 3)
    ref = refine_disparity(colour, pred, A)
    band = uncertain_band(pred, A)
    assert band.any() and not band.all()
    np.testing.assert_array_equal(ref[~band], pred[~band])
    assert (ref[band] != pred[band]).mean() > 0.5  # it does act there


def test_refinement_leaves_a_smooth_surface_alone():
    """A tilted plane spanning less than jump_px over the window is not an edge."""
    colour, _ = _two_regions()
    x = np.arange(64)[None, :] * np.ones((64, 1))
    D = 0.2 + 0.001 * x  # 0.04 px of blur radius per pixel at A = 40
    np.testing.assert_array_equal(refine_disparity(colour, D, 40.0), D)


def _steep_ground(seed: int = 0):
    """A ground plane near the camera under a checkerboard: disparity linear in the image
    and steep, 0.5 px of blur radius per row at A = 40 (6 px over the 13 px window, more
    than jump_px), with a degraded map's noise (0.3 %: 0.57 px of blur radius at most)."""
    rng = np.random.default_rng(seed)
    y = np.arange(96)[:, None] * np.ones((1, 96))
    x = np.ones((96, 1)) * np.arange(96)[None, :]
    checks = ((y // 8 + x // 8) % 2).astype(np.float64)
    colour = np.repeat((0.2 + 0.6 * checks)[..., None], 3, axis=-1)
    plane = 0.2 + 0.0125 * y
    return rng, x, colour, plane


def test_refinement_does_not_cut_a_steep_plane_into_steps():
    """The window's range on a steep plane is what its slope gives, so there is no edge
    to move. Cut into flat patches with steps between them, it made seams across the
    checks (3.5 px of blur radius off the plane; the Blender suite's ground-near lost
    8 dB on its near ground). The refined map stays within the input's noise of the
    plane (0.57 px): the bound is 1 px, half of jump_px."""
    rng, _, colour, plane = _steep_ground()
    D = plane * (1.0 + 0.003 * rng.standard_normal(plane.shape))
    A = 40.0
    assert A * np.abs(D - plane).max() < 0.6
    assert A * np.abs(refine_disparity(colour, D, A) - plane).max() < 1.0


def test_refinement_moves_an_edge_on_a_steep_plane():
    """A box (0.2 nearer, 8 px of blur radius) stands on the steep ground; its predicted
    edge is smoothed over 7 px and shifted by 2. The refinement puts it on the colour
    edge and leaves the ground a plane: fewer than 1 % of the pixels end more than
    jump_px of blur radius off the true map (the prediction: 6 %; with the slope taken
    for an edge everywhere, 89 %)."""
    from scipy import ndimage

    rng, x, colour, plane = _steep_ground(1)
    truth = np.where(x >= 48, plane + 0.2, plane)
    colour[:, 48:] = [0.9, 0.2, 0.1]
    D = truth * (1.0 + 0.003 * rng.standard_normal(truth.shape))
    pred = np.roll(ndimage.uniform_filter(D, 7), 2, axis=1)
    A = 40.0
    assert (A * np.abs(pred - truth) > 2.0).mean() > 0.05
    assert (A * np.abs(refine_disparity(colour, pred, A) - truth) > 2.0).mean() < 0.01


def test_refine_option_in_passes_settings():
    colour, D = _two_regions()
    pred = np.roll(degrade_disparity(D, 0, blur_px=2.0, down=1, shift_px=0.0, noise=0.0), 2, 1)
    off, _ = layers_from_passes(colour, pred, 40.0, PassesSettings())
    on, _ = layers_from_passes(colour, pred, 40.0, PassesSettings(refine="guided"))
    assert off.plane_count != on.plane_count or any(
        not np.array_equal(a.rgba, b.rgba) for a, b in zip(off.layers, on.layers))
    with pytest.raises(ValueError, match="refine"):
        layers_from_passes(colour, pred, 40.0, PassesSettings(refine="matting"))


def test_photos_suite_on_one_tiny_scene_per_family(tmp_path):
    from mpib_validate.bench import photos

    r = photos.run(tmp_path, seeds=range(1), size=32, ref_spp=64, hd=False, figure=False,
                   remnants=False)
    methods = {row["method"] for row in r["rows"]}
    for preset in ("draft", "default", "best"):
        for kind in ("exact (bound)", "degraded", "degraded + guided"):
            assert f"{preset} {kind}" in methods
    for m in ("default exact + guided", "default degraded + guided-thin",
              "default exact + guided-thin"):
        assert m in methods
    for m in photos.ORACLES.values():
        assert m in methods
    for row in r["rows"]:
        assert math.isfinite(row["psnr"]) and math.isfinite(row["psnr_ob"])
        assert 0 <= row["scoped_fraction"] <= 1
        assert 0 <= row["remnants"] <= row["must_blur_smooth"] <= row["must_blur"]
    page = (tmp_path / "photos.md").read_text()
    if "defocus-node degraded" in methods:  # the targets need the node (bpy)
        assert page.count("cards: re-scoped degraded-depth targets\n") == 2
    assert page.count("cards: sharp remnants against the truth\n") == 2
    # a family table and a remnant table per family
    assert page.count("| default degraded |") == 4
    assert (tmp_path / "photos.md").read_text().count("where the degraded depth loses") == 2
    assert (tmp_path / "photos.json").stat().st_size > 0


def test_oracle_disparities_give_back_exact_values_on_their_region_only():
    """The loss decomposition's disparities (photos and Blender suites): each equals the
    exact disparity on its region (highlights: all-in-focus > 1 grown by
    HIGHLIGHT_GROW_PX; the refinement's uncertain band; both) and the guided refinement
    of the degraded map everywhere else."""
    from scipy import ndimage

    from mpib_validate.bench import photos
    from mpib_validate.runtime.layers.refine import uncertain_band

    colour, D = _two_regions(size=64, edge=30)
    colour = colour.copy()
    colour[8:10, 8:10] = 20.0  # a small light, far from the edge
    pred = degrade_disparity(D, 3)
    out = photos.oracle_disparities(colour, D, pred, 40.0)
    assert set(out) == set(photos.ORACLES.values())
    refined = refine_disparity(colour, pred, 40.0)
    lights = ndimage.binary_dilation(colour.max(-1) > 1.0,
                                     iterations=photos.HIGHLIGHT_GROW_PX)
    band = uncertain_band(pred, 40.0)
    # a 2x2 square grown twice by the 4-neighbour cross: 24 pixels
    assert lights.sum() == 24 and band.any() and not (lights & band).any()
    for key, region in (("highlights", lights), ("band", band), ("both", lights | band)):
        got = out[photos.ORACLES[key]]
        np.testing.assert_array_equal(got[region], D[region])
        np.testing.assert_array_equal(got[~region], refined[~region])


def test_refinement_on_tiles_equals_the_whole_image(monkeypatch):
    """The guided filter runs on boxes around the edges with a 2 r margin; with one tile
    the size of the image the result must be the same: it is a threshold of the filter
    output (which differs by rounding at most) and the windows' extremes (exact)."""
    from mpib_validate.runtime.layers import refine

    colour, D = _two_regions(size=96, edge=40)
    pred = degrade_disparity(D, 2)
    small = refine_disparity(colour, pred, 40.0)
    monkeypatch.setattr(refine, "TILE", 128)
    np.testing.assert_array_equal(small, refine_disparity(colour, pred, 40.0))


def test_side_values_on_boxes_equal_the_whole_image(monkeypatch):
    """The side values (the nearest pixel outside the band on each side) are computed on
    the boxes of the band's tiles grown by twice their reach; two objects far apart make
    two boxes that do not cover the image, and one tile the size of the image one box:
    the same disparity, bit for bit."""
    from mpib_validate.runtime.layers import refine

    rng = np.random.default_rng(5)
    size = 224
    colour = np.empty((size, size, 3))
    colour[:] = (0.1, 0.2, 0.5)
    D = np.full((size, size), 0.1) + 0.0004 * np.arange(size)[None, :]  # a slanted wall
    for y, x in ((20, 20), (150, 160)):  # two near squares, one of them slanted too
        colour[y:y + 50, x:x + 50] = (0.6, 0.15, 0.1)
        D[y:y + 50, x:x + 50] = 0.5 + 0.001 * np.arange(50)[:, None]
    colour *= 1.0 + 0.01 * rng.standard_normal(colour.shape)
    pred = degrade_disparity(D, 1)
    boxes = list(refine._boxes(refine.uncertain_band(pred, 40.0), refine.TILE))
    assert len(boxes) == 2
    small = refine_disparity(colour, pred, 40.0)
    monkeypatch.setattr(refine, "TILE", 256)
    np.testing.assert_array_equal(small, refine_disparity(colour, pred, 40.0))


def test_refinement_in_small_blocks_equals_large_ones(monkeypatch):
    """A large photograph's edge boxes are cut into blocks (refine.BLOCK_PX) to bound the
    working memory; blocks of 64 px, each with its own margin, give the disparity of
    blocks larger than the image, bit for bit."""
    from mpib_validate.runtime.layers import refine

    colour, D = _two_regions(size=160, edge=70)
    pred = degrade_disparity(D, 4)
    monkeypatch.setattr(refine, "BLOCK_PX", 64)
    assert len(list(refine._boxes(refine.uncertain_band(pred, 40.0), refine.TILE))) > 1
    small = refine_disparity(colour, pred, 40.0)
    monkeypatch.setattr(refine, "BLOCK_PX", 4096)
    assert len(list(refine._boxes(refine.uncertain_band(pred, 40.0), refine.TILE))) == 1
    np.testing.assert_array_equal(small, refine_disparity(colour, pred, 40.0))


def test_side_values_reach_outside_the_band_tiles():
    """A band that fills its tiles exactly (columns 32-63): the nearest pixels outside it
    lie in the neighbouring tiles, which the box's margin must hold; the boxed result
    equals the whole image's."""
    from mpib_validate.runtime.layers import refine

    H, W = 64, 128
    x = np.arange(W)[None, :] * np.ones((H, 1))
    D = np.where(x < 48, 0.5 + 0.001 * x, 0.1)  # a slanted near side, a flat far side
    band = (x >= 32) & (x < 64)
    hi = np.full((H, W), D.max())
    lo = np.full((H, W), D.min())
    boxed = [hi.copy(), lo.copy()]
    for box, b_at, h, l in refine._outside_side_blocks(D, band, hi, lo, 18):
        boxed[0][box][b_at], boxed[1][box][b_at] = h, l
    at, *whole = refine._outside_sides_box(D, band, hi, lo, 18)
    for b, w in zip(boxed, whole):
        np.testing.assert_array_equal(b[at], w)
    # the near side continues with the slanted wall's value at the band's edge (x = 31)
    # within the reach of 18 px; beyond it, the window's maximum
    reached = band & (x <= 31 + 18)
    np.testing.assert_allclose(boxed[0][reached], 0.5 + 0.001 * 31)
    np.testing.assert_array_equal(boxed[0][band & ~reached], hi[band & ~reached])
    np.testing.assert_array_equal(boxed[1][band], 0.1)  # the far side: the flat 0.1


def test_refocus_takes_the_refine_option():
    from mpib_validate.runtime.refocus import Passes, refocus
    from mpib_validate.runtime.request import RefocusRequest

    colour, D = _two_regions()
    pred = np.roll(degrade_disparity(D, 0, blur_px=2.0, down=1, shift_px=0.0, noise=0.0), 2, 1)
    passes = Passes(colour.astype(np.float32), 1.0 / pred, "c", "d")
    off = refocus(RefocusRequest(passes, 40.0, 0.1)).image
    on = refocus(RefocusRequest(passes, 40.0, 0.1, refine="guided")).image
    # focus on the far side: the near red surface blurs by 16 px; moving its edge 2 px
    # changes the image near the edge
    assert np.abs(on - off).max() > 0.01
    assert np.array_equal(off, refocus(RefocusRequest(passes, 40.0, 0.1, refine="off")).image)


def test_guided_thin_gives_a_thin_wire_its_disparity_back():
    """A 2 px wire (d = 0.5, white) before a far grey wall (d = 0.1), its disparity blurred
    (sigma 2 px): the blur keeps the local mean, so over a 13 px window the wire's
    near fraction 2/13 and the mean give back its jump; the window's maximum alone keeps
    about 0.4 of it (2 px of a sigma-2 Gaussian)."""
    colour = np.full((48, 48, 3), 0.2)
    colour[:, 23:25] = 0.9
    D = np.full((48, 48), 0.1)
    D[:, 23:25] = 0.5
    pred = degrade_disparity(D, 0, blur_px=2.0, down=1, shift_px=0.0, noise=0.0)
    assert pred[24, 23] < 0.3  # the prediction has lost most of the wire
    plain = refine_disparity(colour, pred, 40.0)
    thin = refine_disparity(colour, pred, 40.0, thin=True, flip_px=48)
    assert plain[24, 23] < 0.3
    # within 0.02 (0.8 px of blur radius at A = 40): the Gaussian's tails beyond the
    # 13 px window (3 sigma) and the window's clipped mean at the wire's edge
    np.testing.assert_allclose(thin[8:40, 23:25], 0.5, atol=0.02)
    # the wall keeps its value, or the prediction's within keep_px (0.5 px / A)
    np.testing.assert_allclose(thin[8:40, :18], 0.1, atol=0.5 / 40.0)
    np.testing.assert_allclose(thin[8:40, 29:], 0.1, atol=0.5 / 40.0)


def _face_and_temple(shift_px=-1.5, K=60.0, n=128, edge=64):
    """A synthetic portrait detail: a skin-coloured near surface (d = 0.8, left of
    column ``edge``) before a dark far one (d = 0.2), and a dark line two pixels wide
    (a temple of sunglasses) across the skin up to its outline. The map is shaped like
    a network's: Gaussian blur 2 px, 4x down (block mean) and bilinear up, shifted
    ``shift_px`` in x (into the skin: the map's edge lies inside the outline). Returns
    (linear colour, predicted disparity)."""
    from scipy import ndimage

    srgb = np.full((n, n, 3), 0.12)
    srgb[:, :edge] = (0.85, 0.62, 0.5)
    srgb[n // 2 - 1:n // 2 + 1, :edge] = 0.08
    D = np.full((n, n), 0.2)
    D[:, :edge] = 0.8
    low = ndimage.gaussian_filter(D, 2.0, mode="nearest").reshape(
        n // 4, 4, n // 4, 4).mean(axis=(1, 3))
    c = (np.arange(n) + 0.5) / 4 - 0.5
    gy, gx = np.meshgrid(c, c, indexing="ij")
    pred = ndimage.map_coordinates(low, [gy, gx], order=1, mode="nearest")
    pred = ndimage.shift(pred, (0, shift_px), order=1, mode="nearest")
    return srgb ** 2.2, pred


def _refocused(colour, D, K, d_f, refine):
    """The default preset's Eq. 1 result, display-encoded (``c^(1/2.2)``, 8-bit levels)."""
    from mpib_validate.runtime.compositor.composite import render_subapertures
    from mpib_validate.runtime.presets import PRESETS

    p = PRESETS["default"]
    mpi, _ = layers_from_passes(colour, D, K, dataclasses.replace(p.passes, refine=refine))
    out = render_subapertures(mpi, K, d_f, p.subapertures, p.composite)[..., :3]
    return np.round(np.clip(out, 0, 1) ** (1 / 2.2) * 255) / 255


@pytest.mark.parametrize("shift_px", [-1.5, -2.0])
def test_refinement_draws_no_sharp_line_into_the_blur(shift_px):
    """Focused on the far side (K = 60, the paper's), the skin blurs by 36 px. Moved
    across the predicted edge by its colour (dark, like the background), the temple's
    end became a line at the background's depth, in focus inside the blurred face
    (6 and 2 sharp remnants before the flips had to be wide). The unrefined result is
    the smooth reference."""
    from mpib_validate.metrics import sharp_remnants

    colour, pred = _face_and_temple(shift_px)
    K, d_f = 60.0, 0.2
    off = _refocused(colour, pred, K, d_f, "off")
    guided = _refocused(colour, pred, K, d_f, "guided")
    rem, must = sharp_remnants(guided, off, pred, K, d_f)
    assert must.sum() > 0.4 * must.size  # the skin and its outline must blur
    assert rem.sum() == 0, np.argwhere(rem)[:8].tolist()


def _cup_and_shadow(n=128, edge=64, gap=2, width=2, fat=4):
    """Cause (b) of the remnants that the refinement leaves on photographs: a bright
    near surface (a cup, d = 0.8, left of column ``edge``) before a red far one (a
    saucer, d = 0.3), with a dark shadow line ``width`` px wide on the saucer ``gap`` px
    from the cup's outline. The map is shaped like a network's: the near side fattened
    by ``fat`` px (the shadow line lies inside it), Gaussian blur 2 px, 4x down (block
    mean) and bilinear up. Returns (linear colour, predicted disparity, true
    disparity)."""
    from scipy import ndimage

    srgb = np.zeros((n, n, 3))
    srgb[:] = (0.75, 0.12, 0.08)
    srgb[:, :edge] = (0.95, 0.93, 0.88)
    srgb[:, edge + gap:edge + gap + width] = 0.1
    D = np.full((n, n), 0.3)
    D[:, :edge] = 0.8
    fattened = np.full((n, n), 0.3)
    fattened[:, :edge + fat] = 0.8
    low = ndimage.gaussian_filter(fattened, 2.0, mode="nearest").reshape(
        n // 4, 4, n // 4, 4).mean(axis=(1, 3))
    c = (np.arange(n) + 0.5) / 4 - 0.5
    gy, gx = np.meshgrid(c, c, indexing="ij")
    pred = ndimage.map_coordinates(low, [gy, gx], order=1, mode="nearest")
    return srgb ** 2.2, pred, D


def _cup_and_shadow_remnants(refine):
    """Sharp remnants of the cup-and-shadow scene focused on the cup (K = 60: the saucer
    blurs by 30 px) against its true-disparity render, and the must-blur region."""
    from mpib_validate.metrics import sharp_remnants

    colour, pred, D = _cup_and_shadow()
    K, d_f = 60.0, 0.8
    reference = _refocused(colour, D, K, d_f, "off")
    return sharp_remnants(_refocused(colour, pred, K, d_f, refine), reference, D, K, d_f)


def test_cup_and_shadow_is_a_fair_case():
    """The shadow line (columns 66-67) lies in the region that the true disparity blurs
    (its whole 5x5 window on the saucer), and the unrefined map leaves no remnant
    there: a line that the refinement keeps sharp is its own."""
    rem, must = _cup_and_shadow_remnants("off")
    assert must[:, 66:68].all()
    assert rem.sum() == 0


def test_refinement_keeps_no_background_strip_sharp():
    """The dark shadow line on the saucer lies inside the fattened map's near side. The
    colour may move the edge by 3 px only, and the guided filter's linear colour model
    fits the dark line to the cup's side (white and dark -> near, red -> far); kept at
    the cup's depth, it was sharp along the in-focus outline, where the saucer blurs by
    30 px (256 remnants: the 2 px line over 128 rows). The red gap and the line are
    closer in colour to the saucer than to the cup and touch it: the far-coloured strip
    goes to the far side (refine._far_coloured_strips), and a lens leaves none."""
    rem, must = _cup_and_shadow_remnants("guided")
    assert must.sum() > 0
    assert rem.sum() == 0, int(rem.sum())


def test_far_coloured_strips_move_the_background_and_not_the_object():
    """A grey card (columns < 40, with light stripes) before a background whose colour
    runs from blue to orange down the rows (its local mean is greyish), with the
    predicted near side 4 px too wide: the background columns on the near side go to
    the far side, but for the one next to the card, whose 3x3 colour mean is a third
    the card's (a mixed pixel, either side); no pixel of the card does."""
    from mpib_validate.runtime.layers import refine

    H, W = 64, 96
    t = np.linspace(0.0, 1.0, H)[:, None]
    colour = np.empty((H, W, 3))
    colour[:] = np.stack([0.05 + 0.6 * t, 0.1 + 0.1 * t, 0.6 - 0.55 * t], -1)  # blue -> orange
    colour[:, :40] = 0.16  # the grey card
    colour[::6, :40] = 0.5  # its light stripes
    colour *= 1.0 + 0.01 * np.random.default_rng(3).standard_normal(colour.shape)
    x = np.arange(W)[None, :] * np.ones((H, 1), int)
    m = x < 44
    band = (x >= 30) & (x < 56)
    out = refine._far_coloured_strips(colour, m.copy(), band, band, m)
    assert out[:, :40].all()  # the card
    assert not out[:, 41:].any()  # the strip moved, the far side as it was


def test_sharp_remnants_see_a_line_and_not_an_edge():
    """The measure counts a line one or two pixels wide kept in the must-blur region,
    not a step edge, and nothing where the reference holds the line too."""
    from mpib_validate.metrics import sharp_remnants, thin_structure

    smooth = np.tile(np.linspace(0.2, 0.6, 64)[None, :, None], (48, 1, 3))
    step = smooth.copy()
    step[:, 32:] += 0.3
    line = smooth.copy()
    line[20:22, 10:50] -= 0.1  # 2 px wide, 0.1 deep: 25/255
    assert thin_structure(step)[:, 1:-1].max() < 1e-12  # (the border column: one ramp step)
    D = np.full((48, 64), 0.9)  # A |d - d_f| = 20 px everywhere
    rem, must = sharp_remnants(line, smooth, D, 40.0, 0.4)
    assert must.all() and rem.sum() == 2 * 40
    assert not sharp_remnants(step, smooth, D, 40.0, 0.4)[0].any()
    assert not sharp_remnants(line, line, D, 40.0, 0.4)[0].any()  # the reference's own
    assert not sharp_remnants(line, smooth, D, 40.0, 0.85)[0].any()  # in focus: may be sharp
    # with two maps, the region must blur in both: where the second puts the line's rows
    # in focus (a refined map that moved an edge there), only the rest of it counts
    R = D.copy()
    R[15:25, 30:] = 0.4
    rem2, must2 = sharp_remnants(line, smooth, (D, R), 40.0, 0.4)
    assert not must2[20, 40] and must2[20, 10] and rem2.sum() == 2 * (30 - 2 - 10)


def test_sharp_edges_see_a_step_in_the_blur_and_not_a_blurred_one():
    """A step inside the must-blur region is a sharp edge; the same step blurred by a
    disk of 6 px is not, nor is a step from black seen through the sRGB curve, nor one
    that the reference has too, nor one in focus."""
    from scipy import ndimage

    from mpib_validate.metrics import sharp_edges, step_edges
    from mpib_validate.runtime.io.colour import linear_to_srgb

    y, x = np.mgrid[-6:7, -6:7]
    disk = ((x ** 2 + y ** 2) <= 36).astype(float)
    disk /= disk.sum()

    def blurred(lin):
        return np.stack([ndimage.convolve(lin[..., c], disk, mode="nearest")
                         for c in range(3)], -1)

    lin = np.full((48, 64, 3), 0.05)
    lin[:, 32:] = 0.4
    black = np.zeros((48, 64, 3))
    black[:, 32:] = 1.0
    step, smooth = linear_to_srgb(lin), linear_to_srgb(blurred(lin))
    assert step_edges(step).sum() == 2 * 48  # the two columns either side of the step
    assert not step_edges(smooth).any()
    assert not step_edges(linear_to_srgb(blurred(black))).any()
    D = np.full((48, 64), 0.9)  # A |d - d_f| = 20 px everywhere
    edges, must = sharp_edges(step, smooth, D, 40.0, 0.4)
    assert must.all() and edges.sum() == 2 * 48
    assert not sharp_edges(step, step, D, 40.0, 0.4)[0].any()  # the reference's own
    assert not sharp_edges(step, smooth, D, 40.0, 0.85)[0].any()  # in focus


def test_remnant_table_and_crops_on_one_shipped_photograph(tmp_path):
    """The photos suite's remnant part on scikit-image's cat (451x300): a row per focus,
    counts within their must-blur regions, the matting variant's columns, the crops
    figure with five columns (input, default, refinement off, matting, truth)."""
    from PIL import Image

    from mpib_validate.bench import remnants

    r = remnants.run(tmp_path, photos=("chelsea",))
    assert [row["focus"] for row in r["rows"]] == ["near", "far"]
    for row in r["rows"]:
        assert 0 <= row["remnants_input"] <= row["must_blur_input"] > 0
        assert 0 <= row["remnants_both"] <= row["must_blur_both"] <= row["must_blur_input"]
        assert 0 <= row["edges_both"] <= row["must_blur_both"]
        assert 0 <= row["edges_true"] <= row["must_blur_true"]
        assert 0 <= row["remnants_true"] <= row["must_blur_true"] > 0
        assert row["psnr_guided"] > 30 and row["psnr_off"] > 30 and row["psnr_matting"] > 30
        assert 0 <= row["remnants_both_matting"] <= row["must_blur_both"]
        assert 0 <= row["remnants_true_matting"] <= row["must_blur_true"]
        assert 0 <= row["remnants_true_overshoot"] <= row["must_blur_true"]
        assert row["psnr_overshoot"] > 30
    with Image.open(tmp_path / "remnants.png") as im:
        assert im.width == 3 * 5 * (48 + 4) and im.height == 3 * 2 * (48 + 4)
    md = "\n".join(remnants.markdown(r))
    assert "| chelsea (451x300) | near |" in md and "PSNR matting |" in md
    assert f"--map-overshoot {remnants.OVERSHOOT_PX}: remnants vs truth" in md


def test_shipped_photographs_meet_the_remnant_target():
    """The issue's target on every shipped photograph and focus: sharp remnants where
    the input map and the refined map both blur (the lines the default draws into the
    blur, counted against its output with the refinement off) at most 0.02 % of those
    pixels (``photos.REMNANT_TARGET``). Measured worst row 0.015 % (astronaut near);
    before the chain's inside and the fill's occluder test, astronaut near 0.040 %
    (far-colour patches through a surface crossing planes) and coffee far 0.021 % (the
    cup's rim filled in behind its silhouette)."""
    from mpib_validate.bench import remnants
    from mpib_validate.bench.photos import REMNANT_TARGET

    rows = [r for name in remnants.PHOTOS for r in remnants.photo_rows(name)]
    share = {(r["photo"], r["focus"]): r["remnants_both"] / r["must_blur_both"] for r in rows}
    assert max(share.values()) <= REMNANT_TARGET, share
    # these maps overshoot by 2 px: --map-overshoot 2 removes most of what is left against
    # the truth (measured 471 -> 72, 40.37 -> 40.84 dB mean PSNR over the eight rows; the
    # default's own far-coloured strip step takes part of what it once gained: 547 -> 68,
    # 40.28 -> 41.03 dB before it); half the measured gain must stay
    assert (sum(r["remnants_true_overshoot"] for r in rows)
            < sum(r["remnants_true"] for r in rows) / 2)
    assert (np.mean([r["psnr_overshoot"] for r in rows])
            > np.mean([r["psnr_guided"] for r in rows]) + 0.23)


def _scope_scene():
    """96x96: a far wall (d = 0.2, in focus) behind a wide near card (d = 0.6, columns
    < 30, a 1 px tip at (70, 30)), a near wire 1 px wide (column 60) and a 3 px wide bar
    (columns 80-82), and a
    point light (radiance 4) on the wall at (10, 45); A = 20 px, so everything near blurs
    by A |0.6 - 0.2| = 8 px."""
    D = np.full((96, 96), 0.2)
    D[:, :30] = 0.6
    D[:, 60] = 0.6
    D[:, 80:83] = 0.6
    D[70, 30] = 0.6  # a 1 px tip of the card's outline (a digitised corner leaves such)
    aif = np.full((96, 96, 3), 0.5)
    aif[10, 45] = 4.0
    return aif, D, 20.0, 0.2


def test_scope_exclusion_drops_a_wire_and_a_highlight_and_keeps_a_card_edge():
    """The re-scoped targets' exclusion: a 1 px wire and an HDR highlight are out, with
    the pixels their blur reaches (8 px from the wire; 2 px of rim + the 9x9 window's
    largest radius, 0 px for a light on the in-focus wall); a wide card's edge and a
    bar 3 px wide stay in, and so does a 1 px tip of the card's outline."""
    from mpib_validate.metrics import degraded_scope_exclusion, thin_disparity

    aif, D, A, d_f = _scope_scene()
    thin = thin_disparity(D, 1.0 / A)
    assert thin[:, 60].all() and thin.sum() == 96  # the wire, nothing else
    assert thin_disparity(D, 1.0 / A, min_pixels=1)[70, 30]  # the tip, a group of 1 px
    ex = degraded_scope_exclusion(aif, D, A, d_f)
    assert ex[:, 60].all() and ex[50, 52] and ex[50, 68]  # the wire and 8 px of its blur
    assert not ex[50, 50] and not ex[50, 70]  # 10 px away: the blur does not reach
    assert ex[10, 45] and ex[12, 45] and not ex[10, 49]  # the light, its rim
    assert not ex[40:90, 20:40].any()  # the card's edge (column 29 | 30), far from the rest
    assert not ex[40:90, 76:87].any()  # the 3 px bar: a structure a map can hold
    # the same wire at the far side's depth is no structure (no jump above 1 px of blur)
    D2 = D.copy()
    D2[:, 60] = 0.2 + 0.9 / A
    assert not thin_disparity(D2, 1.0 / A)[:, 60].any()


def test_scope_scores_and_targets_on_a_synthetic_pair():
    """``scope_scores``: the masked PSNR leaves the excluded pixels out (an error there
    changes the unmasked figure only) and a line kept in the blur is a remnant;
    ``scope_summary`` states each target met or missed and names the failing scenes."""
    from mpib_validate import metrics
    from mpib_validate.bench.photos import scope_scores, scope_summary

    aif, D, A, d_f = _scope_scene()
    d_f = 0.6  # the card in focus: the wall blurs by 8 px
    rng = np.random.default_rng(0)
    truth = 0.3 + 0.01 * rng.standard_normal((96, 96, 3))
    truth = np.clip(truth, 0, 1)
    from scipy import ndimage

    truth = ndimage.uniform_filter(truth, (9, 9, 1))  # smooth: what a blur leaves
    mask = np.ones((96, 96), bool)
    ex = metrics.degraded_scope_exclusion(aif, D, A, d_f)
    out = truth + 0.01
    out[:, 58:63] += 0.2  # a wrong wire's blur, inside the exclusion
    out[40, 38:52] -= 0.15  # a 1 px dark line on the blurred wall, kept sharp
    s = scope_scores(truth, out, mask, ex, D, A, d_f)
    keep = ~ex
    assert math.isclose(s["psnr_ob_scoped"], metrics.psnr(truth, np.clip(out, 0, 1), keep))
    assert s["psnr_ob_scoped"] > metrics.psnr(truth, np.clip(out, 0, 1), mask) + 10
    assert math.isclose(s["scoped_fraction"], keep.mean())
    assert s["remnants"] == 14 and s["must_blur"] > 0
    # the wire's hard sides and the line's flanks are steps the smooth truth does not have
    assert s["edges"] > 0
    assert scope_scores(truth, truth + 0.01, mask, ex, D, A, d_f)["edges"] == 0
    # the photographs' region: where both maps blur; against the truth and against the
    # unrefined output, which counts only a line that output does not have itself
    s2 = scope_scores(truth, out, mask, ex, D, A, d_f, (D, D), truth + 0.01)
    assert s2["remnants_maps"] == s2["remnants_maps_off"] == 14
    assert s2["must_blur_maps"] == s["must_blur"]
    assert scope_scores(truth, out, mask, ex, D, A, d_f, (D, D), out)["remnants_maps_off"] == 0
    R = D.copy()
    R[35:46] = d_f  # a refined map that puts the line's rows in focus: it may stay sharp
    s3 = scope_scores(truth, out, mask, ex, D, A, d_f, (D, R), truth + 0.01)
    assert s3["remnants_maps"] == s3["remnants_maps_off"] == 0
    assert 0 < s3["must_blur_maps"] < s["must_blur"]
    rows = [{"scene": sc, "method": m, "psnr_ob": ob, "psnr_ob_scoped": sv, "scoped_fraction": 0.5}
            for sc, vals in (("a", (30.0, 28.0, 23.0)), ("b", (30.0, 26.0, 23.0)))
            for m, sv, ob in zip(("exact", "guided", "node"), vals, (30.0, 20.0, 18.0))]
    sm = scope_summary(rows, "toy", "exact", "guided", "node")
    assert sm["scoped"]["within"] == -3.0 and sm["scoped"]["within_met"]
    assert sm["scoped"]["within_fails"] == {"b": -4.0}
    assert sm["scoped"]["over_node"] == 4.0 and sm["scoped"]["over_node_met"]
    assert sm["scoped"]["over_node_fails"] == {"b": 3.0}
    assert not sm["unmasked"]["within_met"] and not sm["unmasked"]["over_node_met"]
    assert "fails on b -4.0" in sm["headline"] and "missed" in sm["headline"]
    # the remnant summary's verdict in the photographs' region: at most 0.02 % of it
    from mpib_validate.bench.photos import remnant_summary

    def summary(n_off):
        rows = [{"scene": sc, "method": m, "remnants": 1, "must_blur": 500,
                 "must_blur_smooth": 400, "remnants_maps": 1, "must_blur_maps": 10000,
                 **({"remnants_maps_off": n_off} if m == "guided" else {})}
                for sc in ("a", "b") for m in ("exact", "guided")]
        return remnant_summary(rows, "toy", ("exact", "guided"), "guided", "exact")

    met, missed = summary(2), summary(3)
    assert met["methods"]["guided"]["remnants_maps_off"] == 4
    assert met["methods"]["guided"]["must_blur_maps"] == 20000
    assert ("4 (0.020 %) against the unrefined output (target 0.02 % over the suite: met; "
            "most in a, 2 of 10000 px)") in met["headline"]
    assert "6 (0.030 %)" in missed["headline"] and "missed" in missed["headline"]
    assert "exact-depth control 2 against the truth" in met["headline"]


def test_refine_cost_measures_the_whole_refocus_at_the_size_asked():
    """``refine_cost`` (the suite runs it at the issue's 2000x1333): the scene has the
    size asked and a largest blur radius of 60 px; the whole refocus is the refinement
    plus the rest."""
    from mpib_validate.bench import photos

    scene = photos.cost_scene(200, 134)
    lo, hi = scene.disparity_range()
    cam = scene.camera
    assert (cam.width, cam.height) == (200, 134)
    assert math.isclose(cam.blur_parameter * max(abs(hi - cam.focus_disparity),
                                                 abs(lo - cam.focus_disparity)), 60.0)
    c = photos.refine_cost((200, 134))
    assert (c["width"], c["height"]) == (200, 134)
    assert c["refine_cpu_s"] > 0 and c["rest_cpu_s"] > 0 and c["refine_photo_cpu_s"] > 0 < c["refine_photo_wall_s"]
    assert math.isclose(c["refocus_cpu_s"], c["refine_cpu_s"] + c["rest_cpu_s"])
    assert photos.COST_SIZE == (2000, 1333)


def test_no_light_patches_in_blurred_hair_with_a_network_resolution_map():
    """A photographer's flow on the astronaut (``remnants.light_patches``): her network-like
    map brought down to 128 px (8-bit), upsampled 4x as ``mpib refocus`` does, the
    paper's K = 30 and focus 232/255 (on the helmet she holds: her hair blurs by 4 to 6
    px, below the remnant measure's 6 px). The refined map puts a jump at the hair's
    outline, so the wall's hidden fill lies behind the hair, and in the same chain (the
    map is continuous). Before the chain kept its last slab apart, the fill showed
    through the hair where its disparity crosses two slabs: light patches along the
    map's contours, 14 % of the head's inside more than 10 display levels lighter than
    with the refinement off (79 levels at most). Measured now 0.5 % (22 levels at most),
    the rest within about 1.5 blur radii of the outline, where the refined edge is not
    the unrefined one. Required: ``photos.PATCH_TARGET`` (1 %)."""
    from mpib_validate.bench import remnants
    from mpib_validate.bench.photos import PATCH_TARGET

    lp = remnants.light_patches()
    assert lp["head_px"] > 10000, lp
    assert lp["share"] <= PATCH_TARGET, lp


def test_matting_variant_mattes_the_band_around_the_jumps_only():
    """The bench's matting variant (`bench.matting`): on a soft colour edge (a 5 px linear
    mix of a near red and a far blue surface, the disparity stepping in its middle) the
    closed-form matte gives the nearer layer the mix's alpha, and the layers away from
    the band are the default's."""
    import dataclasses

    from mpib_validate.bench.matting import BAND_PX, matte_sheets
    from mpib_validate.runtime.layers.mpi import Pixels, Sheet
    from mpib_validate.runtime.layers.passes import sheets_from_passes
    from mpib_validate.runtime.presets import PRESETS

    colour, D = _two_regions(edge=32)
    red, blue = np.array((0.6, 0.15, 0.1)), np.array((0.1, 0.2, 0.5))
    mix = np.clip((34.5 - np.arange(64)) / 5.0, 0.0, 1.0)  # 1 up to column 30, 0 from 35
    colour = (mix[None, :, None] * red + (1 - mix[None, :, None]) * blue) * np.ones((64, 1, 1))
    settings = PRESETS["default"].passes
    A = 40.0
    sheets = matte_sheets(colour, D, A, settings)
    default, _ = sheets_from_passes(colour, D, A, dataclasses.replace(settings, refine="off"))
    band = np.abs(np.arange(64) - 31.5) <= BAND_PX + 0.5  # columns within 4 px of the jump
    matte = sheets[-1]
    assert isinstance(matte, Pixels)
    cols = matte.index % 64
    assert set(np.unique(cols)) == set(np.flatnonzero(band))
    # the matte's alpha follows the mix. The matte's colour model is linear in display
    # values, the mix in linear ones: projected onto the line between the two display
    # colours, the mix bends by at most 0.033 between these two; 0.01 more for the
    # Laplacian's smoothing over its 3x3 windows (measured: 0.036 at most)
    for c in np.flatnonzero(band):
        a = matte.alpha[cols == c]
        assert abs(np.median(a) - mix[c]) < 0.045, (c, np.median(a), mix[c])
    # its nearer layer at the near surface's disparity, the farther at the far one's
    assert np.allclose(matte.disparity, 0.5)
    i = next(i for i, sh in enumerate(sheets) if isinstance(sh, Sheet))
    far = sheets[i - 1]  # the matte's background, just below the visible sheet
    assert np.array_equal(far.index, matte.index) and np.allclose(far.disparity, 0.1)
    # away from the band the visible sheet is the default's
    shown = sheets[i]
    shown_default = next(sh for sh in default if isinstance(sh, Sheet))
    assert np.array_equal(shown.alpha[:, ~band], shown_default.alpha[:, ~band])
    assert np.all(shown.alpha[:, band] == 0)


def test_side_smoothing_is_the_mean_over_each_sides_band_pixels_in_the_window():
    """Each band pixel's value becomes the mean of the values of the band pixels on its
    side within the (2s+1)^2 window, clipped at the image; pixels off the band keep
    theirs. Checked against the sum written out pixel by pixel."""
    from mpib_validate.runtime.layers import refine

    rng = np.random.default_rng(3)
    H, W, s = 23, 31, 2
    out = rng.random((H, W))
    band = rng.random((H, W)) < 0.4
    near = rng.random((H, W)) < 0.5
    want = out.copy()
    for y, x in zip(*np.nonzero(band)):
        win = (slice(max(0, y - s), y + s + 1), slice(max(0, x - s), x + s + 1))
        sel = band[win] & (near[win] == near[y, x])
        want[y, x] = out[win][sel].mean()
    got = refine._smooth_sides(out.copy(), band, near, s)
    # float32 window sums of values in [0, 1]: about 1e-7 each
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert np.abs(got - out)[band].max() > 0.1
    np.testing.assert_array_equal(got[~band], out[~band])
