"""Photographs with a disparity map: encodings, 8/16-bit files, the paper's K and focus,
and ``mpib refocus photo.jpg --disparity disp.png`` end to end.

Every file here is real (written with Pillow, tifffile, numpy or OpenEXR into tmp_path);
the images are small (96x64) so the whole file runs in seconds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from clirun import one_line_error, run
from mpib_validate.runtime.camera import OFFICIAL_BINS
from mpib_validate.runtime.io.exr import read_exr
from mpib_validate.runtime.io.colour import (SRGB_KNEE_ENCODED, SRGB_KNEE_LINEAR, linear_to_srgb,
                                             srgb_to_linear)
from mpib_validate.runtime.io.photo import (Encoding, PhotoError, encode_photo, quantise, read_disparity,
                                            read_photo, write_photo)

H, W = 64, 96


def _texture(seed=0):
    """A random 8-bit RGB photograph (every level and colour mixed)."""
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def _save(path, a, **kw):
    Image.fromarray(a).save(path, **kw)
    return path


def _disparity_u8(near=210, far=40):
    """A near rectangle (disparity near/255) over a far background (far/255)."""
    d = np.full((H, W), far, np.uint8)
    d[16:48, 30:70] = near
    return d


# --------------------------------------------------------------------------- encodings


def test_srgb_transfer_is_exact_at_the_ends_and_the_knee():
    assert srgb_to_linear(0.0) == 0.0 and linear_to_srgb(0.0) == 0.0
    assert srgb_to_linear(1.0) == 1.0 and linear_to_srgb(1.0) == 1.0
    # below the knee both directions are the linear segment, exactly: v / 12.92
    assert srgb_to_linear(SRGB_KNEE_ENCODED) == SRGB_KNEE_ENCODED / 12.92
    assert linear_to_srgb(SRGB_KNEE_LINEAR) == 12.92 * SRGB_KNEE_LINEAR
    # The standard's rounded constants leave its two segments 2.9e-8 apart at the knee
    # (1.055 k^(1/2.4) - 0.055 vs 12.92 k); the decoded knee 0.04045 / 12.92 lies just
    # above k, on the power segment, so its round trip errs by that gap and no more.
    x = SRGB_KNEE_ENCODED / 12.92
    gap = abs(1.055 * x ** (1 / 2.4) - 0.055 - 12.92 * x)
    assert gap < 3e-8
    assert abs(linear_to_srgb(srgb_to_linear(SRGB_KNEE_ENCODED)) - SRGB_KNEE_ENCODED) <= gap + 1e-15
    # the curve is the IEC one, not a plain power: mid grey 0.5 -> 0.21404
    assert srgb_to_linear(0.5) == pytest.approx(((0.5 + 0.055) / 1.055) ** 2.4, rel=1e-15)


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("encoding", [Encoding("srgb"), Encoding("gamma", 2.2)])
def test_every_integer_level_round_trips(bits, encoding):
    # decode then encode is the identity to ~1e-16 (float64); a level is off only past
    # half a level, 1/(2 (2^b - 1)) >= 7.6e-6: so every level must come back exactly
    top = (1 << bits) - 1
    levels = np.arange(top + 1)
    back = quantise(encoding.encode(encoding.decode(levels / top)), bits)
    assert np.array_equal(back, levels)


def test_gamma_is_the_papers_power():
    e = Encoding("gamma", 2.2)
    v = np.linspace(0, 1, 11)
    assert np.allclose(e.decode(v), v ** 2.2, rtol=0, atol=1e-15)
    assert np.allclose(e.encode(v ** 2.2), v, rtol=0, atol=1e-12)


def test_encoding_clips_what_a_file_cannot_hold():
    # an HDR highlight (radiance 3) becomes white; negatives and NaN black
    px = encode_photo(np.array([[[3.0, -1.0, np.nan]]]), None, Encoding("srgb"), 8)
    assert px.tolist() == [[[255, 0, 0]]]


# --------------------------------------------------------------------------- files


def test_photo_files_decode_to_linear(tmp_path):
    a = _texture()
    ref = srgb_to_linear(a / 255.0)
    png = read_photo(_save(tmp_path / "p.png", a))
    assert png.bits == 8 and png.alpha is None and np.array_equal(png.rgb, ref)
    grey = read_photo(_save(tmp_path / "g.png", a[..., 0]))
    assert np.array_equal(grey.rgb, np.repeat(ref[..., :1], 3, axis=-1))
    opaque = read_photo(_save(tmp_path / "o.png", np.dstack([a, np.full((H, W), 255, np.uint8)])))
    assert opaque.alpha is None  # an everywhere-opaque alpha is no alpha
    gamma = read_photo(tmp_path / "p.png", Encoding("gamma", 2.2))
    assert np.allclose(gamma.rgb, (a / 255.0) ** 2.2, rtol=0, atol=1e-15)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16_bit_colour_round_trips_exactly(tmp_path, suffix):
    # 16-bit RGB: Pillow would read a PNG as 8 bit; it is decoded here (and TIFF by
    # tifffile). Written and read back, every value must be the same.
    a16 = np.random.default_rng(1).integers(0, 65536, (H, W, 3), dtype=np.uint16)
    lin = srgb_to_linear(a16 / 65535.0)
    path = tmp_path / f"p16{suffix}"
    write_photo(path, lin, None, Encoding("srgb"), 16)
    back = read_photo(path)
    assert back.bits == 16
    assert np.array_equal(quantise(linear_to_srgb(back.rgb), 16), a16)


def test_16_bit_png_filters_are_undone(tmp_path):
    # A 16-bit PNG written by another encoder uses the Sub, Up, Average and Paeth
    # filters: each row with one (filtered here, byte by byte, by the PNG spec's
    # definitions), decoded by the diagonal wavefront.
    import struct
    import zlib

    from mpib_validate.runtime.io.png16 import _png_chunk

    def _paeth(a, b, c):  # the PNG spec's predictor, one byte at a time
        p = a + b - c
        pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
        return a if pa <= pb and pa <= pc else (b if pb <= pc else c)

    rng = np.random.default_rng(2)
    h, w, bpp = 23, 31, 6
    img = rng.integers(0, 65536, (h, w, 3), dtype=np.uint16)
    img[:8, :8] = 65535  # flat patches: Paeth's ties and Average's carries
    img[-8:, -8:] = 0
    raw = img.astype(">u2").view(np.uint8).reshape(h, -1).astype(int)
    rows, prev = [], np.zeros(raw.shape[1], int)
    kinds = [0, 1, 2, 3, 4] + list(rng.integers(0, 5, h - 5))
    for y, kind in enumerate(kinds):
        cur, f = raw[y], np.zeros_like(raw[y])
        for i in range(cur.size):
            a = cur[i - bpp] if i >= bpp else 0
            c = prev[i - bpp] if i >= bpp else 0
            pred = [0, a, prev[i], (a + prev[i]) // 2, _paeth(a, prev[i], c)][kind]
            f[i] = (cur[i] - pred) % 256
        rows.append(bytes([kind]) + bytes(f.astype(np.uint8)))
        prev = cur
    data = (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0))
            + _png_chunk(b"IDAT", zlib.compress(b"".join(rows))) + _png_chunk(b"IEND", b""))
    (tmp_path / "f.png").write_bytes(data)
    back = read_photo(tmp_path / "f.png")
    assert np.array_equal(quantise(linear_to_srgb(back.rgb), 16), img)


def test_disparity_scaling_8_and_16_bit(tmp_path):
    v8 = np.tile(np.arange(256, dtype=np.uint8), (H, 1))[:, :W]
    v8[0, :2] = [0, 255]
    m = read_disparity(_save(tmp_path / "d8.png", v8), (H, W), normalised=True)
    assert m.kind == "8-bit" and np.array_equal(m.values, v8 / 255.0)
    assert m.values[0, 0] == 0.0 and m.values[0, 1] == 1.0
    v16 = (np.arange(H * W, dtype=np.int64).reshape(H, W) * 11 % 65536).astype(np.uint16)
    v16[0, :2] = [0, 65535]
    m = read_disparity(_save(tmp_path / "d16.png", v16), (H, W), normalised=True)
    assert m.kind == "16-bit" and np.array_equal(m.values, v16 / 65535.0)
    assert m.values[0, 0] == 0.0 and m.values[0, 1] == 1.0
    # the same map as a 16-bit TIFF, and an 8-bit grey image stored as RGB
    import tifffile

    tifffile.imwrite(tmp_path / "d16.tif", v16)
    assert np.array_equal(read_disparity(tmp_path / "d16.tif", (H, W), True).values, v16 / 65535.0)
    rgb = np.repeat(v8[..., None], 3, axis=-1)
    assert np.array_equal(read_disparity(_save(tmp_path / "rgb.png", rgb), (H, W), True).values,
                          v8 / 255.0)
    # a grey JPEG (as the official demo's disparity): chroma is zero, so R = G = B
    rgbj = read_disparity(_save(tmp_path / "d.jpg", rgb, quality=95), (H, W), True)
    assert rgbj.kind == "8-bit"
    # float maps are taken as stored
    f = np.random.default_rng(3).uniform(0, 1, (H, W)).astype(np.float32)
    np.save(tmp_path / "d.npy", f)
    assert np.array_equal(read_disparity(tmp_path / "d.npy", (H, W), True).values, f)


# --------------------------------------------------------------------------- the paper's K


def _dot_photo(tmp_path, disparity_u8):
    """A black 8-bit PNG with one white pixel (sRGB 255 -> linear 1, 0 -> 0 exactly) at
    the centre, and a constant disparity map."""
    a = np.zeros((H, W, 3), np.uint8)
    a[H // 2, W // 2] = 255
    _save(tmp_path / "dot.png", a)
    _save(tmp_path / "d.png", np.full((H, W), disparity_u8, np.uint8))
    return tmp_path / "dot.png", tmp_path / "d.png"


def _measured_radius(img):
    """Blur radius of a refocused dot from its second moment: a photograph is a
    continuous scene (``Passes.pixel_model``), whose kernel has the disk's own moment
    E[rho^2] = r^2 / 2 (``kernels.continuous_radius``), so r = sqrt(2 E[rho^2])."""
    w = img[..., 0].astype(np.float64)
    y, x = np.mgrid[:H, :W]
    m2 = (w * ((y - H // 2) ** 2 + (x - W // 2) ** 2)).sum() / w.sum()
    return math.sqrt(max(2.0 * m2, 0.0))


def _official_radius(K, i, disp_focus, increase_focus_range):
    """The official renderer's kernel radius of plane ``i`` (``MPIBokehRenderer``): plane
    disparity ``(i + 0.5) / 32``, defocus ``|d_i - d_f|`` less half a bin with
    ``increase_focus_range`` (clamped at 0), radius ``round(K * defocus)``."""
    defocus = abs((i + 0.5) / OFFICIAL_BINS - disp_focus)
    if increase_focus_range:
        defocus = max(defocus - 0.5 / OFFICIAL_BINS, 0.0)
    return round(K * defocus)


@pytest.mark.parametrize("plane", [3, 12, 20, 31])
def test_blur_radius_is_the_papers_for_K_and_disp_focus(tmp_path, plane):
    """A dot on the official plane i (disparity (i + 0.5)/32, written as a 16-bit map so
    the plane value is exact to 1/65535) refocused with the paper's K and focus blurs
    into the published radius K |d_i - d_f|; with --official-focus-range into the
    official renderer's K max(|d_i - d_f| - 1/64, 0) before its rounding to integers."""
    K, focus = 30.0, 207 / 255
    d16 = round((plane + 0.5) / OFFICIAL_BINS * 65535)
    photo, _ = _dot_photo(tmp_path, 0)
    _save(tmp_path / "d16.png", np.full((H, W), d16, np.uint16))
    d_i = d16 / 65535
    for flag, expected, official in (
            ([], K * abs(d_i - focus), _official_radius(K, plane, focus, False)),
            (["--official-focus-range"], K * max(abs(d_i - focus) - 0.5 / OFFICIAL_BINS, 0.0),
             _official_radius(K, plane, focus, True))):
        out = tmp_path / f"out{len(flag)}.exr"
        rc, _, err = run("refocus", photo, "--disparity", tmp_path / "d16.png", "--K", K,
                         "--disp-focus", focus, "-o", out, "--no-preview", "-q", *flag)
        assert rc == 0, err
        img = read_exr(out).channels
        r = _measured_radius(np.dstack([img["R"]]))
        # The continuous kernel's moment is the disk's to 0.02 px^2 per axis
        # (test_kernels), 0.01 px of radius at 4.7 px and less above (these radii are
        # 4.7 to 21 px). 0.05 px allows that and
        # fails for any other K, a scaled disparity or an offset of the focus range
        # (K / 64 = 0.47 px); one 1/65535 step of the map moves r by 5e-4 px.
        assert r == pytest.approx(expected, abs=0.05)
        # the official renderer's integer radius is the same one rounded: within 1/2 px
        # of what the project renders
        assert abs(r - official) <= 0.5 + 0.05


