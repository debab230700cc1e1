"""Tiled layers and tiled compositing: the same result as the dense, untiled path.

A smooth predicted-like disparity (mpib_validate.bench.photo) cuts into planes that are
thin bands across the frame: their layers are stored as 32 px tiles, and the compositor
blurs only the output tiles whose window holds content. Both must give the untiled,
dense result up to float32 rounding.
"""
from __future__ import annotations

import numpy as np
import pytest

from mpib_validate.bench.photosize import photo_passes
from mpib_validate.runtime.compositor import composite as C
from mpib_validate.runtime.layers import mpi as M
from mpib_validate.runtime.layers.passes import PassesSettings, depth_to_disparity, layers_from_passes


@pytest.fixture(scope="module")
def smooth_mpi():
    colour, depth, A, d_f = photo_passes(3, 768, 512, span_px=24.0)
    D = depth_to_disparity(depth)
    settings = PassesSettings(tolerance_px=0.5, split="additive", slab_px=2.0)
    mpi, _ = layers_from_passes(colour, D, A, settings)
    return mpi, A, d_f


def _dense_copy(mpi):
    return M.MPI(mpi.height, mpi.width, mpi.margin,
                 [M.Layer(l.disparity, l.rgba.copy(), l.y0, l.x0, l.group) for l in mpi.layers],
                 mpi.colour_max)


