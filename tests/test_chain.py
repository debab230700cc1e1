"""Chains of slabs (``CompositeSettings.chain_px``): closer to the exact renderer than
Eq. 1 where Eq. 1 errs on an MPI built from passes, and Eq. 1 itself elsewhere.

The exact reference is :func:`mpib_validate.cards.mpi.render_exact` on the same passes' MPI with the
over split (additive groups have no card form; the bench's ``exact-mpi`` does the same).
Its own aperture noise is measured from two sample sets: a deterministic image ``X``
against one noisy render ``E`` has ``rms(X - E)^2 = bias^2 + s^2`` with ``s^2`` the
render's noise variance, half the pair's ``rms(E_0 - E_1)^2``; :func:`_bias` removes it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpib_validate.runtime import samples
from mpib_validate.cards.scene import Camera
from mpib_validate.runtime.compositor import composite as C
from mpib_validate.runtime.layers import mpi as M
from mpib_validate.cards import mpi as CM
from mpib_validate.runtime.layers.passes import layers_from_passes
from mpib_validate.runtime.presets import get_preset

DEFAULT = get_preset("default")
EQ1 = replace(DEFAULT.composite, chain_px=None)
CHAIN = DEFAULT.composite


def _bias(image, exact, exact2, window):
    """The rms difference of ``image`` from the exact render over ``window``, less the
    render's own noise, and that noise (``s``)."""
    d2 = float(((image - exact)[window] ** 2).mean())
    s2 = 0.5 * float(((exact - exact2)[window] ** 2).mean())
    return float(np.sqrt(max(d2 - s2, 0.0))), float(np.sqrt(s2))


def _compare(colour, disparity, A, d_f, window):
    """Bias of Eq. 1 and of chains from the exact render, and the exact's noise."""
    H, W = disparity.shape
    mpi, _ = layers_from_passes(colour, disparity, A, DEFAULT.passes)
    over, _ = layers_from_passes(colour, disparity, A, replace(DEFAULT.passes, split="linear"))
    cam = Camera(W, H, A, d_f)
    ex = CM.render_exact(over, cam, samples.stratified(1024, seed=0))[..., :3]
    ex2 = CM.render_exact(over, cam, samples.stratified(1024, seed=1))[..., :3]
    eq1, s = _bias(C.composite(mpi, A, d_f, EQ1)[..., :3], ex, ex2, window)
    chain, _ = _bias(C.composite(mpi, A, d_f, CHAIN)[..., :3], ex, ex2, window)
    return eq1, chain, s


def test_holes_behind_an_occluder_are_filled_from_the_farther_surface():
    """A box at d = 0.15 before sky at infinity, focus near (d_f = 0.5, A = 32: radii
    11.2 and 16 px). The fill behind the box reaches A (0.15 - 0) = 4.8 px, so the sky's
    blur next to the box's silhouette is partly empty; Eq. 1's final division hands that
    share to the box too (a halo of its colour), while the rays that miss the box see
    sky. Measured (64x64, 1,024 samples): bias from the exact render 0.0080 (Eq. 1)
    against 0.0010 (chains), the exact's noise 0.0009. Required: the case is real (Eq. 1
    off by more than 4 noise) and chains remove at least 3/4 of Eq. 1's bias."""
    H = W = 64
    colour = np.zeros((H, W, 3), np.float32)
    colour[:] = [0.3, 0.5, 0.9]
    D = np.zeros((H, W))
    D[20:44, 20:44] = 0.15
    colour[20:44, 20:44] = [0.9, 0.5, 0.2]
    eq1, chain, s = _compare(colour, D, 32.0, 0.5, (slice(None), slice(None)))
    assert eq1 > 4 * s, (eq1, chain, s)
    assert chain < 0.25 * eq1, (eq1, chain, s)


