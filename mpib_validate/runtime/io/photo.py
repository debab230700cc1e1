"""Photographs and disparity maps as photographers and researchers have them.

Colour: JPEG, PNG (8 or 16 bit), TIFF (8, 16 bit or float) and EXR. Disparity: an 8- or
16-bit grey PNG/JPEG/TIFF normalised to [0, 1] (what DPT, MiDaS or Depth Anything users
save), or a float map (EXR, float TIFF, ``.npy``). Every function here is a pure
function of arrays except the readers and writers at the bottom, which only move
arrays between files and memory.

Colour encodings (:class:`Encoding`), each with its exact inverse:

- ``srgb``: IEC 61966-2-1. Decode ``c = v / 12.92`` for ``v <= 0.04045``, else
  ``((v + 0.055) / 1.055) ** 2.4``; encode ``v = 12.92 c`` for ``c <= 0.0031308``,
  else ``1.055 c ** (1 / 2.4) - 0.055``.
- ``gamma``: the MPIB paper's convention (Eq. 1 is applied to ``image ** gamma``, the
  result raised to ``1 / gamma``): decode ``c = v ** g``, encode ``v = c ** (1 / g)``.
- ``linear``: the values are radiance already (EXR, float TIFF).

Quantisation (the writers): an integer file of ``b`` bits stores
``round(clip(encode(c), 0, 1) * (2**b - 1))``: linear radiance above 1 (a refocused HDR
highlight) clips to white, and the encoded value is rounded to the nearest level, an
error of at most half a level (1/510 for 8 bit, 1/131070 for 16 bit in the encoded
value). JPEG adds its own DCT quantisation (quality 95, no chroma subsampling here).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpib_validate.runtime.io.atomic import atomic_path
from mpib_validate.runtime.io.colour import linear_to_srgb, srgb_to_linear
from mpib_validate.runtime.io.png16 import PngError, png16_bytes, png_dimensions, png_header, read_png16


class PhotoError(ValueError):
    """An unusable photograph or disparity map; the message names the file."""


@dataclass(frozen=True)
class Encoding:
    """How a file's values map to linear radiance: ``srgb``, ``gamma`` (``value ** gamma``
    is linear, the paper's convention) or ``linear``."""

    name: str = "srgb"
    gamma: float = 2.2

    def __post_init__(self):
        if self.name not in ("srgb", "gamma", "linear"):
            raise ValueError(f"encoding must be srgb, gamma or linear, got {self.name!r}")
        if self.name == "gamma" and not (np.isfinite(self.gamma) and self.gamma > 0):
            raise ValueError(f"--gamma must be finite and > 0, got {self.gamma}")

    def decode(self, v: np.ndarray) -> np.ndarray:
        """File values (``[0, 1]`` for integer files) to linear radiance."""
        if self.name == "srgb":
            return srgb_to_linear(v)
        if self.name == "gamma":
            return np.power(np.clip(np.asarray(v, np.float64), 0.0, 1.0), self.gamma)
        return np.asarray(v, np.float64)

    def encode(self, c: np.ndarray) -> np.ndarray:
        """Linear radiance to encoded values in [0, 1] (clipped: see the module
        docstring). ``linear`` only clips."""
        if self.name == "srgb":
            return linear_to_srgb(c)
        c = np.clip(np.nan_to_num(np.asarray(c, np.float64)), 0.0, 1.0)
        return np.power(c, 1.0 / self.gamma) if self.name == "gamma" else c

    def describe(self) -> str:
        return f"gamma {self.gamma:g}" if self.name == "gamma" else self.name


def quantise(encoded: np.ndarray, bits: int) -> np.ndarray:
    """``round(clip(v, 0, 1) * (2**bits - 1))`` as uint8 (8 bits) or uint16 (16 bits)."""
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    top = (1 << bits) - 1
    q = np.round(np.clip(np.asarray(encoded, np.float64), 0.0, 1.0) * top)
    return q.astype(np.uint8 if bits == 8 else np.uint16)


