"""layers_from_sheets against a plain per-plane reference: the same layers, to the bit.

The builder groups each share of a pixel by plane with a counting sort, reads the colour
plane by plane and writes each layer straight into its own box or tiles. The reference
below does what the docstring says in the most direct way: per layer, a canvas-sized
float32 plane, every sheet's share laid "over" it far to near
(``L = L (1 - cover) + premult``), then cropped to the content's box. With the additive
split the layers of a slab are summed by the compositor, so there a share is weighted
by the transmission ``prod (1 - alpha_t)`` of the nearer sheets ``t`` that have a share
anywhere in the same slab at that pixel (float32, nearest first), and the layer is the
sum of the weighted shares.
"""
from __future__ import annotations

import numpy as np
import pytest

from mpib_validate.runtime.layers import mpi as M


def _shares(sh, planes, split, snap, wc):
    """[(canvas index, share alpha, cover, colour, role)] of one sheet, as defined by
    split_between_planes (additive roles: 0 on a plane, 1 far and 2 near share)."""
    px = sh.pixels(wc) if isinstance(sh, M.Sheet) else sh
    d, al = np.asarray(px.disparity, float), np.asarray(px.alpha, float)
    col, where = np.asarray(px.colour, float), np.asarray(px.index)
    n = len(planes)
    if split == "nearest":
        return [(np.abs(d[:, None] - planes).argmin(axis=1), al, al, 0)], col, where
    idx, lo, hi = M.split_between_planes(d, al, planes, snap, additive=split == "additive")
    up = np.minimum(idx + 1, n - 1)
    if split == "linear":
        return [(idx, lo, lo, 0), (up, hi, hi, 1)], col, where
    inside = (lo > 0) & (hi > 0)
    return [(idx, np.where(inside, 0, lo), al, 0), (up, np.where(inside, 0, hi), al, 0),
            (idx, np.where(inside, lo, 0), al, 1), (up, np.where(inside, hi, 0), al, 2)], \
        col, where


def _reference(sheets, planes, H, W, margin, split, snap, slab):
    hc, wc = H + 2 * margin, W + 2 * margin
    shares = []
    for sh in sheets:
        parts, col, where = _shares(sh, planes, split, snap, wc)
        shares += [(p, a, cov, col, where, role) for p, a, cov, role in parts]
    K = shares[0][3].shape[1]
    slab_of = M.slab_of_groups(planes, slab) if split == "additive" else {}
    group_of = {0: lambda p: 2 * p, 1: lambda p: 2 * p + 1, 2: lambda p: 2 * p - 1}
    # additive: the transmission of the nearer sheets' content in each slab, per sheet
    n_sheets = len(sheets)
    trans = {}
    if split == "additive":
        sheet_of = [k for k, sh in enumerate(sheets)
                    for _ in _shares(sh, planes, split, snap, wc)[0]]
        for sl in set(slab_of.values()):
            has = np.zeros((n_sheets, hc * wc), bool)
            alpha = np.zeros((n_sheets, hc * wc))
            for k, (pl, a, cov, col, where, role) in zip(sheet_of, shares):
                g = np.array([{0: 2 * q, 1: 2 * q + 1, 2: 2 * q - 1}[role] for q in pl])
                m = (a > 0) & np.array([slab_of.get(int(x)) == sl for x in g], bool)
                has[k, where[m]] = True
                alpha[k, where[m]] = cov[m]
            t = np.ones(hc * wc, np.float32)
            for k in range(n_sheets - 1, -1, -1):
                trans[sl, k] = t.copy()
                t[has[k]] *= (1.0 - alpha[k, has[k]]).astype(np.float32)
    out = []
    for p, d in enumerate(planes):
        if split == "additive":
            sets = {}
            for role in (1, 0, 2):
                if group_of[role](p) in slab_of:
                    sets.setdefault(slab_of[group_of[role](p)], []).append(role)
            role_sets = [(tuple(r), s) for s, r in sets.items()]
        else:
            role_sets = [((0, 1), None)]
        for roles, sl in role_sets:
            plane = np.zeros((hc * wc, K + 1), np.float32)
            hit = np.zeros(hc * wc, bool)
            for k, (pl, a, cov, col, where, role) in zip(
                    sheet_of if split == "additive" else [None] * len(shares), shares):
                m = (pl == p) & (a > 0)
                if role not in roles or not m.any():
                    continue
                premult = np.concatenate([col[m, :3] * a[m, None], a[m, None],
                                          col[m, 3:] * a[m, None]], axis=1)
                if split == "additive":
                    premult = premult * trans[sl, k][where[m]].astype(np.float64)[:, None]
                    plane[where[m]] = plane[where[m]] + premult.astype(np.float32)
                else:
                    plane[where[m]] = (plane[where[m]]
                                       * (1.0 - cov[m, None]).astype(np.float32)
                                       + premult.astype(np.float32))
                hit[where[m]] = True
            if hit.any():
                r, c = np.divmod(np.flatnonzero(hit), wc)
                box = (r.min(), r.max() + 1, c.min(), c.max() + 1)
                img = plane.reshape(hc, wc, K + 1)[box[0]:box[1], box[2]:box[3]]
                out.append((sl, float(d), box, img))
    out.sort(key=lambda t: (-1 if t[0] is None else t[0], t[1]))
    return out


@pytest.mark.parametrize("split, slab", [("linear", 0.0), ("nearest", 0.0),
                                         ("additive", 0.0), ("additive", 0.05)])