def test_focus_pixel_on_a_disparity_map_focuses_there(tmp_path):
    a = _texture(4)
    photo = _save(tmp_path / "p.png", a)
    disp = _save(tmp_path / "d.png", _disparity_u8())
    out = tmp_path / "o.png"
    # focus on the near rectangle (centre 50, 32)
    rc, stdout, err = run("refocus", photo, "--disparity", disp, "--K", 20, "--focus-pixel",
                          "50,32", "-o", out, "-q")
    assert rc == 0, err
    assert "d_f = 0.82353" in stdout  # 210 / 255
    b = np.asarray(Image.open(out))
    # inside the rectangle, away from its edges by more than the background's blur
    # reach (the fill behind the foreground does not reach into it): unchanged exactly,
    # radius 0 being the identity and every level round-tripping (test above)
    inner = (slice(20, 44), slice(34, 66))
    assert np.array_equal(b[inner], a[inner])
    # the far background is blurred (radius 20 (210 - 40)/255 = 13 px): its pixel
    # noise falls by more than 3x (a uniform random texture averaged over ~500 px)
    far = (slice(0, 10), slice(0, 25))
    assert b[far].astype(float).std() < a[far].astype(float).std() / 3


# --------------------------------------------------------------------------- end to end


def test_jpeg_and_png_in_jpeg_out_one_command(tmp_path):
    photo = _save(tmp_path / "photo.jpg", _texture(5), quality=92)
    disp = _save(tmp_path / "disp.png", _disparity_u8())
    out = tmp_path / "out.jpg"
    rc, stdout, err = run("refocus", photo, "--disparity", disp, "--K", 24, "--disp-focus",
                          210 / 255, "--gamma", 2.2, "-o", out, "--exr", tmp_path / "lin.exr", "-q")
    assert rc == 0, err
    with Image.open(out) as im:
        assert im.format == "JPEG" and im.mode == "RGB" and im.size == (W, H)  # opaque
    lin = read_exr(tmp_path / "lin.exr").channels
    assert np.all(lin["A"] == 1.0)  # opaque in, opaque out
    assert all(np.isfinite(lin[c]).all() for c in "RGB")
    assert "A = K = 24 px" in stdout and "gamma 2.2" in stdout