def encode_photo(rgb: np.ndarray, alpha: np.ndarray | None, encoding: Encoding,
                 bits: int) -> np.ndarray:
    """``(H, W, 3)`` straight linear colour (and ``(H, W)`` alpha, or None) to the
    integer pixels of a file: the colour encoded and quantised (:func:`quantise`), the
    alpha (linear coverage, never encoded) quantised. ``(H, W, 3)`` or ``(H, W, 4)``."""
    out = encoding.encode(np.asarray(rgb)[..., :3])
    if alpha is not None:
        out = np.concatenate([out, np.clip(np.asarray(alpha, np.float64), 0, 1)[..., None]],
                             axis=-1)
    return quantise(out, bits)


# ------------------------------------------------------------------------------------
# files

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: Where each output format comes from: the -o suffix.
_FORMATS = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG", ".tif": "TIFF", ".tiff": "TIFF",
            ".exr": "EXR"}
#: JPEG quality of written files (libjpeg scale); no chroma subsampling (4:4:4).
JPEG_QUALITY = 95


def image_format(path) -> str | None:
    """``JPEG``, ``PNG``, ``TIFF`` or ``EXR`` by the file suffix, else None."""
    return _FORMATS.get(Path(path).suffix.lower())


@dataclass
class Photo:
    """A photograph in memory: ``rgb`` ``(H, W, 3)`` float64 linear radiance, straight
    (not premultiplied); ``alpha`` ``(H, W)`` in [0, 1] or None (opaque); ``bits``: 8,
    16 (integer files) or 32 (float); ``encoding``: how the file was decoded."""

    rgb: np.ndarray
    alpha: np.ndarray | None
    bits: int
    format: str
    encoding: Encoding
    path: str
    #: the file's embedded ICC colour profile, written again into the output (the
    #: encodings above are transfer curves; the primaries, e.g. Display P3, are the
    #: profile's, and a linear mix is the same in any linear RGB)
    icc_profile: bytes | None = None


def _read_integer_pixels(path) -> tuple[np.ndarray, bytes | None]:
    """``(H, W, C)`` uint8/uint16 or float pixels of a JPEG, PNG or TIFF, and the file's
    ICC profile (or None). A JPEG's or PNG's EXIF orientation is applied (as viewers and
    OpenCV's ``imread``, which the official code and depth networks use, do), so the
    pixels are the picture as shown."""
    fmt = image_format(path)
    if fmt == "TIFF":
        import tifffile

        try:
            with tifffile.TiffFile(str(path)) as tf:
                series = tf.series[0]
                axes = _tiff_axes(series.axes, series.shape, path)
                a = series.asarray()
                tag = tf.pages[0].tags.get(34675)  # InterColorProfile
                icc = bytes(tag.value) if tag is not None else None
        except PhotoError:
            raise
        except Exception as exc:  # tifffile raises several types for bad files
            raise PhotoError(f"cannot read '{path}': {' '.join(str(exc).split())}") from None
        if axes == "SYX":  # planar configuration: one plane per sample
            a = np.moveaxis(a, 0, -1)
        return (a[..., None] if a.ndim == 2 else a), icc
    head = png_header(path) if fmt == "PNG" else None
    if head is not None and head[0] == 16 and head[1] != 0:
        try:
            return read_png16(path)
        except PngError as exc:
            raise PhotoError(str(exc)) from None
    from PIL import Image, ImageOps, UnidentifiedImageError

    try:
        with Image.open(path) as opened:
            icc = opened.info.get("icc_profile") or None
            im = ImageOps.exif_transpose(opened)
            mode = im.mode
            if mode.startswith("I;16") or (mode == "I" and head is not None and head[0] == 16):
                a = np.asarray(im).astype(np.uint16)  # 16-bit grey (some Pillows say "I")
            elif mode in ("L", "RGB", "RGBA", "LA"):
                a = np.asarray(im)
            elif mode == "P":
                a = np.asarray(im.convert("RGBA" if "transparency" in im.info else "RGB"))
            elif mode in ("1",):
                a = np.asarray(im.convert("L"))
            else:
                raise PhotoError(f"'{path}': unsupported image mode {mode} (use 8/16-bit "
                                 f"grey or RGB, or a float TIFF/EXR)")
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError) as exc:
        raise PhotoError(f"cannot read '{path}': {' '.join(str(exc).split())}") from None
    return (a[..., None] if a.ndim == 2 else a), icc