@pytest.mark.parametrize("channels", [3, 4])
def test_layers_equal_the_plain_reference(split, slab, channels):
    rng = np.random.default_rng(7)
    H, W, margin = 250, 300, 3
    hc, wc = H + 2 * margin, W + 2 * margin
    # a smooth ramp over the frame (band-like planes), a patch with an offset origin,
    # and sparse pixels (with repeats of the ramp's pixels) in front
    ramp_d = np.linspace(0.1, 0.6, hc)[:, None] * np.ones((1, wc))
    ramp_c = rng.uniform(0, 2, (hc, wc, channels)).astype(np.float32)
    ramp_a = np.ones((hc, wc))
    ramp_a[:5] = 0.0
    patch_d = rng.uniform(0.2, 0.5, (20, 30))
    patch = M.Sheet((10, 40), rng.uniform(0, 1, (20, 30, channels)),
                    rng.uniform(0, 1, (20, 30)) * (rng.random((20, 30)) > 0.2), patch_d)
    idx = rng.choice(hc * wc, 300, replace=False)
    pixels = M.Pixels(idx, rng.uniform(0, 3, (300, channels)), rng.uniform(0.1, 1, 300),
                      rng.uniform(0.05, 0.65, 300))
    sheets = [M.Sheet((0, 0), ramp_c, ramp_a, ramp_d), patch, pixels]
    planes = M.adaptive_planes([(0.05, 0.65)], 40.0, 0.5)
    snap = 0.02 / 40.0
    got = M.layers_from_sheets(sheets, planes, H, W, margin, split, snap, slab)
    want = _reference(sheets, planes, H, W, margin, split, snap, slab)
    assert any(l.tiles is not None for l in got.layers)  # the ramp's bands are tiled
    assert len(got.layers) == len(want)
    for layer, (sl, d, box, img) in zip(got.layers, want):
        assert (layer.group, layer.disparity, layer.box) == (sl, d, tuple(int(v) for v in box))
        assert layer.rgba.tobytes() == img.tobytes()
    colours = np.concatenate([ramp_c.reshape(-1, channels)[ramp_a.ravel() > 0],
                              patch.colour[patch.alpha > 0], pixels.colour])
    np.testing.assert_array_equal(got.colour_max, colours.max(axis=0).astype(np.float32))


def test_a_nearer_sheet_hides_a_farther_one_on_every_plane_of_its_slab():
    """Additive split: the layers of a slab are summed, so an opaque pixel of a nearer
    sheet on one plane of the slab must hide a farther sheet's pixel on another plane of
    the same slab. Two opaque pixels (far red on plane 0, near blue on plane 2, one
    slab): the slab's layers sum to coverage 1 and blue (the plain per-plane "over" gave
    coverage 2, half red after Eq. 1's division); a nearer alpha of 1/4 leaves 3/4 of the
    red. Sheets in different slabs are left to Eq. 1's "over" between slabs."""
    planes = np.array([0.1, 0.2, 0.3])

    def slab_sums(near_alpha, slab):
        far = M.Pixels(np.array([5]), np.array([[1.0, 0.0, 0.0]]), np.array([1.0]),
                       np.array([0.1]))
        near = M.Pixels(np.array([5]), np.array([[0.0, 0.0, 1.0]]), np.array([near_alpha]),
                        np.array([0.3]))
        mpi = M.layers_from_sheets([far, near], planes, 1, 10, split="additive", slab=slab)
        sums = {}
        for layer in mpi.layers:
            v = layer.rgba[0, 5 - layer.x0] if layer.box[2] <= 5 < layer.box[3] else 0
            sums[layer.group] = sums.get(layer.group, 0) + np.asarray(v, np.float64)
        return sums

    one = slab_sums(1.0, slab=1.0)  # every group in one slab
    assert list(one) == [0]
    np.testing.assert_allclose(one[0], [0, 0, 1, 1], atol=1e-7)
    quarter = slab_sums(0.25, slab=1.0)
    np.testing.assert_allclose(quarter[0], [0.75, 0, 0.25, 1], atol=1e-7)
    apart = slab_sums(1.0, slab=0.0)  # each group its own slab: both kept whole
    assert len(apart) == 2
    for v in apart.values():
        assert v[3] == 1.0


def test_each_slab_covers_a_pixel_at_most_once():
    """Whatever the sheets (a ramp, an offset patch, sparse pixels over them), the summed
    alpha of a slab's layers at any pixel is at most 1 (float32 rounding aside)."""
    rng = np.random.default_rng(3)
    H, W = 60, 80
    ramp = M.Sheet((0, 0), rng.uniform(0, 1, (H, W, 3)), np.ones((H, W)),
                   np.linspace(0.1, 0.6, H)[:, None] * np.ones((1, W)))
    patch = M.Sheet((10, 20), rng.uniform(0, 1, (20, 30, 3)), rng.uniform(0.2, 1, (20, 30)),
                    rng.uniform(0.2, 0.5, (20, 30)))
    idx = rng.choice(H * W, 500, replace=False)
    pixels = M.Pixels(idx, rng.uniform(0, 1, (500, 3)), rng.uniform(0.1, 1, 500),
                      rng.uniform(0.05, 0.65, 500))
    planes = M.adaptive_planes([(0.05, 0.65)], 40.0, 0.5)
    mpi = M.layers_from_sheets([ramp, patch, pixels], planes, H, W, split="additive",
                               slab=2.0 / 40.0)
    cover = {}
    for layer in mpi.layers:
        y0, y1, x0, x1 = layer.box
        c = cover.setdefault(layer.group, np.zeros((H, W)))
        c[y0:y1, x0:x1] += layer.rgba[..., 3]
    assert max(c.max() for c in cover.values()) <= 1.0 + 1e-5