def test_tiled_layers_hold_exactly_the_dense_content(smooth_mpi):
    mpi, _, _ = smooth_mpi
    tiled = [l for l in mpi.layers if l.tiles is not None]
    assert tiled, "a smooth depth at this size should give band-like (tiled) layers"
    for l in tiled:
        keys, data = l.tiles
        assert data.nbytes <= M.TILED_FILL_MAX * 16 * l.shape[0] * l.shape[1] + 1
        dense = l.rgba
        # every non-zero pixel of the box lies in a stored tile, and read() of any
        # window agrees with slicing the dense box
        occ = l.occupancy(mpi.canvas_shape)
        ys, xs = np.nonzero((dense != 0).any(axis=2))
        assert occ[(ys + l.y0) // M.TILE_PX, (xs + l.x0) // M.TILE_PX].all()
        y0, y1, x0, x1 = l.box
        win = np.zeros((y1 - y0 + 10, x1 - x0 + 6, l.shape[2]), np.float32)
        l.read(win, y0 - 3, x0 - 2)
        np.testing.assert_array_equal(win[3:3 + y1 - y0, 2:2 + x1 - x0], dense)
        assert not win[:3].any() and not win[:, :2].any()


def test_adding_a_channel_equals_reading_it(smooth_mpi):
    """``Layer.add_channel`` (the chains' footprints) adds a tiled layer's stored tiles in
    one step: the same sum as reading the channel, for tiled and dense layers."""
    mpi, _, _ = smooth_mpi
    H, W = mpi.canvas_shape
    T = M.TILE_PX
    kinds = set()
    for l in mpi.layers:
        kinds.add(l.tiles is None)
        out = np.full((-(-H // T) * T, -(-W // T) * T), 0.25, np.float32)
        l.add_channel(out, 3)
        ref = np.zeros(out.shape, np.float32)
        y0, y1, x0, x1 = l.box
        l.read(ref[y0:y1, x0:x1], y0, x0, channel=3)
        np.testing.assert_array_equal(out, ref + np.float32(0.25))
        if l.tiles is not None:  # a tiled layer's tiles need the storage grid
            with pytest.raises(ValueError, match="storage tile"):
                l.add_channel(np.zeros((out.shape[0] + 1, out.shape[1]), np.float32), 3)
    assert kinds == {True, False}, kinds


def test_tiled_composite_matches_untiled_dense(smooth_mpi):
    """Tiles and batches change only the FFT sizes (float32, noise below 3e-8 of the
    peak, kernels.FFT_DTYPE) and the order of nothing else; the output is float32 after ~40 layers of float32
    "over" on values up to the HDR peak, so agreement to 1e-5 of the peak is float32
    rounding (ulp 6e-8, a few ulp per layer)."""
    mpi, A, d_f = smooth_mpi
    dense = _dense_copy(mpi)
    tiled_out = C.composite(mpi, A, d_f, C.CompositeSettings())
    plain_out = C.composite(dense, A, d_f, C.CompositeSettings(tiles=False))
    peak = float(np.abs(plain_out).max())
    np.testing.assert_allclose(tiled_out, plain_out, rtol=0, atol=1e-5 * peak)
    # and the tiled path did skip work: some layer blurred on tiles
    plans = []
    for l in mpi.layers:
        R = int(np.ceil(abs(A * (l.disparity - d_f)))) + 1
        box = (0, mpi.height, 0, mpi.width)
        plans.append(C._tile_plan(l, R, (2 * R + 1) ** 2, box, mpi.canvas_shape))
    assert any(p is not None for p in plans)


def test_reduced_resolution_blur_on_tiles_matches_the_whole_box(smooth_mpi):
    """The reduced path's coarse cells lie on the canvas grid, so blurring a band on
    output tiles reads the same cells as blurring its box: float32 rounding only (as
    above). reduce_above=4 sends every layer past 4 px of radius (up to 12 px here)
    through it, with s = 2 and 3; the phase of a 64 px tile on a grid of 3 px varies."""
    mpi, A, d_f = smooth_mpi
    settings = C.CompositeSettings(reduce_above=4.0)
    radii = [abs(A * (l.disparity - d_f)) for l in mpi.layers]
    assert max(radii) > 8.0  # s = 3 occurs
    tiled_out = C.composite(mpi, A, d_f, settings)
    plain_out = C.composite(_dense_copy(mpi), A, d_f,
                            C.CompositeSettings(reduce_above=4.0, tiles=False))
    peak = float(np.abs(plain_out).max())
    np.testing.assert_allclose(tiled_out, plain_out, rtol=0, atol=1e-5 * peak)
    plans = []
    for l, r in zip(mpi.layers, radii):
        if r > 4.0:
            parts = list(C._blur_parts(l, A * (l.disparity - d_f), (0, mpi.height, 0, mpi.width),
                                       mpi.canvas_shape, settings))
            plans.append(len(parts))
    assert max(plans) > 1  # some reduced layer was blurred on tiles


def test_reduced_blur_is_the_same_at_any_box_origin():
    """One coarse grid for the canvas: a pixel's reduced blur does not depend on where
    the box that computes it starts (boxes offset by 0..s-1 px agree to rounding)."""
    rng = np.random.default_rng(4)
    rgba = np.zeros((96, 96, 4), np.float32)
    rgba[30:60, 20:70, :3] = rng.random((30, 50, 3))
    rgba[30:60, 20:70, 3] = 1.0
    layer = M.Layer(0.5, rgba, 0, 0)
    settings = C.CompositeSettings(reduce_above=5.0, tiles=False)  # one part: the box
    rho = 14.0  # s = 3

    def blur(box):
        (part,) = C._blur_parts(layer, rho, box, (96, 96), settings)
        return part[1]

    ref = blur((10, 90, 5, 90))
    for dy in range(3):
        out = blur((10 + dy, 90, 5 + 2 * dy, 90))
        np.testing.assert_allclose(out, ref[dy:, 2 * dy:], rtol=0, atol=1e-6)


def test_tiled_composite_matches_with_replication_at_the_edges():
    """Content touching the frame edge is replicated past it; a tile near the edge
    must read the same replicated window as the whole box does."""
    rng = np.random.default_rng(1)
    H, W = 320, 448
    rgba = np.zeros((2, H, W, 4), np.float32)
    # a thin diagonal band that touches all four edges, and a full background
    yy, xx = np.mgrid[0:H, 0:W]
    band = np.abs(yy - 0.7 * xx) < 6
    rgba[1, band, :3] = rng.random((int(band.sum()), 3))
    rgba[1, band, 3] = 1.0
    rgba[1, 0, :40, 3] = 1.0  # on the top row, replicated upwards
    rgba[1, 0, :40, :3] = 0.5
    rgba[1, 310:, 430:, 3] = 1.0  # in the bottom right corner
    rgba[1, 310:, 430:, :3] = 2.0
    rgba[0, ..., :3] = rng.random((H, W, 3))
    rgba[0, ..., 3] = 1.0
    mpi = M.MPI.from_dense([0.1, 0.6], rgba)
    touched = np.flatnonzero((rgba[1] != 0).any(axis=2))
    far = mpi.layers[0]
    near = M.MPI(H, W)
    near.add(0.6, rgba[1], 0, 0, box=(0, H, 0, W), touched=touched)
    assert near.layers[0].tiles is not None
    tiled = M.MPI(H, W, 0, [far, near.layers[0]])
    # kernel radius 10 and 30 px on the band; k = 2: sub-aperture kernels (the best preset)
    for A, k in ((20.0, 1), (60.0, 1), (20.0, 2)):
        a = C.render_subapertures(tiled, A, 0.1, k)
        b = C.render_subapertures(_dense_copy(tiled), A, 0.1, k,
                                  C.CompositeSettings(tiles=False))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * float(np.abs(b).max()))


def test_photo_too_large_for_the_limit_is_refused_with_the_estimate(tmp_path):
    """A 640 x 427 smooth photograph needs about 0.1 GB (its layers stored as tiles);
    under a 0.05 GB limit `mpib refocus` refuses it before any work, in one line naming
    the option and the estimate, and writes nothing."""
    from clirun import one_line_error, run

    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    colour, depth, A, d_f = photo_passes(0, 640, 427)
    write_exr(tmp_path / "in.exr", {**channels_from_rgba(colour),
                                    "Depth.Z": depth.astype(np.float32)})
    line = one_line_error(*run("refocus", tmp_path / "in.exr", "-o", tmp_path / "out.exr",
                               "--blur-parameter", A, "--focus-disparity", d_f,
                               "--max-memory-gb", 0.05)[::2])
    assert "--max-memory-gb" in line and "estimated memory" in line and "planes" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.exr"]