def _tiff_axes(axes: str, shape, path) -> str:
    """The axes of a TIFF's first image series with the length-1 ones dropped: ``YX``
    (grey), ``YXS`` (samples interleaved) or ``SYX`` (planar configuration); anything
    else (several pages or images, a volume) is refused naming the file."""
    kept = "".join(a for a, n in zip(axes, shape) if n != 1 or a in "YX")
    if kept not in ("YX", "YXS", "SYX"):
        raise PhotoError(f"'{path}' holds an image series of shape {tuple(shape)} (axes "
                         f"{axes}): several pages or a volume; a photograph or map is one "
                         f"image (save the one you mean on its own)")
    return kept


#: Peak bytes per pixel of reading a photograph (measured with ``read_photo`` on
#: 4000x3000 files, fresh processes): 8- and 16-bit files 150-153 (the decoded
#: integers, float64 colour and the transfer curve's temporaries), float TIFF 63, EXR
#: 65; what :func:`read_photo` keeps is 24 (float64 RGB). Disparity maps: 13-18 (what
#: :func:`read_disparity` keeps is 8).
READ_BYTES_PER_PX = {"integer": 160, "float": 72, "map": 24}


def header_size(path, what: str = "photograph") -> tuple[int, int]:
    """``(width, height)`` of a JPEG, PNG, TIFF, EXR or ``.npy`` file from its header
    alone (no pixel is decoded), so that its memory is known before it is read.
    Raises :class:`PhotoError` naming the file when the header is unreadable."""
    from mpib_validate.runtime.io.atomic import InputError, check_input

    try:
        p = check_input(path, what)
    except InputError as exc:
        raise PhotoError(str(exc)) from None
    suffix = p.suffix.lower()
    fmt = image_format(p)
    try:
        if suffix == ".npy":
            with open(p, "rb") as fh:
                version = np.lib.format.read_magic(fh)
                shape, _, _ = np.lib.format._read_array_header(fh, version)
            if len(shape) < 2:
                raise PhotoError(f"'{path}': a {what} is a 2-D array, got shape {shape}")
            return int(shape[1]), int(shape[0])
        if fmt == "EXR":
            from mpib_validate.runtime.io.exr import header_size as exr_size

            w, h, _ = exr_size(p)
            return w, h
        if fmt == "TIFF":
            import tifffile

            with tifffile.TiffFile(str(p)) as tf:
                series = tf.series[0]
                _tiff_axes(series.axes, series.shape, path)
                dims = [n for a, n in zip(series.axes, series.shape) if a in "YX"]
            return int(dims[1]), int(dims[0])
        if fmt == "PNG":
            head = png_dimensions(p)
            if head is not None:
                return head
        from PIL import Image

        with Image.open(p) as im:  # reads the header only
            w, h = im.size
            if _exif_transposes(im):
                w, h = h, w
            return int(w), int(h)
    except PhotoError:
        raise
    except Exception as exc:  # noqa: BLE001 - Pillow, tifffile and numpy raise many types
        raise PhotoError(f"cannot read '{path}': {' '.join(str(exc).split())[:200]}") from None


def _exif_transposes(im) -> bool:
    """Whether the EXIF orientation (5 to 8) swaps the width and the height, as
    ``ImageOps.exif_transpose`` will."""
    try:
        return int(im.getexif().get(0x0112, 1)) in (5, 6, 7, 8)
    except Exception:  # noqa: BLE001 - a malformed EXIF block is read as stored
        return False