def test_seams_between_slabs_of_one_surface_do_not_crack():
    """A surface receding across the frame (disparity 0.25 to 0.45 along x, stripes),
    focus at 0.8 with A = 16 (radii 8.8 to 5.6 px): it is cut into slabs 2 px of radius
    apart, and at each seam Eq. 1 lays the two slabs' complementary blurred edges with
    "over", whose coverage ``1 - (1 - a)(1 - (1 - a))`` dips to 3/4; nothing lies behind,
    so the division restores the brightness but mixes the wrong share of each side. The
    disjoint over sums them there. Nothing is farther than the surface, so no hole is
    involved. Measured (64x96, interior 9 px from the edges, 1,024 samples): bias 0.0059
    (Eq. 1) against 0.0014 (chains, at the noise: the estimate cannot resolve less),
    noise 0.0014. Required: Eq. 1 off by more than 2
    noise, chains at most half of Eq. 1's bias."""
    H, W = 64, 96
    colour = np.zeros((H, W, 3), np.float32) + np.float32([0.9, 0.8, 0.3])
    colour[:, ::8] = [0.2, 0.3, 0.6]
    D = np.zeros((H, W)) + 0.25 + 0.2 * np.arange(W) / W
    b = 9  # farther than the largest radius (8.8 px) from the frame's edges
    eq1, chain, s = _compare(colour, D, 16.0, 0.8, (slice(b, H - b), slice(b, W - b)))
    assert eq1 > 2 * s, (eq1, chain, s)
    assert chain < 0.5 * eq1, (eq1, chain, s)


def test_where_eq1_has_no_hole_or_seam_chains_are_eq1():
    """An opaque background with nothing missing (no fill needed: a foreground over the
    whole background) and a foreground far from it in depth: the renormalisation divides
    by 1 and the slabs form no chain, so the result is Eq. 1's up to float32 rounding
    (1e-6 of the colour peak, 1.0 here)."""
    H = W = 48
    rgba = np.zeros((2, H, W, 4), np.float32)
    rng = np.random.default_rng(3)
    rgba[0, ..., :3] = rng.random((H, W, 3))
    rgba[0, ..., 3] = 1.0
    rgba[1, 12:30, 14:36, :3] = [0.8, 0.2, 0.1]
    rgba[1, 12:30, 14:36, 3] = 1.0
    mpi = M.MPI.from_dense([0.1, 0.6], rgba)
    for l, g in zip(mpi.layers, (0, 1)):  # two additive slabs of one layer each
        l.group = g
    for d_f in (0.1, 0.35, 0.6, 0.9):
        a = C.composite(mpi, 20.0, d_f, EQ1)
        b = C.composite(mpi, 20.0, d_f, CHAIN)
        np.testing.assert_allclose(b[..., :3], a[..., :3], rtol=0, atol=1e-6)


def test_chains_ignore_ungrouped_layers():
    """``chain_px`` acts on additive groups only: layers of the over split (no group)
    are composited by Eq. 1, bit for bit."""
    H, W = 40, 56
    colour = np.zeros((H, W, 3), np.float32) + 0.4
    D = np.zeros((H, W))
    D[10:30, 12:40] = 0.3
    colour[10:30, 12:40] = [0.9, 0.3, 0.1]
    mpi, _ = layers_from_passes(colour, D, 24.0, replace(DEFAULT.passes, split="linear"))
    assert all(l.group is None for l in mpi.layers)
    np.testing.assert_array_equal(C.composite(mpi, 24.0, 0.6, CHAIN),
                                  C.composite(mpi, 24.0, 0.6, EQ1))


@pytest.mark.parametrize("k", [1, 2])
def test_chains_on_tiles_match_the_dense_untiled_path(k):
    """Chains work on the canvas tiles each slab wrote; the tiled layers and tiled blurs
    (a photo-like smooth depth, band-shaped layers) must give the dense untiled result
    up to float32 rounding, as Eq. 1 does (tests/test_tiles.py: 1e-5 of the peak; the
    renormalisation divides by a coverage of at least 1e-3 where it changes the sum,
    but the output is the ratio of colour to normaliser, which rounding moves alike)."""
    from mpib_validate.bench.photosize import photo_passes
    from mpib_validate.runtime.layers.passes import depth_to_disparity

    colour, depth, A, d_f = photo_passes(3, 768, 512, span_px=24.0)
    mpi, _ = layers_from_passes(colour, depth_to_disparity(depth), A, DEFAULT.passes)
    assert any(l.tiles is not None for l in mpi.layers)
    dense = M.MPI(mpi.height, mpi.width, mpi.margin,
                  [M.Layer(l.disparity, l.rgba.copy(), l.y0, l.x0, l.group) for l in mpi.layers],
                  mpi.colour_max)
    a = C.render_subapertures(mpi, A, d_f, k, CHAIN)
    b = C.render_subapertures(dense, A, d_f, k, replace(CHAIN, tiles=False))
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * float(np.abs(b).max()))


