"""Tests for mpib_validate.cards.textures: shapes, ranges, determinism, mask properties, HDR spots."""

import socket

import numpy as np
import pytest
from scipy import ndimage
from skimage import measure

from mpib_validate.cards import textures as T

H, W = 72, 96  # non-square on purpose, to catch swapped axes
SEEDS = (0, 1, 2)


def rng(seed=0):
    return np.random.default_rng(seed)


def check_image(img, h=H, w=W, hi=1.0):
    assert img.shape == (h, w, 3)
    assert img.dtype == np.float32 and img.flags.c_contiguous
    assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= hi


def check_mask(a, h=H, w=W):
    assert a.shape == (h, w)
    assert a.dtype == np.float32 and a.flags.c_contiguous
    assert np.isfinite(a).all() and a.min() >= 0.0 and a.max() <= 1.0


# --------------------------------------------------------------------------- sRGB
def test_srgb_to_linear():
    v = T.srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0]))
    assert v[0] == 0.0 and v[3] == 1.0
    assert v[1] == pytest.approx(0.04045 / 12.92)
    assert v[2] == pytest.approx(0.21404, abs=1e-5)
    x = np.linspace(0, 1, 101)
    assert np.all(np.diff(T.srgb_to_linear(x)) > 0)


# --------------------------------------------------------------------------- images
def test_shipped_images_load_offline(monkeypatch):
    def no_network(*args, **kwargs):
        raise OSError("network disabled in test")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    T._load_shipped.cache_clear()
    for name in T.SHIPPED_IMAGES:
        check_image(T.shipped_image(name, 24, 40), 24, 40)


def test_shipped_image_crop_and_determinism():
    img = T.shipped_image("astronaut", H, W)
    check_image(img)
    assert np.array_equal(img, T.shipped_image("astronaut", H, W))  # no rng: centred crop
    a = T.shipped_image("coffee", H, W, rng(3))
    b = T.shipped_image("coffee", H, W, rng(3))
    assert a.tobytes() == b.tobytes()
    assert not np.array_equal(a, T.shipped_image("coffee", H, W, rng(4)))
    grey = T.shipped_image("camera", 32, 32, rng(0))
    assert np.array_equal(grey[..., 0], grey[..., 1]) and np.array_equal(grey[..., 0], grey[..., 2])


def test_shipped_image_is_linearised():
    # At native size (no crop, no resampling) the texture is exactly the decoded sRGB data.
    src = T._load_shipped("camera")
    img = T.shipped_image("camera", src.shape[0], src.shape[1])
    assert np.allclose(img[..., 0], T.srgb_to_linear(src[..., 0] / 255.0), atol=1e-6)


def test_shipped_image_unknown_name():
    with pytest.raises(ValueError, match="astronaut"):
        T.shipped_image("eagle", 8, 8)


# --------------------------------------------------------------------------- procedural
@pytest.mark.parametrize("kind", T.PROCEDURAL_TEXTURES)
def test_procedural_texture(kind):
    for seed in SEEDS:
        a = T.procedural_texture(kind, H, W, rng(seed))
        check_image(a)
        assert a.tobytes() == T.procedural_texture(kind, H, W, rng(seed)).tobytes()
        assert a.std() > 1e-3  # not a flat image
    assert not np.array_equal(a, T.procedural_texture(kind, H, W, rng(99)))


def test_procedural_edges_antialiased():
    a = T.procedural_texture("checker", H, W, rng(0))
    n_colours = len(np.unique(a.reshape(-1, 3), axis=0))
    assert n_colours > 2  # mixed edge pixels, not just the two colours


def test_random_texture():
    for seed in range(8):
        t = T.random_texture(H, W, rng(seed))
        check_image(t)
        assert t.tobytes() == T.random_texture(H, W, rng(seed)).tobytes()


def test_unknown_texture_kind():
    with pytest.raises(ValueError, match="checker"):
        T.procedural_texture("plaid", 8, 8, rng())


# --------------------------------------------------------------------------- masks
def fractional(a):
    return (a > 0) & (a < 1)