def _bits_of(a: np.ndarray, path) -> int:
    if a.dtype == np.uint8:
        return 8
    if a.dtype == np.uint16:
        return 16
    if np.issubdtype(a.dtype, np.floating):
        return 32
    raise PhotoError(f"'{path}': unsupported sample type {a.dtype} (use 8/16-bit integers "
                     f"or float)")


def read_photo(path, encoding: Encoding | None = None) -> Photo:
    """Read a photograph as linear radiance.

    Integer files (JPEG, PNG, 8/16-bit TIFF) are decoded with ``encoding`` (default
    sRGB); float TIFF and EXR hold linear radiance (``encoding`` must then be None or
    linear). Grey images are repeated into three channels. An alpha channel that is
    everywhere opaque is dropped; otherwise it is the film alpha (``Photo.alpha``,
    linear coverage). Raises :class:`PhotoError` naming the file for unreadable files,
    unsupported layouts and NaN or infinite values.
    """
    from mpib_validate.runtime.io.atomic import InputError, check_input

    fmt = image_format(path)
    if fmt is None:
        raise PhotoError(f"'{path}': unknown image type (use .jpg, .png, .tif or .exr)")
    try:
        check_input(path, "photograph")
    except InputError as exc:
        raise PhotoError(str(exc)) from None
    if fmt == "EXR":
        if encoding is not None and encoding.name != "linear":
            raise PhotoError(f"'{path}' is an EXR, which holds linear radiance: drop "
                             f"--gamma / --encoding {encoding.name}")
        from mpib_validate.runtime.refocus import read_colour

        rgba = read_colour(path).astype(np.float64)
        alpha = np.clip(rgba[..., 3], 0.0, 1.0)
        opaque = bool(np.all(alpha >= 1.0))
        rgb = rgba[..., :3] if opaque else np.divide(
            rgba[..., :3], alpha[..., None], out=np.zeros_like(rgba[..., :3]),
            where=alpha[..., None] > 0)  # EXR colour is premultiplied
        return Photo(rgb, None if opaque else alpha, 32, fmt, Encoding("linear"), str(path))
    a, icc = _read_integer_pixels(path)
    bits = _bits_of(a, path)
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise PhotoError(f"'{path}' is empty ({a.shape[1]}x{a.shape[0]} pixels)")
    C = a.shape[2]
    if C not in (1, 2, 3, 4):
        raise PhotoError(f"'{path}' has {C} channels; a photograph has 1 (grey), 3 (RGB) "
                         f"or 4 (RGBA)")
    if bits == 32:
        if encoding is not None and encoding.name != "linear":
            raise PhotoError(f"'{path}' is a float image, read as linear radiance: drop "
                             f"--gamma / --encoding {encoding.name}")
        encoding, v = Encoding("linear"), a.astype(np.float64)
        bad = ~np.isfinite(v)
        if bad.any():
            y, x, _ = np.argwhere(bad)[0]
            raise PhotoError(f"'{path}': {int(bad.sum())} NaN or infinite value(s), first at "
                             f"row {y}, column {x}")
        top = 1.0
    else:
        encoding = encoding or Encoding("srgb")
        v, top = a.astype(np.float64), float((1 << bits) - 1)
    colour = v[..., :3] if C >= 3 else np.repeat(v[..., :1], 3, axis=-1)
    alpha = v[..., -1] / top if C in (2, 4) else None
    if alpha is not None and np.all(alpha >= 1.0):
        alpha = None
    rgb = encoding.decode(colour / top) if bits != 32 else np.maximum(colour, 0.0)
    return Photo(rgb, alpha, bits, fmt, encoding, str(path), icc)