def test_nothing_farther_shows_through_a_surface_crossing_planes():
    """A large grey surface at d = 0.70 with a noisy disparity (1 % rms, smooth over 2
    px, so it crosses planes and slabs) before a blue background at 0.2, focus 0.92,
    A = 32 (radii about 8 and 23 px). Beyond its own blur radius inside the surface only
    the surface can be seen, but the chain's coverage falls short there by up to about
    0.10 (a pixel's shares are blurred with different radii), which "over" the farther
    composite filled with blue: measured up to 0.10 before the chain's inside was
    known, up to 0.075 where the farther composite was only the tail of the
    background's blur (n between 1/1000 and 1/20 of its rays). Required: no blue deeper
    than the chain's ramp (``R + 1`` px from an uncovered pixel, ``R`` its largest
    blur reach), up to float32 rounding; in the ramp, a tail adds at most
    ``deficit * n / floor`` (0.10 x 0.05 / 0.25 = 0.02)."""
    from scipy import ndimage

    H = W = 160
    A, d_f = 32.0, 0.92
    near = np.zeros((H, W), bool)
    near[16:144, 16:144] = True
    noise = ndimage.gaussian_filter(np.random.default_rng(0).standard_normal((H, W)), 2.0)
    D = np.where(near, 0.70 + 0.01 * noise / noise.std(), 0.2)
    colour = np.where(near[..., None], np.float32([0.5, 0.5, 0.5]), np.float32([0.1, 0.2, 0.9]))
    mpi, _ = layers_from_passes(colour, D, A, DEFAULT.passes)
    far = M.MPI(H, W, 0, [l for l in mpi.layers if l.disparity < 0.5])
    n_far = C.composite(far, A, d_f, CHAIN)[..., 3]
    r_near = A * (d_f - D[near].min())
    inside = ndimage.binary_erosion(near, iterations=int(np.ceil(r_near)) + 1)
    R = max(C._reach(A * (l.disparity - d_f), CHAIN) for l in mpi.layers if l.disparity > 0.5)
    deep = ndimage.binary_erosion(near, iterations=int(np.ceil(R + 1)))
    assert deep.sum() > 1000, deep.sum()
    blue = (C.composite(mpi, A, d_f, CHAIN)[..., 2] - 0.5) / (0.9 - 0.5)
    assert np.abs(blue[deep]).max() < 1e-5, np.abs(blue[deep]).max()


def _surface_beside_a_ramp(ramp_from: float):
    """``(A, d_f, near, D, mpi)``, 160x200, A = 32, focus 0.92: a grey surface (``near``)
    at d = 0.70 with a noisy disparity (1 % rms, smooth over 2 px) before a blue
    background at 0.2, and a red ramp at the picture's left edge (12 px wide) whose
    disparity goes from ``ramp_from`` to 0.75 down the picture; ``mpi`` built by the
    default preset's passes."""
    from scipy import ndimage

    H, W = 160, 200
    A, d_f = 32.0, 0.92
    near = np.zeros((H, W), bool)
    near[16:144, 56:184] = True
    noise = ndimage.gaussian_filter(np.random.default_rng(0).standard_normal((H, W)), 2.0)
    D = np.where(near, 0.70 + 0.01 * noise / noise.std(), 0.2)
    ramp = np.zeros((H, W), bool)
    ramp[:, :12] = True
    D = np.where(ramp, np.linspace(ramp_from, 0.75, H)[:, None], D)
    colour = np.where(near[..., None], np.float32([0.5, 0.5, 0.5]), np.float32([0.1, 0.2, 0.9]))
    colour = np.where(ramp[..., None], np.float32([0.9, 0.2, 0.1]), colour)
    mpi, _ = layers_from_passes(colour, D, A, DEFAULT.passes)
    return A, d_f, near, D, mpi