def test_disp_focus_takes_the_official_demos_fraction(tmp_path):
    """``--disp-focus 207/255`` is the number 207/255: the same image to the bit."""
    photo = _save(tmp_path / "photo.png", _texture(7))
    disp = _save(tmp_path / "disp.png", _disparity_u8())
    outs = []
    for i, focus in enumerate(("207/255", repr(207 / 255))):
        outs.append(tmp_path / f"o{i}.png")
        rc, _, err = run("refocus", photo, "--disparity", disp, "--K", 20, "--disp-focus",
                         focus, "-o", outs[-1], "-q")
        assert rc == 0, err
    assert np.array_equal(np.asarray(Image.open(outs[0])), np.asarray(Image.open(outs[1])))


def test_a_network_resolution_map_is_upsampled_with_a_notice(tmp_path):
    """A map at a quarter of the photograph's size (same aspect ratio) is accepted: one
    notice line, and the result is that of the same map upsampled beforehand by
    :func:`upsample_disparity` (bilinear, centres aligned) and given at full size."""
    from mpib_validate.runtime.io.photo import upsample_disparity

    photo = _save(tmp_path / "photo.png", _texture(8))
    full = _disparity_u8()
    low = full.reshape(H // 4, 4, W // 4, 4).mean(axis=(1, 3)).round().astype(np.uint8)
    small = _save(tmp_path / "small.png", low)
    up = upsample_disparity(low / 255.0, (H, W))
    assert up.shape == (H, W)
    # bilinear with centres aligned: the map's mean is kept within a level
    assert abs(up.mean() - low.mean() / 255.0) < 1 / 255
    np.save(tmp_path / "up.npy", up.astype(np.float32))
    common = ["--K", 20, "--disp-focus", "0.5", "-q", "--refine", "guided"]
    rc, _, err = run("refocus", photo, "--disparity", small, "-o", tmp_path / "a.png", *common)
    assert rc == 0, err
    notice = [ln for ln in err.splitlines() if "notice" in ln]
    assert len(notice) == 1 and "small.png" in notice[0] and f"{W}x{H}" in notice[0]
    rc, _, err = run("refocus", photo, "--disparity", tmp_path / "up.npy", "-o",
                     tmp_path / "b.png", *common)
    assert rc == 0, err
    assert np.array_equal(np.asarray(Image.open(tmp_path / "a.png")),
                          np.asarray(Image.open(tmp_path / "b.png")))


def test_map_overshoot_shrinks_a_fattened_near_side_first(tmp_path):
    """A map whose near rectangle overshoots the object by 4 px keeps a 4 px strip of
    background in focus, sharp where the background blurs by 13 px; ``--map-overshoot
    4`` erodes the map first, which gives back the object's own rectangle (a rectangle
    dilated by a square and eroded by the same square is itself): the same image to
    the bit as the exact map, with one notice line. Bad values and a depth EXR are
    refused in one line."""
    photo_a = _texture(9)
    photo = _save(tmp_path / "photo.png", photo_a)
    exact = _save(tmp_path / "exact.png", _disparity_u8())
    fat = np.full((H, W), 40, np.uint8)
    fat[12:52, 26:74] = 210
    fattened = _save(tmp_path / "fat.png", fat)
    common = ["--K", 20, "--disp-focus", "210/255", "--refine", "off", "-q"]
    outs = {}
    for name, disp, extra in (("exact", exact, []), ("fat", fattened, []),
                              ("shrunk", fattened, ["--map-overshoot", 4])):
        outs[name] = tmp_path / f"out-{name}.png"
        rc, _, err = run("refocus", photo, "--disparity", disp, "-o", outs[name], *common,
                         *extra)
        assert rc == 0, err
        notice = [ln for ln in err.splitlines() if "--map-overshoot" in ln]
        assert len(notice) == (1 if extra else 0), err
    img = {k: np.asarray(Image.open(v)) for k, v in outs.items()}
    # background inside the overshoot, off its ends and its outer row (an edge pixel)
    strip = (slice(13, 16), slice(34, 66))
    assert np.array_equal(img["fat"][strip], photo_a[strip])  # the halo: kept sharp
    assert img["exact"][strip].astype(float).std() < photo_a[strip].astype(float).std() / 3
    assert np.array_equal(img["shrunk"], img["exact"])
    for bad in ("-1", "65", "1.5", "x"):
        line = one_line_error(*run("refocus", photo, "--disparity", fattened, "-o",
                                   tmp_path / "bad.png", *common, "--map-overshoot", bad)[::2])
        assert "--map-overshoot" in line and "bad.png" not in {p.name for p in tmp_path.iterdir()}
    from mpib_validate.runtime.io.exr import write_exr

    write_exr(tmp_path / "z.exr", {"Z": np.full((H, W), 2.0, np.float32)})
    line = one_line_error(*run("refocus", photo, "--depth", tmp_path / "z.exr",
                               "--blur-parameter", 5, "--focus-depth", 2, "-o",
                               tmp_path / "bad.png", "-q", "--map-overshoot", 2)[::2])
    assert "--map-overshoot" in line and "--disparity" in line


@pytest.mark.parametrize("bits", [8, 16])
def test_in_focus_constant_disparity_png_round_trips_exactly(tmp_path, bits):
    """One plane in focus: radius 0, the identity kernel; the float path adds ~1e-12
    (FFT floor) to the linear values, far below half a level (7.6e-6 at 16 bit), so
    PNG in -> PNG out must give every pixel back exactly (tolerance 0)."""
    rng = np.random.default_rng(6)
    if bits == 8:
        a = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        _save(tmp_path / "p.png", a)
    else:
        a = rng.integers(0, 65536, (H, W, 3), dtype=np.uint16)
        write_photo(tmp_path / "p.png", srgb_to_linear(a / 65535.0), None, Encoding("srgb"), 16)
    _save(tmp_path / "d.png", np.full((H, W), 128, np.uint8))
    rc, _, err = run("refocus", tmp_path / "p.png", "--disparity", tmp_path / "d.png", "--K", 40,
                     "--disp-focus", 128 / 255, "-o", tmp_path / "o.png", "-q")
    assert rc == 0, err
    back = read_photo(tmp_path / "o.png")
    assert back.bits == bits and back.alpha is None
    assert np.array_equal(quantise(linear_to_srgb(back.rgb), bits), a)


def test_in_focus_constant_disparity_jpeg_round_trips_within_jpeg_quantisation(tmp_path):
    """JPEG in -> JPEG out, in focus: the pixels handed to the encoder are the input's
    (as the PNG test shows), so the difference is the re-encoding alone. With 4:4:4 and
    the file's own quantisation tables q_k, each DCT coefficient of the luma errs
    uniformly by at most q_k / 2 (variance q_k^2 / 12); the DCT is orthonormal, so the
    luma RMS error is sqrt(mean_k q_k^2 / 12), plus the decoder's rounding to 8 bits
    (RMS 1/sqrt(12) = 0.29 each, before and after). That model takes every
    coefficient's error as spread over its whole bin, an upper estimate (measured here:
    0.28 levels against a bound of 2.0); exposure or encoding errors give tens."""
    a = _texture(7)
    _save(tmp_path / "p.jpg", a, quality=95, subsampling=0)
    _save(tmp_path / "d.png", np.full((H, W), 90, np.uint8))
    rc, _, err = run("refocus", tmp_path / "p.jpg", "--disparity", tmp_path / "d.png", "--K", 40,
                     "--disp-focus", 90 / 255, "-o", tmp_path / "o.jpg", "-q")
    assert rc == 0, err
    with Image.open(tmp_path / "p.jpg") as im_in, Image.open(tmp_path / "o.jpg") as im_out:
        q = np.asarray(im_out.quantization[0], np.float64)
        y_in = np.asarray(im_in.convert("YCbCr"), np.float64)[..., 0]
        y_out = np.asarray(im_out.convert("YCbCr"), np.float64)[..., 0]
    bound = math.sqrt((q ** 2).mean() / 12.0 + 2.0 / 12.0)
    rms = math.sqrt(((y_out - y_in) ** 2).mean())
    assert rms <= bound, (rms, bound)


def test_edge_is_blurred_in_linear_light(tmp_path):
    """Eq. 1 on linear colour: a black | white edge, defocused, has mirror pixels whose
    linear values sum to 1 (the kernel is symmetric); each output level errs by half a
    level, 1/510, times the decode slope (at most 2.3 for sRGB, 2.2 for gamma 2.2), so
    the sum is 1 within 2 x 2.3 / 510 = 0.009. Blurring the encoded values instead
    would give 2 decode(0.5) = 0.43 for sRGB."""
    a = np.zeros((H, W, 3), np.uint8)
    a[:, W // 2:] = 255
    _save(tmp_path / "e.png", a)
    _save(tmp_path / "d.png", np.full((H, W), 0, np.uint8))
    for args, enc in (([], Encoding("srgb")), (["--gamma", 2.2], Encoding("gamma", 2.2))):
        rc, _, err = run("refocus", tmp_path / "e.png", "--disparity", tmp_path / "d.png", "--K",
                         20, "--disp-focus", 0.3, "-o", tmp_path / "o.png", "-q", *args)
        assert rc == 0, err
        v = np.asarray(Image.open(tmp_path / "o.png"), np.float64)[H // 2, :, 0] / 255
        lin = enc.decode(v)
        for k in range(1, 6):
            assert lin[W // 2 - k] + lin[W // 2 - 1 + k] == pytest.approx(1.0, abs=0.009)
        assert 0.05 < lin[W // 2 - 3] < 0.45  # it is blurred (radius 6 px)


def test_all_constant_disparity_is_one_plane(tmp_path):
    # everything at one disparity (0: infinity): sharp when focused there
    a = _texture(8)
    _save(tmp_path / "p.png", a)
    _save(tmp_path / "d.png", np.zeros((H, W), np.uint8))
    rc, stdout, err = run("refocus", tmp_path / "p.png", "--disparity", tmp_path / "d.png", "--K",
                          50, "--disp-focus", 0, "-o", tmp_path / "o.png", "-q")
    assert rc == 0, err
    assert " 1 planes" in stdout
    assert np.array_equal(np.asarray(Image.open(tmp_path / "o.png")), a)


def test_float_disparity_and_exr_photo(tmp_path):
    from mpib_validate.runtime.io.exr import write_exr

    lin = srgb_to_linear(_texture(9) / 255.0).astype(np.float32)
    write_exr(tmp_path / "p.exr", {"R": lin[..., 0], "G": lin[..., 1], "B": lin[..., 2]})
    np.save(tmp_path / "d.npy", (_disparity_u8() / 255.0).astype(np.float32))
    rc, _, err = run("refocus", tmp_path / "p.exr", "--disparity", tmp_path / "d.npy", "--K", 20,
                     "--disp-focus", 210 / 255, "-o", tmp_path / "o.jpg", "-q")
    assert rc == 0, err  # linear in, sRGB JPEG out
    # a float map in 1/scene-unit with a physical lens: allowed (not the paper's K)
    np.save(tmp_path / "dz.npy", np.full((H, W), 0.5, np.float32))
    rc, _, err = run("refocus", tmp_path / "p.exr", "--disparity", tmp_path / "dz.npy", "--fstop",
                     2, "--focal-mm", 50, "--focus-disparity", 0.4, "-o", tmp_path / "o2.png", "-q")
    assert rc == 0, err


# --------------------------------------------------------------------------- bad input


def _bad_cases(tmp_path):
    photo = _save(tmp_path / "photo.jpg", _texture(10))
    disp = _save(tmp_path / "disp.png", _disparity_u8())
    small = _save(tmp_path / "small.png", np.zeros((32, 32), np.uint8))  # square: 1:1, not 3:2
    colour = _save(tmp_path / "colour.png", _texture(11))
    nan = np.full((H, W), 0.5, np.float32)
    nan[3, 4] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    inf = np.full((H, W), 0.5, np.float32)
    inf[5, 6] = np.inf
    np.save(tmp_path / "inf.npy", inf)
    np.save(tmp_path / "big.npy", np.full((H, W), 3.0, np.float32))
    np.save(tmp_path / "neg.npy", np.full((H, W), -0.1, np.float32))
    rgba = np.dstack([_texture(12), np.full((H, W), 128, np.uint8)])
    trans = _save(tmp_path / "trans.png", rgba)
    k = ["--K", 20, "--disp-focus", 0.5]
    return {
        "aspect ratio": ([photo, "--disparity", small, *k], "small.png"),
        "focus fraction over zero": ([photo, "--disparity", disp, "--K", 20, "--disp-focus",
                                      "207/0"], "--disp-focus"),
        "focus fraction of words": ([photo, "--disparity", disp, "--K", 20, "--disp-focus",
                                     "a/b"], "--disp-focus"),
        "focus fraction above one": ([photo, "--disparity", disp, "--K", 20, "--disp-focus",
                                      "300/255"], "--disp-focus"),
        "colour map": ([photo, "--disparity", colour, *k], "colour image"),
        "nan": ([photo, "--disparity", tmp_path / "nan.npy", *k], "NaN"),
        "inf": ([photo, "--disparity", tmp_path / "inf.npy", *k], "infinite"),
        "above one with K": ([photo, "--disparity", tmp_path / "big.npy", *k], "above 1"),
        "negative": ([photo, "--disparity", tmp_path / "neg.npy", *k], "negative"),
        "no disparity": ([photo, *k], "--disparity"),
        "no blur": ([photo, "--disparity", disp, "--disp-focus", 0.5], "--K"),
        "no focus": ([photo, "--disparity", disp, "--K", 20], "--disp-focus"),
        "focus outside [0, 1]": ([photo, "--disparity", disp, "--K", 20, "--disp-focus", 1.5],
                                 "--disp-focus"),
        "K with a lens": ([photo, "--disparity", disp, *k, "--fstop", 2], "--fstop"),
        "lens on a normalised map": ([photo, "--disparity", disp, "--fstop", 2, "--focal-mm", 50,
                                      "--focus-disparity", 0.5], "normalised"),
        "gamma on EXR-only option": ([photo, "--disparity", disp, *k, "--encoding", "linear",
                                      "--gamma", 2.2], "--gamma"),
        "transparent to JPEG": ([trans, "--disparity", disp, *k], "JPEG"),
        "focus pixel outside": ([photo, "--disparity", disp, "--K", 20, "--focus-pixel",
                                 "500,5"], "--focus-pixel"),
        "missing disparity file": ([photo, "--disparity", tmp_path / "none.png", *k], "none.png"),
    }


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path):
    for name, (args, needle) in _bad_cases(tmp_path).items():
        out = tmp_path / "out.jpg"
        rc, _, err = run("refocus", *args, "-o", out, "-q")
        line = one_line_error(rc, err)
        assert needle in line, (name, line)
        assert not out.exists(), name
        assert not list(tmp_path.glob(".out*")), name  # no temporary file left


def test_the_input_is_never_overwritten(tmp_path):
    photo = _save(tmp_path / "photo.jpg", _texture(13))
    disp = _save(tmp_path / "disp.png", _disparity_u8())
    from mpib_validate.runtime.io.exr import write_exr

    write_exr(tmp_path / "disp.exr", {"Y": np.full((H, W), 0.5, np.float32)})
    exr = tmp_path / "disp.exr"
    before = photo.read_bytes(), disp.read_bytes(), exr.read_bytes()
    for out, d, extra in ((photo, disp, []), (disp, disp, []),
                          (tmp_path / "o.jpg", exr, ["--exr", exr])):
        rc, _, err = run("refocus", photo, "--disparity", d, "--K", 20, "--disp-focus", 0.5,
                         "-o", out, "-q", *extra)
        assert "overwrite" in one_line_error(rc, err)
    assert (photo.read_bytes(), disp.read_bytes(), exr.read_bytes()) == before
    assert not (tmp_path / "o.jpg").exists()


def test_photo_options_are_refused_for_exr_passes(tmp_path):
    from mpib_validate.runtime.io.exr import write_exr

    z = np.full((H, W), 2.0, np.float32)
    write_exr(tmp_path / "r.exr", {"R": z, "G": z, "B": z, "Depth.Z": z})
    rc, _, err = run("refocus", tmp_path / "r.exr", "--K", 20, "--disp-focus", 0.5, "-o",
                     tmp_path / "o.exr")
    assert "--K" in one_line_error(rc, err)


def test_read_disparity_names_the_file(tmp_path):
    _save(tmp_path / "c.png", _texture(14))
    with pytest.raises(PhotoError, match="c.png"):
        read_disparity(tmp_path / "c.png", (H, W), True)


def test_transparent_png_keeps_its_alpha(tmp_path):
    """A transparent PNG in focus: straight colour and alpha come back exactly (the
    colour travels premultiplied in float32, relative error 6e-8, far below half a
    level, 1/510)."""
    rng = np.random.default_rng(15)
    a = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
    a[..., 3] = rng.integers(1, 256, (H, W))  # alpha 0 has no colour to give back
    _save(tmp_path / "t.png", a)
    _save(tmp_path / "d.png", np.full((H, W), 100, np.uint8))
    rc, _, err = run("refocus", tmp_path / "t.png", "--disparity", tmp_path / "d.png", "--K", 30,
                     "--disp-focus", 100 / 255, "-o", tmp_path / "o.png", "-q")
    assert rc == 0, err
    with Image.open(tmp_path / "o.png") as im:
        assert im.mode == "RGBA"
        assert np.array_equal(np.asarray(im), a)


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_exif_orientation_and_icc_profile(tmp_path, suffix):
    """A phone photo stored sideways (EXIF orientation 6: rotate 90 degrees clockwise)
    is read as shown, so that its disparity map (predicted on the shown picture) fits;
    its ICC profile (here any bytes: it is copied, not parsed) is written again."""
    a = _texture(16)[:, :80]  # 64 x 80 stored, 80 x 64 shown
    exif = Image.Exif()
    exif[0x0112] = 6
    icc = b"not a real profile, copied as is" * 4
    _save(tmp_path / f"p{suffix}", a, exif=exif, icc_profile=icc,
          **({"quality": 95} if suffix == ".jpg" else {}))
    shown = read_photo(tmp_path / f"p{suffix}")
    assert shown.rgb.shape == (80, 64, 3) and shown.icc_profile == icc
    if suffix == ".png":  # lossless: the pixels are the stored ones turned clockwise
        assert np.array_equal(quantise(linear_to_srgb(shown.rgb), 8), np.rot90(a, -1))
    _save(tmp_path / "d.png", np.full((80, 64), 50, np.uint8))
    out = tmp_path / f"o{suffix}"
    rc, _, err = run("refocus", tmp_path / f"p{suffix}", "--disparity", tmp_path / "d.png", "--K",
                     10, "--disp-focus", 50 / 255, "-o", out, "-q")
    assert rc == 0, err
    with Image.open(out) as im:
        assert im.size == (64, 80) and im.info.get("icc_profile") == icc
        assert im.getexif().get(0x0112) in (None, 1)  # already upright


def test_16_bit_png_keeps_its_icc_profile(tmp_path):
    icc = b"profile bytes" * 8
    lin = srgb_to_linear(_texture(17) / 255.0)
    write_photo(tmp_path / "p.png", lin, None, Encoding("srgb"), 16, icc)
    assert read_photo(tmp_path / "p.png").icc_profile == icc


def test_photo_with_a_depth_exr_and_a_float_tiff_map(tmp_path):
    import tifffile

    from mpib_validate.runtime.io.exr import write_exr

    a = _texture(18)
    photo = _save(tmp_path / "p.png", a)
    z = np.where(_disparity_u8() > 100, 1.0, 4.0).astype(np.float32)  # metres
    write_exr(tmp_path / "z.exr", {"Z": z})
    out = tmp_path / "o.png"
    rc, stdout, err = run("refocus", photo, "--depth", tmp_path / "z.exr", "--blur-parameter", 16,
                          "--focus-depth", 1.0, "-o", out, "-q")
    assert rc == 0, err
    inner = (slice(20, 44), slice(34, 66))  # the near rectangle, in focus at 1 m
    assert np.array_equal(np.asarray(Image.open(out))[inner], a[inner])
    rc, _, err = run("refocus", photo, "--depth", tmp_path / "z.exr", "--K", 16, "--disp-focus",
                     0.5, "-o", tmp_path / "o2.png")
    assert "--K" in one_line_error(rc, err)
    # the same scene as a float TIFF disparity (1/Z), with the paper's K
    tifffile.imwrite(tmp_path / "d.tif", (1.0 / z).astype(np.float32))
    # the same disparity as a float map (a predicted map is refined by default; the
    # depth EXR is taken as exact, so compare like with like)
    rc, _, err = run("refocus", photo, "--disparity", tmp_path / "d.tif", "--K", 16,
                     "--disp-focus", 1.0, "--refine", "off", "-o", tmp_path / "o3.png", "-q")
    assert rc == 0, err
    assert np.array_equal(np.asarray(Image.open(tmp_path / "o3.png")), np.asarray(Image.open(out)))


# --------------------------------------------------------------------------- fuzz

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

# valid choices repeated so that about half the examples run through (the rest refused)
_MAPS = st.sampled_from(["u8", "u16", "rgb-grey", "float", "constant"] * 3
                        + ["rgb-colour", "float-nan", "float-neg", "float-big", "small"])


def _write_map(tmp, kind, rng, h, w):
    if kind in ("u8", "constant", "small"):
        hh, ww = (h // 2, w // 2) if kind == "small" else (h, w)
        v = np.full((hh, ww), 77, np.uint8) if kind == "constant" else rng.integers(
            0, 256, (hh, ww), dtype=np.uint8)
        return _save(tmp / "d.png", v)
    if kind == "u16":
        return _save(tmp / "d.png", rng.integers(0, 65536, (h, w), dtype=np.uint16))
    if kind.startswith("rgb"):
        v = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        if kind == "rgb-grey":
            v[..., 1] = v[..., 2] = v[..., 0]
        return _save(tmp / "d.png", v)
    f = rng.uniform(0, 1, (h, w)).astype(np.float32)
    if kind == "float-nan":
        f[1, 2] = np.nan
    elif kind == "float-neg":
        f[0, 0] = -0.5
    elif kind == "float-big":
        f *= 7
    np.save(tmp / "d.npy", f)
    return tmp / "d.npy"


@settings(max_examples=30, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(kind=_MAPS, photo=st.sampled_from([".jpg", ".png", ".tif"]),
       out=st.sampled_from([".jpg", ".png", ".tif", ".exr"] * 3 + [".bmp"]),
       K=st.sampled_from([12.0] * 6 + [0.5, None, 1e7]),
       focus=st.sampled_from([0.0, 0.4, 1.0] * 3 + [None, 1.5, -0.1]),
       extra=st.lists(st.sampled_from([["--gamma", "2.2"], ["--encoding", "linear"],
                                       ["--official-focus-range"], ["--focus-pixel", "3,4"],
                                       ["--blur-parameter", "5"], ["--fstop", "2"],
                                       ["--focus-disparity", "0.3"], ["--exr", "x.exr"],
                                       ["--map-overshoot", "2"], ["--map-overshoot", "65"]]),
                      max_size=1),
       seed=st.integers(0, 1000))
def test_fuzz_photo_refocus_succeeds_or_refuses_in_one_line(tmp_path_factory, kind, photo, out,
                                                            K, focus, extra, seed):
    import tempfile
    from pathlib import Path

    tmp = Path(tempfile.mkdtemp(dir=tmp_path_factory.getbasetemp()))
    rng = np.random.default_rng(seed)
    h, w = 16, 24
    a = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    ppath = _save(tmp / f"p{photo}", a) if photo != ".tif" else tmp / "p.tif"
    if photo == ".tif":
        import tifffile

        tifffile.imwrite(ppath, (a.astype(np.uint16) * 257), photometric="rgb")
    dpath = _write_map(tmp, kind, rng, h, w)
    args = [ppath, "--disparity", dpath, "-o", tmp / f"o{out}", "-q", "--max-memory-gb", "2"]
    if K is not None:
        args += ["--K", K]
    if focus is not None:
        args += ["--disp-focus", focus]
    for e in extra:
        args += [e[0], tmp / e[1]] if e[0] == "--exr" else e
    before = {p.name: p.read_bytes() for p in tmp.iterdir()}
    rc, stdout, err = run("refocus", *args)
    assert "Traceback" not in err, err
    assert rc in (0, 2), (rc, err)
    after = {p.name: p.read_bytes() for p in tmp.iterdir()}
    assert all(after.get(k) == v for k, v in before.items())  # no input changed
    new = set(after) - set(before)
    if rc == 2:
        one_line_error(rc, err)
        assert not new, new  # no partial output, no temporary file
        return
    assert f"o{out}" in new
    for name in new:
        if name.endswith(".exr"):
            assert all(np.isfinite(c).all() for c in read_exr(tmp / name).channels.values())


def test_help_puts_the_papers_parameters_beside_the_physical_ones():
    rc, out, _ = run("refocus", "--help")
    assert rc == 0
    for option in ("--disparity", "--K", "--disp-focus", "--gamma", "--encoding", "--exr",
                   "--official-focus-range", "--map-overshoot", "--fstop", "--focal-mm",
                   "--blur-parameter"):
        assert option in out, option
    table = out[out.index("parameters, paper and physical"):]
    assert "--K K" in table and "--fstop N" in table and "A = K = R f_px" in table
