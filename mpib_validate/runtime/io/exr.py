"""OpenEXR input/output (pure I/O, no image processing).

Conventions
-----------
* Pixel values are **linear scene radiance** (no transfer curve, no
  clamping).  Depth channels hold whatever distance the renderer wrote, in
  scene units; this module does not interpret them.  Nothing here converts,
  normalises, flips or tone-maps anything.
* Every channel is a 2-D ``(H, W)`` numpy array, row 0 at the *top* of the
  image (EXR ``INCREASING_Y`` order), indexed ``[y, x]``.  Arrays cover the
  file's data window; it is checked only that every channel has the same
  shape (``header["dataWindow"]`` / ``["displayWindow"]`` are kept as read).
* dtypes are kept as stored: ``float32`` (FLOAT), ``float16`` (HALF) or
  ``uint32`` (UINT).  Non-finite values are data and pass through untouched.
* Channel names are fully qualified.  A single-part file written by
  :func:`write_exr` has names exactly as written (``"R"``, ``"Depth.Z"``,
  ``"AllInFocus.R"`` ...).  In a multi-part file (Blender 5.0 writes
  multilayer EXR as one part per pass, part ``"ViewLayer.Combined"`` with
  channels ``"ViewLayer.Combined.R"`` ...) every channel of a *named* part is
  reported as ``"<part name>.<channel>"`` unless the stored channel name
  already starts with ``"<part name>."``.  The rule is applied to every part
  that has a name, also in a single-part file with a ``name`` attribute.
  Note that the OpenEXR Python binding gives unnamed parts of a multi-part
  file the names ``"Part0"``, ``"Part1"`` ... when it writes them.
* All failures (missing, empty, non-EXR, truncated or corrupt files, deep
  images, bad arguments to :func:`write_exr`) raise :class:`ExrError`, a
  ``ValueError`` whose message names the file.  Caveats of OpenEXR 3.4: on
  truncated/corrupt pixel data it prints diagnostics to stderr (from C, not
  suppressible here) and silently drops the part, which :func:`read_exr`
  detects; a damaged offset table is silently rebuilt; and damage *inside*
  compressed pixel data can decode to wrong pixels without any error (EXR
  has no checksums), so that cannot be detected.

Writing (:func:`write_exr`) produces single-part scanline files, atomically
(temporary file in the target directory + ``os.replace``) and
deterministically (the same data and attributes give byte-identical files;
OpenEXR 3.4 writes no time stamp or other varying attribute).
"""

from __future__ import annotations

import enum
import os
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
import OpenEXR

__all__ = [
    "ExrError",
    "ExrImage",
    "read_exr",
    "write_exr",
    "rgba_from",
    "channels_from_rgba",
    "find_pass",
]

_MAGIC = b"\x76\x2f\x31\x01"

# Header attributes that OpenEXR (or write_exr) sets itself; they cannot be
# given as extra ``attributes``.
_RESERVED_ATTRIBUTES = frozenset(
    {
        "channels",
        "chunkCount",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "name",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "tiles",
        "type",
        "version",
        "view",
    }
)

_COMPRESSIONS = {
    "none": OpenEXR.NO_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
    "pxr24": OpenEXR.PXR24_COMPRESSION,
    "b44": OpenEXR.B44_COMPRESSION,
    "b44a": OpenEXR.B44A_COMPRESSION,
    "dwaa": OpenEXR.DWAA_COMPRESSION,
    "dwab": OpenEXR.DWAB_COMPRESSION,
}


class ExrError(ValueError):
    """An EXR file could not be read or written (message names the file)."""