def test_a_fill_in_the_same_chain_shows_only_through_the_shortfall():
    """The surface of the test above, now in one chain with its background: a ramp at
    the picture's edge holds every disparity in between (as a photograph's continuous
    map does), so the blue fill behind the surface's silhouette lies in the chain, under
    the surface's slabs. Where the noisy surface crosses two slabs, the disjoint over
    of the nearer slab on all before it shrank the farther slab and the fill alike, and
    the fill showed through the surface far inside its silhouette (blue up to 0.29 of
    the colour; light patches in blurred hair on a photograph). Required: beyond the
    surface's own blur radius inside it, blue no more than the shortfall of a surface
    crossing planes (up to about 0.10, see above); deeper than the two slabs' ramp
    (``R + 1`` px from a pixel they do not cover opaquely, the exact distance), none
    (0.076 before that rule)."""
    from scipy import ndimage

    A, d_f, near, D, mpi = _surface_beside_a_ramp(0.2)
    r_near = A * (d_f - D[near].min())
    inside = ndimage.binary_erosion(near, iterations=int(np.ceil(r_near)) + 2)
    blue = (C.composite(mpi, A, d_f, CHAIN)[..., 2] - 0.5) / (0.9 - 0.5)
    assert blue[inside].max() < 0.10, blue[inside].max()
    R = max(C._reach(A * (l.disparity - d_f), CHAIN) for l in mpi.layers if l.disparity > 0.5)
    deep = ndimage.distance_transform_edt(near) > R + 1
    assert deep.sum() > 1000, deep.sum()
    assert np.abs(blue[deep]).max() < 1e-5, np.abs(blue[deep]).max()


def test_a_surface_hides_what_lies_behind_beyond_its_own_blur_radius():
    """The surface of the tests above (grey, d = 0.70 with a noisy disparity, radius
    about 7 px) before a blue background at 0.2, in a chain that also holds a red ramp
    from 0.5 to 0.75 at the picture's left edge (radius up to 13.4 px there): the
    chain's largest blur reach is the ramp's, twice the surface's. A thin lens sees
    past the surface only within the surface's own blur radius of its silhouette; there
    the farther composite (the blue) fills the chain's shortfall. Deeper, blue can show
    only through the shortfall of a surface crossing planes (up to about 0.10 of the
    colour, see above), which is no view of what lies behind. Required: no blue deeper
    than the surface's own reach plus one pixel, up to float32 rounding (a ramp from the
    chain's largest reach instead let blue through between 8 and 15 px inside)."""
    from scipy import ndimage

    A, d_f, near, D, mpi = _surface_beside_a_ramp(0.5)
    own = max(C._reach(A * (l.disparity - d_f), CHAIN) for l in mpi.layers
              if l.disparity > D[near].min() - 0.04)
    largest = max(C._reach(A * (l.disparity - d_f), CHAIN) for l in mpi.layers
                  if l.disparity > 0.45)
    assert largest > own + 4, (largest, own)
    deep = ndimage.binary_erosion(near, iterations=int(np.ceil(own + 1)))
    blue = (C.composite(mpi, A, d_f, CHAIN)[..., 2] - 0.5) / (0.9 - 0.5)
    assert np.abs(blue[deep]).max() < 1e-5, np.abs(blue[deep]).max()


@pytest.mark.parametrize("seed", range(6))
def test_deep_inside_is_the_ramp_of_the_exact_distance(seed, monkeypatch):
    """The chain's depth weight, computed exactly only on the ring that cells leave
    undecided, equals the ramp of scipy's Euclidean distance transform everywhere, up to
    float32 rounding: on smooth blobs, scattered holes and solid frames, for radii from
    below a cell's diagonal to several cells; the ring in one part or in many."""
    from scipy import ndimage

    if seed % 2:
        monkeypatch.setattr(C, "_RING_CELLS_AT_ONCE", 5)
    rng = np.random.default_rng(seed)
    for _ in range(8):
        H, W = 4 * int(rng.integers(3, 50)), 4 * int(rng.integers(3, 50))
        kind = rng.integers(4)
        if kind == 0:
            solid = rng.random((H, W)) > 0.02  # scattered holes
        elif kind == 1:
            solid = np.ones((H, W), bool)
        else:
            size = int(rng.integers(1, 12))
            solid = ndimage.uniform_filter(rng.random((H, W)), size) > rng.uniform(0.3, 0.7)
        R = int(rng.integers(1, 30))
        got = np.broadcast_to(np.asarray(C._deep_inside(solid, R), np.float64), (H, W))
        want = (np.clip(ndimage.distance_transform_edt(solid) - R, 0.0, 1.0)
                if not solid.all() else np.ones((H, W)))
        np.testing.assert_allclose(got, want, atol=2e-6)