def write_photo(path, rgb: np.ndarray, alpha: np.ndarray | None, encoding: Encoding,
                bits: int = 8, icc_profile: bytes | None = None) -> None:
    """Write straight linear colour (and alpha, None = opaque) as a JPEG, PNG or TIFF by
    the suffix of ``path``, atomically. ``bits``: 8 or 16 (PNG/TIFF; JPEG is always 8).
    The values are encoded and quantised by :func:`encode_photo`. A transparent image
    cannot be a JPEG (:class:`PhotoError`). ``icc_profile``: embedded as is (the
    input's, so that its primaries travel with the picture)."""
    fmt = image_format(path)
    if fmt not in ("JPEG", "PNG", "TIFF"):
        raise PhotoError(f"'{path}': a photograph is written as .jpg, .png or .tif")
    if fmt == "JPEG":
        if alpha is not None:
            raise PhotoError(f"'{path}': JPEG has no alpha and this image is transparent; "
                             f"write a .png")
        bits = 8
    if not (np.isfinite(rgb).all() and (alpha is None or np.isfinite(alpha).all())):
        raise PhotoError(f"'{path}': the image to write holds NaN or infinite values (a bug; "
                         f"please report it with the inputs); nothing was written")
    pixels = encode_photo(rgb, alpha, encoding, bits)
    with atomic_path(path) as tmp:
        if fmt == "TIFF":
            import tifffile

            tifffile.imwrite(str(tmp), pixels, photometric="rgb", iccprofile=icc_profile)
        elif bits == 16:
            tmp.write_bytes(png16_bytes(pixels, icc_profile))
        else:
            from PIL import Image

            im = Image.fromarray(pixels)  # uint8 (H, W, 3|4): RGB or RGBA
            extra = {"icc_profile": icc_profile} if icc_profile else {}
            if fmt == "JPEG":
                im.save(tmp, format="JPEG", quality=JPEG_QUALITY, subsampling=0, **extra)
            else:
                im.save(tmp, format="PNG", **extra)


# ------------------------------------------------------------------------------------
# disparity maps


@dataclass
class ScalarMap:
    """One value per pixel: ``values`` ``(H, W)`` float64, and ``kind``: ``8-bit`` or
    ``16-bit`` (integers scaled to [0, 1] by 255 or 65535: a normalised map) or
    ``float`` (as stored)."""

    values: np.ndarray
    kind: str
    path: str

    @property
    def normalised(self) -> bool:
        return self.kind != "float"


def _one_channel(a: np.ndarray, path, what: str) -> np.ndarray:
    """The single channel of ``(H, W, C)``: grey, grey + opaque alpha, or RGB(A) whose
    colour channels are equal (a grey image stored as RGB). A colour image is refused."""
    C = a.shape[2]
    if C in (2, 4):
        top = np.iinfo(a.dtype).max if np.issubdtype(a.dtype, np.integer) else 1.0
        if np.any(a[..., -1] < top):
            raise PhotoError(f"'{path}': a {what} has no transparency, but this image's "
                             f"alpha is below 1 at {int((a[..., -1] < top).sum())} pixel(s)")
        a = a[..., :-1]
        C -= 1
    if C == 3:
        differ = (a[..., 0] != a[..., 1]) | (a[..., 0] != a[..., 2])
        if differ.any():
            y, x = np.argwhere(differ)[0]
            raise PhotoError(f"'{path}' is a colour image (R, G, B differ at "
                             f"{int(differ.sum())} pixel(s), first at row {y}, column {x}); "
                             f"a {what} is one grey channel (a colour-mapped visualisation? "
                             f"save the network's grey output)")
        return a[..., 0]
    if C != 1:
        raise PhotoError(f"'{path}' has {C} channels; a {what} is one grey channel")
    return a[..., 0]