@dataclass(frozen=True, eq=False)
class ExrImage:
    """The pixels and metadata of one EXR file (all parts merged).

    Attributes
    ----------
    channels:
        Fully qualified channel name -> 2-D ``(H, W)`` array of linear
        radiance (or whatever the pass stores, e.g. depth in scene units),
        dtype ``float32``/``float16``/``uint32`` as stored in the file.
        Insertion order: part by part, channels in file order (alphabetical).
    header:
        The first part's header as plain Python values: enums become their
        name (``"ZIP_COMPRESSION"``), numpy arrays become (nested) tuples, so
        windows are ``((xmin, ymin), (xmax, ymax))`` (inclusive), ``"channels"``
        is the list of the part's stored channel names.  String attributes (e.g. JSON
        metadata written via ``write_exr(attributes=...)``) are ``str``.
    path:
        The path the image was read from.
    """

    channels: dict[str, np.ndarray]
    header: dict[str, Any]
    path: str

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` shared by all channels."""
        first = next(iter(self.channels.values()))
        return (int(first.shape[0]), int(first.shape[1]))


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------


def _plain(value: Any) -> Any:
    """Convert an OpenEXR header value to plain Python where possible."""
    if isinstance(value, np.ndarray):
        return _plain(tuple(value.tolist()))
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, list)):
        converted = [_plain(v) for v in value]
        return tuple(converted) if isinstance(value, tuple) else converted
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, OpenEXR.Channel):
        return value.name
    if isinstance(value, enum.Enum):
        return value.name
    # pybind11 enums (Compression, LineOrder, Storage, ...) are not
    # enum.Enum but have a ``name`` and ``__members__``.
    if hasattr(type(value), "__members__") and hasattr(value, "name"):
        return str(value.name)
    return value


def _storage_name(value: Any) -> str:
    return str(getattr(value, "name", value))


def _check_file(path: str) -> None:
    """Raise ExrError for the cheap-to-diagnose failures, before OpenEXR: a missing
    file, anything but a regular file (a FIFO would block the open forever), an empty
    file, a bad magic number."""
    from mpib_validate.runtime.io.atomic import InputError, check_input

    try:
        check_input(path, "EXR")
    except InputError as exc:
        raise ExrError(str(exc)) from None
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise ExrError(f"cannot read EXR {path!r}: {exc.strerror or exc}") from exc
    if len(magic) == 0:
        raise ExrError(f"cannot read EXR {path!r}: file is empty")
    if magic != _MAGIC:
        raise ExrError(f"cannot read EXR {path!r}: not an OpenEXR file (bad magic number)")


def image_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """``(width, height)`` of the first part's data window, from the header alone.
    Raises :class:`ExrError` (message contains the path) like :func:`read_exr`."""
    path = os.fspath(path)
    _check_file(path)
    try:
        head = OpenEXR.File(path, separate_channels=True, header_only=True)
        (x0, y0), (x1, y1) = head.parts[0].header["dataWindow"]
    except Exception as exc:  # RuntimeError/ValueError/KeyError/IndexError from the binding
        raise ExrError(f"cannot read EXR {path!r}: corrupt or unreadable header ({exc})") from exc
    return int(x1) - int(x0) + 1, int(y1) - int(y0) + 1


def header_size(path: str | os.PathLike[str]) -> tuple[int, int, int]:
    """``(width, height, channels)`` from the header alone: the largest data window of
    any part and the number of channels over all parts, so that what decoding would
    allocate (at most 4 B per channel and pixel) is known before any pixel is read.
    Raises :class:`ExrError` (message contains the path) like :func:`read_exr`."""
    path = os.fspath(path)
    _check_file(path)
    try:
        head = OpenEXR.File(path, separate_channels=True, header_only=True)
        width = height = channels = 0
        for part in head.parts:
            (x0, y0), (x1, y1) = part.header["dataWindow"]
            width = max(width, int(x1) - int(x0) + 1)
            height = max(height, int(y1) - int(y0) + 1)
            channels += len(part.header.get("channels", []))
    except Exception as exc:  # RuntimeError/ValueError/KeyError/IndexError from the binding
        raise ExrError(f"cannot read EXR {path!r}: corrupt or unreadable header ({exc})") from exc
    if width < 1 or height < 1:
        raise ExrError(f"cannot read EXR {path!r}: empty data window ({width}x{height})")
    return width, height, max(channels, 1)


def read_exr(path: str | os.PathLike[str]) -> ExrImage:
    """Read every channel of every part of an EXR file.

    Channels are read separately (``R``, ``G``, ``B``, ``A`` are never grouped
    into one array).  For multi-part files the channel names are qualified
    with the part name as described in the module docstring; two parts that
    produce the same full name raise :class:`ExrError`.  All channels must
    have the same ``(H, W)`` shape (no subsampled channels, no differing data
    windows).  Deep images are refused.

    Raises :class:`ExrError` (message contains the path) for a missing, empty,
    non-EXR, truncated or corrupt file.
    """
    path = os.fspath(path)
    _check_file(path)

    # Header pass: tells how many parts the file declares, so that parts the
    # binding silently drops on a pixel-read error can be detected.
    try:
        head = OpenEXR.File(path, separate_channels=True, header_only=True)
        head_parts = list(head.parts)
    except Exception as exc:  # RuntimeError/ValueError/... from the binding
        raise ExrError(f"cannot read EXR {path!r}: corrupt or unreadable header ({exc})") from exc
    if not head_parts:
        raise ExrError(f"cannot read EXR {path!r}: file has no parts")
    for index, part in enumerate(head_parts):
        storage = _storage_name(part.type())
        if storage.startswith("deep"):
            raise ExrError(
                f"cannot read EXR {path!r}: part {index} ({part.name()!r}) is a deep image "
                f"({storage}); deep images are not supported"
            )

    try:
        exr = OpenEXR.File(path, separate_channels=True, header_only=False)
        parts = list(exr.parts)
    except Exception as exc:
        raise ExrError(f"cannot read EXR {path!r}: corrupt pixel data ({exc})") from exc
    # OpenEXR 3.4 does not raise on truncated/corrupt pixel data: it prints a
    # warning to stderr and leaves the failing part (and later ones) out.
    if len(parts) != len(head_parts):
        raise ExrError(
            f"cannot read EXR {path!r}: truncated or corrupt pixel data "
            f"(header declares {len(head_parts)} part(s), only {len(parts)} could be decoded)"
        )

    channels: dict[str, np.ndarray] = {}
    origin: dict[str, str] = {}
    shape: tuple[int, ...] | None = None
    first_channel = ""
    for index, part in enumerate(parts):
        part_name = part.name() or ""
        declared = [_plain(c) for c in part.header.get("channels", [])]
        stored = dict(part.channels)
        missing = [n for n in declared if n not in stored]
        if missing:
            raise ExrError(
                f"cannot read EXR {path!r}: truncated or corrupt pixel data "
                f"(part {index} lacks channel(s) {missing})"
            )
        for raw_name, channel in stored.items():
            if part_name and not raw_name.startswith(part_name + "."):
                full = f"{part_name}.{raw_name}"
            else:
                full = raw_name
            where = f"part {index} ({part_name!r}) channel {raw_name!r}"
            if full in channels:
                raise ExrError(
                    f"cannot read EXR {path!r}: channel name {full!r} occurs twice "
                    f"({origin[full]} and {where})"
                )
            pixels = channel.pixels
            if pixels is None or not isinstance(pixels, np.ndarray) or pixels.ndim != 2:
                raise ExrError(
                    f"cannot read EXR {path!r}: {where} has no 2-D pixel array "
                    f"(got {type(pixels).__name__}"
                    f"{'' if not isinstance(pixels, np.ndarray) else ' of shape ' + str(pixels.shape)})"
                )
            if pixels.dtype not in (np.float32, np.float16, np.uint32):
                raise ExrError(f"cannot read EXR {path!r}: {where} has unsupported dtype {pixels.dtype}")
            if shape is None:
                shape, first_channel = pixels.shape, full
            elif pixels.shape != shape:
                raise ExrError(
                    f"cannot read EXR {path!r}: channel {full!r} has shape {pixels.shape} but "
                    f"{first_channel!r} has {shape} (subsampled channels or differing data "
                    f"windows are not supported)"
                )
            channels[full] = pixels
            origin[full] = where
    if not channels:
        raise ExrError(f"cannot read EXR {path!r}: file has no channels")

    header = {str(k): _plain(v) for k, v in parts[0].header.items()}
    return ExrImage(channels=channels, header=header, path=path)


# --------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------


_MAX_NAME_BYTES = 255  # OpenEXR silently truncates longer names


def _check_name(path: str, what: str, name: Any) -> None:
    if not isinstance(name, str) or not name:
        raise ExrError(f"cannot write EXR {path!r}: {what} names must be non-empty strings, got {name!r}")
    if "\0" in name:
        raise ExrError(f"cannot write EXR {path!r}: {what} name {name!r} contains a NUL character")
    if len(name.encode("utf-8")) > _MAX_NAME_BYTES:
        raise ExrError(
            f"cannot write EXR {path!r}: {what} name {name[:40]!r}... is longer than "
            f"{_MAX_NAME_BYTES} UTF-8 bytes (OpenEXR would truncate it)"
        )


def _compression(value: Any, path: str) -> Any:
    if isinstance(value, OpenEXR.Compression):
        return value
    if isinstance(value, str):
        key = value.lower().removesuffix("_compression")
        if key in _COMPRESSIONS:
            return _COMPRESSIONS[key]
    raise ExrError(
        f"cannot write EXR {path!r}: unknown compression {value!r}; "
        f"use one of {sorted(_COMPRESSIONS)}"
    )


def _prepare_channels(
    path: str, channels: Mapping[str, np.ndarray], half: bool | set[str] | frozenset[str]
) -> dict[str, np.ndarray]:
    if not channels:
        raise ExrError(f"cannot write EXR {path!r}: no channels given")
    if isinstance(half, bool):
        half_names = None
    else:
        half_names = set(half)
        unknown = sorted(half_names - set(channels))
        if unknown:
            raise ExrError(
                f"cannot write EXR {path!r}: half= names unknown channel(s) {unknown}; "
                f"channels: {sorted(channels)}"
            )

    out: dict[str, np.ndarray] = {}
    shape: tuple[int, ...] | None = None
    first = ""
    for name, array in channels.items():
        _check_name(path, "channel", name)
        arr = np.asarray(array)
        if arr.ndim != 2:
            raise ExrError(
                f"cannot write EXR {path!r}: channel {name!r} must be a 2-D (H, W) array, "
                f"got shape {arr.shape}"
            )
        if arr.shape[0] < 1 or arr.shape[1] < 1:
            raise ExrError(f"cannot write EXR {path!r}: channel {name!r} is empty (shape {arr.shape})")
        if shape is None:
            shape, first = arr.shape, name
        elif arr.shape != shape:
            raise ExrError(
                f"cannot write EXR {path!r}: channel {name!r} has shape {arr.shape} but "
                f"channel {first!r} has shape {shape}; all channels must have the same shape"
            )
        kind = arr.dtype
        if kind == np.float64:
            arr = arr.astype(np.float32)
        elif kind == np.uint32:
            if half_names is not None and name in half_names:
                raise ExrError(f"cannot write EXR {path!r}: half= names uint32 channel {name!r}")
        elif kind not in (np.float32, np.float16):
            raise ExrError(
                f"cannot write EXR {path!r}: channel {name!r} has dtype {arr.dtype}; "
                f"supported are float16, float32, float64 (stored as float32) and uint32"
            )
        if arr.dtype.kind == "f" and (half is True or (half_names is not None and name in half_names)):
            with np.errstate(over="ignore"):  # |x| > 65504 becomes +-inf, as in any half cast
                arr = arr.astype(np.float16)
        # Native byte order and C order are required: the binding writes
        # strided (e.g. rgba[..., 0]) arrays wrongly, without an error.
        arr = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("="))
        out[name] = arr
    return out


#: Scan lines per chunk of each compression (OpenEXR file layout), by its enum value.
_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}


def _check_complete(path: str) -> None:
    """Raise :class:`ExrError` unless the single-part scanline file at ``path`` holds
    every chunk its header and offset table promise, ending exactly at the end of the
    file. OpenEXR can return from a write whose last buffered bytes were never written
    (a full disk: measured under a file-size limit, an empty or truncated file and no
    error), so what it wrote is checked before it is placed."""
    import mmap

    where = f"cannot write EXR {path!r}: the written file is incomplete (a full disk?)"
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size < 8:
            raise ExrError(where)
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            if data[:4] != _MAGIC:
                raise ExrError(where)
            _check_chunks(data, size, where)


def _check_chunks(data, size: int, where: str) -> None:
    """The walk of :func:`_check_complete` over the file's bytes ``data``."""
    import struct

    def index(byte: bytes, start: int) -> int:
        i = data.find(byte, start)
        if i < 0:
            raise ValueError("no end")
        return i

    pos = 8
    window = compression = None
    try:
        while data[pos] != 0:
            name_end = index(b"\0", pos)
            type_end = index(b"\0", name_end + 1)
            (n,) = struct.unpack_from("<i", data, type_end + 1)
            value = type_end + 5
            name = data[pos:name_end]
            if name == b"dataWindow":
                window = struct.unpack_from("<4i", data, value)
            elif name == b"compression":
                compression = data[value]
            pos = value + n
        pos += 1
        if window is None or compression not in _LINES_PER_CHUNK:
            return  # not a layout this check knows (write_exr writes none such)
        lines = window[3] - window[1] + 1
        chunks = -(-lines // _LINES_PER_CHUNK[compression])
        offsets = struct.unpack_from(f"<{chunks}Q", data, pos)
        end = pos + 8 * chunks
        for off in offsets:
            if off < end:
                raise ExrError(where)
            _, n = struct.unpack_from("<ii", data, off)
            end = off + 8 + n
        if end != size:
            raise ExrError(where)
    except (IndexError, ValueError, struct.error):
        raise ExrError(where) from None


def write_exr(
    path: str | os.PathLike[str],
    channels: Mapping[str, np.ndarray],
    *,
    half: bool | set[str] = False,
    attributes: Mapping[str, str] | None = None,
    compression: Any = "zip",
) -> None:
    """Write a single-part scanline EXR file, atomically and deterministically.

    Parameters
    ----------
    path:
        Target file.  Parent directories are created.  The data go to a
        temporary file ``.<name>.tmp-<pid>-<random>.exr`` in the same
        directory which is then ``os.replace``-d onto ``path``; on any
        failure the temporary file is removed and an existing ``path`` is
        left untouched.
    channels:
        Channel name -> 2-D ``(H, W)`` array (linear radiance, depth, ...),
        all the same shape; names are written as given (``"R"``,
        ``"Depth.Z"``, ``"AllInFocus.R"``) and must be 1..255 UTF-8 bytes
        without NUL (OpenEXR would silently truncate longer names).  dtypes: float32 and float16 are
        stored as is, float64 is converted to float32, uint32 is stored as
        UINT.  Non-finite values are written unchanged.
    half:
        ``True`` stores every float channel as float16 (HALF); a set names
        the channels to store as float16.  Values beyond the half range
        become ``+-inf``.  float16 input is always stored as float16.
    attributes:
        Extra string header attributes (e.g. JSON metadata).  Names reserved
        by OpenEXR (``channels``, ``compression``, ``dataWindow`` ...) are
        refused.
    compression:
        ``"none"``, ``"rle"``, ``"zips"``, ``"zip"`` (default, lossless),
        ``"piz"``, ``"pxr24"``, ``"b44"``, ``"b44a"``, ``"dwaa"``, ``"dwab"``
        or an ``OpenEXR.Compression`` value.  pxr24/b44/dwa are lossy.

    Raises
    ------
    ExrError
        On invalid arguments (message names the channel and the shapes) or
        if writing fails.
    """
    path = os.fspath(path)
    prepared = _prepare_channels(path, channels, half)
    comp = _compression(compression, path)

    header: dict[str, Any] = {"compression": comp, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        _check_name(path, "attribute", key)
        if key in _RESERVED_ATTRIBUTES:
            raise ExrError(f"cannot write EXR {path!r}: attribute name {key!r} is reserved by OpenEXR")
        if not isinstance(value, str):
            raise ExrError(
                f"cannot write EXR {path!r}: attribute {key!r} must be a str, got {type(value).__name__}"
            )
        header[key] = value

    from mpib_validate.runtime.io.atomic import OutputError, place, replaceable, temporary_beside

    try:
        replaceable(path, "cannot write EXR: the target")
        tmp = temporary_beside(path, ".exr")
    except OutputError as exc:
        raise ExrError(str(exc)) from None
    except OSError as exc:
        raise ExrError(f"cannot write EXR {path!r}: cannot create directory ({exc})") from exc
    try:
        OpenEXR.File(header, prepared).write(str(tmp))
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        _check_complete(str(tmp))
        place(tmp, path)
    except BaseException as exc:
        try:
            os.remove(tmp)
        except OSError:
            pass
        if isinstance(exc, Exception):
            raise ExrError(f"cannot write EXR {path!r}: {exc}") from exc
        raise


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def rgba_from(img: ExrImage, prefix: str = "") -> np.ndarray:
    """Assemble channels ``prefix+"R"``, ``"G"``, ``"B"``, ``"A"`` into ``(H, W, 4)`` float32.

    ``prefix`` is used literally: ``""`` for a plain RGBA file,
    ``"ViewLayer.Combined."`` for Blender's Combined pass, ``"AllInFocus."``
    ... (note the trailing dot).  A missing alpha channel gives alpha 1.
    Values are linear radiance, converted to float32 but otherwise unchanged
    (alpha is *not* divided out or multiplied in).

    Raises :class:`ExrError` naming the file and the missing channel.
    """
    planes = []
    for letter in "RGBA":
        key = prefix + letter
        if key in img.channels:
            planes.append(np.asarray(img.channels[key], dtype=np.float32))
        elif letter == "A":
            planes.append(np.ones(img.shape, dtype=np.float32))
        else:
            raise ExrError(
                f"no channel {key!r} in {img.path!r}; channels: {', '.join(img.channels)}"
            )
    return np.stack(planes, axis=-1)


def channels_from_rgba(rgba: np.ndarray, prefix: str = "") -> dict[str, np.ndarray]:
    """Split an ``(H, W, 3)`` or ``(H, W, 4)`` array into ``{prefix+"R": ..., ...}``.

    The inverse of :func:`rgba_from`, for :func:`write_exr`.  The returned
    arrays are contiguous copies with the input dtype.
    """
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] not in (3, 4):
        raise ExrError(f"expected an (H, W, 3) or (H, W, 4) array, got shape {rgba.shape}")
    return {prefix + letter: np.ascontiguousarray(rgba[..., i]) for i, letter in enumerate("RGBA"[: rgba.shape[2]])}


def find_pass(img: ExrImage, pass_name: str) -> str:
    """Return the name of the one channel holding pass ``pass_name``.

    A channel matches when its name, without the last ``.``-component (the
    channel letter), is ``pass_name`` or ends with ``"." + pass_name``; i.e.
    ``"<pass>.<chan>"`` or ``"<anything>.<pass>.<chan>"``.  For
    ``pass_name == "Depth"`` a bare channel ``"Z"`` also matches.  So the
    Depth pass is found as ``"Z"``, ``"Depth.Z"`` or ``"ViewLayer.Depth.Z"``.
    Matching is case-sensitive.  Meant for single-channel passes: a pass with
    several channels (e.g. ``Combined``) is ambiguous.

    Raises :class:`ExrError` listing the channels if there is no match or
    more than one.
    """
    matches = []
    for name in img.channels:
        stem, dot, _chan = name.rpartition(".")
        if dot and (stem == pass_name or stem.endswith("." + pass_name)):
            matches.append(name)
        elif pass_name == "Depth" and name == "Z":
            matches.append(name)
    if len(matches) == 1:
        return matches[0]
    available = ", ".join(img.channels)
    if not matches:
        raise ExrError(f"no {pass_name} pass in {img.path!r}; channels: {available}")
    raise ExrError(
        f"ambiguous {pass_name} pass in {img.path!r}: {', '.join(matches)} all match; "
        f"channels: {available}"
    )