@pytest.mark.parametrize("kind", T.MASK_KINDS)
def test_mask_basic(kind):
    for seed in SEEDS:
        a = T.alpha_mask(kind, H, W, rng(seed))
        check_mask(a)
        assert a.tobytes() == T.alpha_mask(kind, H, W, rng(seed)).tobytes()
        # inside the box with a margin, roughly centred
        mg = int(0.05 * min(H, W))
        assert a[:mg].max() == 0 and a[-mg:].max() == 0
        assert a[:, :mg].max() == 0 and a[:, -mg:].max() == 0
        cy, cx = ndimage.center_of_mass(a)
        assert abs(cy - H / 2) < 0.25 * H and abs(cx - W / 2) < 0.25 * W
        assert (a == 0).mean() > 0.3
        assert fractional(a).sum() >= 10
        if kind != "soft":
            assert (a == 1).any()


@pytest.mark.parametrize("kind", ["disk", "ellipse", "rectangle", "blob", "horse"])
def test_solid_masks_antialiased_and_solid(kind):
    for seed in SEEDS:
        a = T.alpha_mask(kind, H, W, rng(seed))
        assert (a == 1).sum() > 0.03 * a.size
        assert measure.label(a > 0, connectivity=2).max() == 1
        # fractional values lie on the outline, next to both transparent and opaque pixels
        # (the horse's thin legs and sub-pixel gaps by the tail are allowed some exceptions)
        frac = fractional(a)
        near_edge = ndimage.binary_dilation(a == 0, iterations=2) & ndimage.binary_dilation(
            a == 1, iterations=2)
        assert (frac & ~near_edge).sum() <= (0.15 if kind == "horse" else 0.02) * frac.sum()


def test_blob_single_component_no_holes():
    for seed in range(6):
        a = T.alpha_mask("blob", H, W, rng(seed))
        assert measure.label(a > 0, connectivity=1).max() == 1
        assert np.array_equal(ndimage.binary_fill_holes(a > 0), a > 0)


@pytest.mark.parametrize("kind, max_kept", [("thin", 0.02), ("hair", 0.4)])
def test_thin_structures(kind, max_kept):
    for seed in SEEDS:
        a = T.alpha_mask(kind, H, W, rng(seed))
        on = a > 0.5
        kept = ndimage.binary_opening(on, np.ones((3, 3), bool))
        assert kept.sum() <= max_kept * on.sum()
        assert (a > 0).mean() < 0.5


def test_hair_partial_coverage():
    a = T.alpha_mask("hair", 128, 128, rng(1))
    assert fractional(a).sum() > (a == 1).sum()  # mostly partially covered pixels


def test_soft_mask():
    glass = opaque = 0
    for seed in range(10):
        a = T.alpha_mask("soft", H, W, rng(seed))
        top = a.max()
        if top == 1.0:
            opaque += 1
        else:
            assert 0.3 <= top <= 0.7  # glass: uniform partial alpha
            glass += 1
        # wide soft edge: the 0.05..0.95 band of the level is >= ~10 px wide, so many pixels
        band = (a > 0.05 * top) & (a < 0.95 * top)
        assert band.sum() > 0.5 * (a >= 0.95 * top).sum() + 100
    assert glass and opaque


def test_unknown_mask_kind():
    with pytest.raises(ValueError, match="horse"):
        T.alpha_mask("cube", 8, 8, rng())


def test_no_global_random_state():
    np.random.seed(0)
    state = np.random.get_state()[1].copy()
    for kind in T.MASK_KINDS:
        T.alpha_mask(kind, 40, 40, rng())
    for kind in T.PROCEDURAL_TEXTURES:
        T.procedural_texture(kind, 40, 40, rng())
    assert np.array_equal(np.random.get_state()[1], state)


# --------------------------------------------------------------------------- HDR
def test_hdr_highlights():
    base = T.procedural_texture("gradient", H, W, rng(0))
    out = T.hdr_highlights(base, rng(1), count=6)
    check_image(out, hi=np.inf)
    assert out.max() > 10
    changed = np.any(out != base, axis=-1)
    assert 0 < changed.mean() < 0.05
    assert np.all(out >= base)  # light is added, never removed
    assert out.tobytes() == T.hdr_highlights(base, rng(1), count=6).tobytes()
    assert np.array_equal(base, T.procedural_texture("gradient", H, W, rng(0)))  # input kept
    assert np.array_equal(T.hdr_highlights(base, rng(1), count=0), base)