def read_scalar_map(path, what: str = "disparity map") -> ScalarMap:
    """Read a one-value-per-pixel map: an 8/16-bit grey PNG, JPEG or TIFF (a grey image
    stored as RGB is accepted), a float TIFF, a ``.npy`` array (2-D, or 3-D with one
    channel) or an EXR (its ``Disparity.Y``, ``Y``, equal ``R, G, B`` or only channel).
    Integers are scaled to [0, 1]: ``v / 255`` (8 bit) and ``v / 65535`` (16 bit).
    Raises :class:`PhotoError` naming the file for colour images, NaN or infinite
    values and unreadable files."""
    from mpib_validate.runtime.io.atomic import InputError, check_input

    try:
        p = check_input(path, what)
    except InputError as exc:
        raise PhotoError(str(exc)) from None
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            a = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise PhotoError(f"cannot read '{path}': {' '.join(str(exc).split())}") from None
        if a.ndim == 3 and a.shape[2] == 1:
            a = a[..., 0]
        if a.ndim != 2:
            raise PhotoError(f"'{path}': a {what} is a 2-D array, got shape {a.shape}")
        a = a[..., None]
    elif suffix == ".exr":
        from mpib_validate.runtime.io.exr import read_exr

        img = read_exr(path)
        ch = img.channels
        name = next((n for n in ("Disparity.Y", "Y") if n in ch), None)
        if name is None and {"R", "G", "B"} <= set(ch):
            a = np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
        else:
            if name is None:
                if len(ch) != 1 and "R" not in ch:
                    raise PhotoError(f"'{path}': no single channel for the {what} (Disparity.Y, "
                                     f"Y or R); channels: {', '.join(sorted(ch))}")
                name = "R" if "R" in ch else next(iter(ch))
            a = ch[name][..., None]
    elif image_format(p) in ("JPEG", "PNG", "TIFF"):
        a, _ = _read_integer_pixels(p)
    else:
        raise PhotoError(f"'{path}': unknown {what} type (use .png, .jpg, .tif, .exr or .npy)")
    bits = 32 if suffix in (".exr",) else _bits_of(a, path)
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise PhotoError(f"'{path}': the {what} is empty ({a.shape[1]}x{a.shape[0]} pixels)")
    v = _one_channel(a, path, what).astype(np.float64)
    if bits == 32:
        bad = ~np.isfinite(v)
        if bad.any():
            y, x = np.argwhere(bad)[0]
            raise PhotoError(f"'{path}': the {what} is NaN or infinite at {int(bad.sum())} "
                             f"pixel(s), first at row {y}, column {x}")
        return ScalarMap(v, "float", str(path))
    return ScalarMap(v / float((1 << bits) - 1), f"{bits}-bit", str(path))


def read_disparity(path, shape, normalised: bool, any_size: bool = False) -> ScalarMap:
    """A disparity map for a ``shape = (H, W)`` photograph (:func:`read_scalar_map`),
    checked: the same size (with ``any_size``, any size of the same aspect ratio, for
    the caller to upsample: the map's sides scaled to the photograph's width match its
    height to within one of the map's pixels), no negative value (disparity ``1/Z`` is
    0 at infinity and positive nearer), and with ``normalised`` (the paper's ``K`` convention) every value
    in [0, 1]. A float map outside [0, 1] is refused then rather than rescaled: its
    scale sets the blur, and guessing it would change ``K``'s meaning; give
    ``--blur-parameter`` (pixels per unit of the map's own disparity) instead. A
    constant map is allowed (everything on one plane). Raises :class:`PhotoError`."""
    m = read_scalar_map(path, "disparity map")
    h, w = m.values.shape
    H, W = shape
    if (h, w) != (H, W):
        if not any_size:
            raise PhotoError(f"disparity map '{path}' is {w}x{h} but the photograph is "
                             f"{W}x{H}; resize it to the photograph")
        if abs(h * W / w - H) > max(1.0, W / w) or abs(w * H / h - W) > max(1.0, H / h):
            raise PhotoError(f"disparity map '{path}' is {w}x{h}, another aspect ratio than "
                             f"the {W}x{H} photograph's; give a map of the photograph's "
                             f"shape (any resolution)")
    lo, hi = float(m.values.min()), float(m.values.max())
    if lo < 0:
        y, x = np.argwhere(m.values < 0)[0]
        raise PhotoError(f"disparity map '{path}' has negative values (min {lo:.4g} at row "
                         f"{y}, column {x}); disparity is 0 at infinity and grows nearer")
    if normalised and hi > 1.0:
        raise PhotoError(f"disparity map '{path}' reaches {hi:.4g}, above 1: --K is per unit "
                         f"of a [0, 1] normalised disparity; normalise the map, or give "
                         f"--blur-parameter in pixels per unit of its values")
    return m


