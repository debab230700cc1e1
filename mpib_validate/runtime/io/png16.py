"""16-bit PNG in and out, which Pillow cannot do for colour (it reads 16-bit RGB as 8 bit
and writes 16 bit only for grey): the chunks, zlib and the five PNG filters (PNG spec,
sections 5, 9 and 11), in numpy. Used by :mod:`mpib_validate.runtime.io.photo`."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np


class PngError(ValueError):
    """An unreadable PNG; the message names the file."""


def png_header(path):
    """``(bit depth, colour type, interlace)`` from a PNG's IHDR, or None if not a PNG."""
    with open(path, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return head[24], head[25], head[28]


def png_dimensions(path) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG's IHDR, or None if not a PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


_PNG_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}
#: The most pixels :func:`read_png16` decodes (Pillow's own decompression-bomb limit for
#: the 8-bit files it reads, ``2 * Image.MAX_IMAGE_PIXELS``): about 150 B per pixel
#: while decoding, so a file of a few kB cannot ask for tens of GB. Callers check a
#: memory limit from :func:`png_dimensions` before.
MAX_PIXELS = 2 * 89_478_485


def _unfilter(rows: np.ndarray, W: int, bpp: int, path) -> np.ndarray:
    """The PNG filters undone (PNG spec section 9) for ``rows`` ``(H, 1 + W bpp)`` uint8
    (each row's filter type first). Byte ``(y, x)`` of a pixel depends on the decoded
    pixels left ``(y, x - 1)``, up ``(y - 1, x)`` and up-left, so the pixels of one
    anti-diagonal ``y + x = t`` are independent: the image is decoded in ``H + W - 1``
    vectorised steps, each over one diagonal (every filter type at once)."""
    H = rows.shape[0]
    kinds = rows[:, 0].astype(np.int64)
    if np.any(kinds > 4):
        y = int(np.argmax(kinds > 4))
        raise PngError(f"'{path}': PNG filter type {kinds[y]} in row {y} is not defined "
                         f"(corrupt file?)")
    F = rows[:, 1:].reshape(H, W, bpp).astype(np.int16)
    if not np.any(kinds >= 1):
        return rows[:, 1:].copy()
    # decoded pixels with a zero row above and a zero column to the left
    out = np.zeros((H + 1, W + 1, bpp), np.int16)
    for t in range(H + W - 1):
        ys = np.arange(max(0, t - W + 1), min(t, H - 1) + 1)
        xs = t - ys
        a = out[ys + 1, xs]      # left
        b = out[ys, xs + 1]      # up
        c = out[ys, xs]          # up-left
        k = kinds[ys][:, None]
        p = a + b - c
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
        paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
        pred = np.select([k == 1, k == 2, k == 3, k == 4], [a, b, (a + b) >> 1, paeth], 0)
        out[ys + 1, xs + 1] = (F[ys, xs] + pred) & 0xFF
    return out[1:, 1:].astype(np.uint8).reshape(H, W * bpp)


def read_png16(path) -> tuple[np.ndarray, bytes | None]:
    """A 16-bit PNG (any colour type, not interlaced) as ``(H, W, C)`` uint16, and its
    ICC profile. Pillow reads 16-bit colour PNGs as 8 bit, so these are decoded here
    (zlib + unfilter)."""
    data = Path(path).read_bytes()
    pos, idat, ihdr, icc = 8, [], None, None
    while pos + 8 <= len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR" and len(body) == 13:
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"iCCP" and b"\0" in body:
            try:
                icc = zlib.decompress(body[body.index(b"\0") + 2:])
            except zlib.error:
                icc = None
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + n
    if ihdr is None:
        raise PngError(f"'{path}' is not a readable PNG (no IHDR)")
    W, H, depth, ctype, _, _, interlace = ihdr
    if W < 1 or H < 1 or W * H > MAX_PIXELS:
        raise PngError(f"'{path}': a {W}x{H} PNG ({W * H:,} pixels) is refused; at most "
                       f"{MAX_PIXELS:,} pixels are decoded")
    if depth != 16 or ctype not in _PNG_CHANNELS or interlace:
        raise PngError(f"'{path}': only non-interlaced 16-bit PNGs are decoded here "
                         f"(bit depth {depth}, colour type {ctype}, interlace {interlace})")
    C = _PNG_CHANNELS[ctype]
    bpp, stride = 2 * C, 2 * C * W
    try:
        # no more than the image needs: compressed data that inflates past it (a
        # "zip bomb") is cut there, not held
        raw = np.frombuffer(zlib.decompressobj().decompress(b"".join(idat),
                                                            H * (stride + 1)), np.uint8)
    except zlib.error as exc:
        raise PngError(f"'{path}': corrupt PNG data ({exc})") from None
    if raw.size < H * (stride + 1):
        raise PngError(f"'{path}': truncated PNG ({raw.size} of {H * (stride + 1)} bytes)")
    rows = raw[:H * (stride + 1)].reshape(H, stride + 1)
    out = _unfilter(rows, W, bpp, path)
    return out.view(">u2").reshape(H, W, C).astype(np.uint16), icc


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return (struct.pack(">I", len(body)) + kind + body
            + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF))


def png16_bytes(pixels: np.ndarray, icc_profile: bytes | None = None) -> bytes:
    """A 16-bit RGB or RGBA PNG of ``(H, W, 3|4)`` uint16 (filter None, zlib level 6),
    with the ICC profile if given."""
    H, W, C = pixels.shape
    rows = np.empty((H, 1 + 2 * C * W), np.uint8)
    rows[:, 0] = 0
    rows[:, 1:] = pixels.astype(">u2").view(np.uint8).reshape(H, -1)
    ihdr = struct.pack(">IIBBBBB", W, H, 16, {3: 2, 4: 6}[C], 0, 0, 0)
    iccp = (_png_chunk(b"iCCP", b"ICC profile\0\0" + zlib.compress(icc_profile))
            if icc_profile else b"")
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + iccp
            + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), 6)) + _png_chunk(b"IEND", b""))