#: The largest overshoot (photograph pixels) that :func:`shrink_overshoot` takes: a
#: network's outline overshoots by a pixel or two of its own 384 to 518 px map, some 16 px
#: of a 4000 px photograph; four times that is no overshoot but a wrong map.
MAX_OVERSHOOT_PX = 64


def shrink_overshoot(disparity: np.ndarray, px: int) -> np.ndarray:
    """A predicted disparity map whose near side overshoots the objects' outlines by
    ``px`` pixels, brought back: the grey erosion ``d'(x) = min_{|u|, |v| <= px}
    d(x + (u, v))`` (the minimum over a ``(2 px + 1)^2`` square, the border repeated),
    which moves every edge between a nearer (larger ``d``) and a farther surface by
    ``px`` pixels into the nearer one. Units as ``disparity``.

    A network's map that is fattened there keeps a strip of background on the near side
    of an in-focus object; the refinement
    (:func:`mpib_validate.runtime.layers.refine.refine_disparity`) moves an edge by 3 px
    at most, so the strip stays in focus, sharp inside the blur around it. On a map that
    does not overshoot, the erosion cuts the objects' outlines instead (docs/photos.md
    gives both, measured)."""
    from scipy import ndimage

    px = int(px)
    if not 0 <= px <= MAX_OVERSHOOT_PX:
        raise ValueError(f"the overshoot must be 0 to {MAX_OVERSHOOT_PX} px, got {px}")
    d = np.asarray(disparity, np.float64)
    if px == 0:
        return d.copy()
    return ndimage.grey_erosion(d, size=(2 * px + 1, 2 * px + 1), mode="nearest")


def upsample_disparity(disparity: np.ndarray, shape) -> np.ndarray:
    """A low-resolution disparity map ``(h, w)`` (a network's, 384 to 518 px) brought to
    the photograph's ``shape = (H, W)`` by bilinear interpolation, pixel centres aligned
    (output pixel ``y`` samples the map at ``(y + 1/2) h / H - 1/2``, edges replicated);
    units as ``disparity``. The image-guided step is
    :func:`mpib_validate.runtime.layers.refine.refine_disparity`, which
    follows and moves the map's edges onto the photograph's colour edges. Measured
    against guided-filter upsampling (He et al. 2013, the coefficients fitted at the
    map's resolution and applied to the full-resolution photograph, eps 1e-3 and 1e-2)
    on three scikit-image photographs with network-like maps 4x down, followed by the
    default refinement (PSNR against the exact-depth render, focus near): bilinear
    38.4 / 32.7 / 37.2 dB, guided 35.1-35.4 / 32.4 / 36.2-36.6 dB: on a map that the
    network already blurred, the guided filter's linear colour model copies texture and
    halos into the disparity, which the refinement then takes for edges. Joint bilateral
    upsampling (Kopf et al. 2007: 5x5 map pixels, spatial sigma 1 map pixel, range sigma
    0.1 on the refinement's colour guide) does not win clearly (docs/photos.md): fewer
    sharp remnants in all, and a higher mean PSNR on three of the four photographs of
    the remnant table, but -1.6 dB on the astronaut and -0.3 to -0.4 dB pooled on
    unfattened maps, at 0.55 CPU s against 0.015 s at 2000x1333."""
    from PIL import Image

    low = np.asarray(disparity, np.float32)
    H, W = shape
    return np.asarray(Image.fromarray(low).resize((W, H), Image.BILINEAR), np.float64)


def output_bits(photo: Photo, path) -> int:
    """Bit depth of an output written in the input's encoding: JPEG 8; PNG and TIFF 16
    for a 16-bit or float input, else 8."""
    if image_format(path) == "JPEG":
        return 8
    return 16 if photo.bits >= 16 else 8

