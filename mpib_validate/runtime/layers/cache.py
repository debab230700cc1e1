"""An on-disk cache of built MPIs, for scripted focus pulls (``mpib refocus --mpi-cache DIR``).

An MPI depends on the passes' pixels, the preset, the far limit, the background render
and the blur parameter ``A``, not on the focus (see :mod:`mpib_validate.runtime.session`). The
cache key is the SHA-256 of all of these (the pixels by content:
:func:`passes_digest`, so a re-saved identical file still hits and
an edited one never does). ``A`` is part of the key exactly: a cached MPI gives the
output a fresh run gives, to the last bit. Each entry is two files, ``<key>.npz`` (the
layers, :func:`mpib_validate.runtime.layers.mpi.save_mpi`) and ``<key>.json`` (what the output's
header needs: the builder's info, opacity, disparity range), each written atomically;
an entry that cannot be used is rebuilt (and replaced), with a notice. Size on disk: about
the MPI's memory (16 B per stored layer pixel; 166 MB for the 1920x1080 benchmark MPI).

A cache folder may be shared or copied, so an entry is untrusted input. Before an entry
is used, :func:`load` checks that its JSON is an object of this format naming its own
key, that the ``.npz`` has the SHA-256 the JSON records (a truncated, edited or swapped
file fails), that the sizes the archive declares fit the input (the frame, the
channels: 4 for an opaque input, 5 with a film alpha) before anything is decompressed,
that every layer lies inside the canvas at a finite disparity >= 0, and that every value
is finite. Any failure is a notice naming the entry and the reason, and a rebuild.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
from pathlib import Path

import numpy as np

#: Bumped when the MPI builder or the entry format changes, so old entries miss.
FORMAT = 3  # 3: the entry records its key, its frame and the SHA-256 of its layers


def digest_arrays(arrays) -> str:
    """Hex SHA-256 of arrays (dtype, shape and bytes of each; None counts too)."""
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.reshape(-1).view(np.uint8))
    return h.hexdigest()


def passes_digest(passes, background=None) -> str:
    """SHA-256 of the passes' pixels (colour, depth, film alpha, the layered groups) and
    of the background render if any: equal digests mean an MPI built from one serves
    the other. About 0.1 s for 1920x1080."""
    groups = [a for g in (passes.groups or ()) for a in g]
    return digest_arrays([passes.colour, passes.depth, passes.alpha, len(groups)] + groups
                         + ["disparity", passes.disparity, "pixel model", passes.pixel_model]
                         + ["background"] + list(background or ()))


def cache_key(digest: str, preset: str, far_limit: float, blur_parameter: float) -> str:
    """Hex SHA-256 naming one entry: the inputs' digest
    (:func:`passes_digest`, background included), the preset, the
    far limit and ``A`` (floats by ``repr``: exact)."""
    text = json.dumps([FORMAT, digest, preset, repr(float(far_limit)),
                       repr(float(blur_parameter))])
    return hashlib.sha256(text.encode()).hexdigest()


def entry_paths(folder, key: str) -> tuple[Path, Path]:
    folder = Path(folder)
    return folder / f"{key}.npz", folder / f"{key}.json"


class EntryError(ValueError):
    """An unusable cache entry; the message says why."""


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _declared_shapes(z) -> dict:
    """``{name: shape}`` of the arrays of an open ``.npz``, read from each member's
    ``.npy`` header (nothing is decompressed beyond the header)."""
    from numpy.lib import format as npy_format

    shapes = {}
    for name in z.files:
        with z.zip.open(f"{name}.npy") as fh:
            version = npy_format.read_magic(fh)
            shape, _, dtype = npy_format._read_array_header(fh, version)
        if dtype.hasobject:
            raise EntryError(f"array {name!r} holds Python objects")
        shapes[name] = (tuple(shape), dtype)
    return shapes


def _check_entry(npz: Path, m, key: str, frame: tuple[int, int], channels: int | None):
    """The MPI of a cache entry after the checks in the module's docstring; raises
    :class:`EntryError` saying what is wrong."""
    from mpib_validate.runtime.budget import format_bytes, memory_limit
    from mpib_validate.runtime.layers.mpi import MPI, Layer

    if not isinstance(m, dict) or m.get("format") != FORMAT or m.get("key") != key:
        raise EntryError("its description is of another format or another entry")
    if m.get("sha256") != file_sha256(npz):
        raise EntryError("its layers file does not match its recorded checksum")
    H, W = frame
    if [m.get("height"), m.get("width")] != [H, W]:
        raise EntryError(f"it is for a {m.get('width')}x{m.get('height')} frame, the input is "
                         f"{W}x{H}")
    with np.load(npz, allow_pickle=False) as z:
        shapes = _declared_shapes(z)
        if shapes.get("meta") != ((4,), np.dtype(np.int64)):
            raise EntryError("it has no valid size record")
        h, w, margin, n = (int(v) for v in z["meta"])
        if (h, w) != (H, W) or not 0 <= margin <= 1 << 16 or not 0 <= n <= 1 << 16:
            raise EntryError(f"its layers are for a {w}x{h} frame (margin {margin}, {n} "
                             f"layers), the input is {W}x{H}")
        hc, wc = H + 2 * margin, W + 2 * margin
        declared = sum(4 * math.prod(s) for name, (s, _) in shapes.items()
                       if name.startswith("rgba"))
        if declared > memory_limit():
            raise EntryError(f"its layers would take {format_bytes(declared)} of memory, more "
                             f"than the limit")
        mpi = MPI(H, W, margin)
        if "colour_max" in z.files:
            mpi.colour_max = z["colour_max"]
            if not np.all(np.isfinite(mpi.colour_max)):
                raise EntryError("its colour bound is not finite")
        for i in range(n):
            (shape, dtype), where_decl = shapes.get(f"rgba{i}", ((), None)), shapes.get(f"where{i}")
            if (dtype != np.float32 or len(shape) != 3 or where_decl is None
                    or where_decl[0] not in ((3,), (4,)) or where_decl[1] != np.float64):
                raise EntryError(f"layer {i} is missing or not float32 (h, w, c)")
            where = z[f"where{i}"]
            if not np.all(np.isfinite(where)):
                raise EntryError(f"layer {i}'s position is not finite")
            d, y0, x0 = float(where[0]), int(where[1]), int(where[2])
            lh, lw, c = shape
            if channels is not None and c != channels:
                raise EntryError(f"layer {i} has {c} channels, the input needs {channels}")
            if c not in (4, 5) or d < 0 or not (0 <= y0 and 0 <= x0 and y0 + lh <= hc
                                                and x0 + lw <= wc):
                raise EntryError(f"layer {i} lies outside the {wc}x{hc} canvas or has "
                                 f"disparity {d}")
            rgba = z[f"rgba{i}"]
            if not np.all(np.isfinite(rgba)):
                raise EntryError(f"layer {i} holds NaN or infinite values")
            group = int(where[3]) if len(where) > 3 and where[3] >= 0 else None
            mpi.layers.append(Layer(d, rgba, y0, x0, group))
    return mpi


def load(folder, key: str, frame: tuple[int, int] | None = None,
         channels: int | None = None):
    """``(entry, notice)``: the cached :class:`mpib_validate.runtime.refocus.BuiltMPI`
    checked against the input (``frame = (H, W)``, ``channels`` per layer when known),
    or None with a one-line notice saying why it is rebuilt (None, None when absent)."""
    from mpib_validate.runtime.layers.passes import PassesInfo
    from mpib_validate.runtime.refocus import BuiltMPI

    npz, meta = entry_paths(folder, key)
    if not (npz.exists() or meta.exists()):
        return None, None
    try:
        if not (npz.is_file() and meta.is_file()):
            raise EntryError("one of its two files is missing or not a regular file")
        if meta.stat().st_size > 1 << 16:
            raise EntryError("its description is too large")
        try:
            m = json.loads(meta.read_text())
        except RecursionError:
            raise EntryError("its description is nested too deeply") from None
        if frame is None:
            frame = (m.get("height"), m.get("width")) if isinstance(m, dict) else (None, None)
        mpi = _check_entry(npz, m, key, frame, channels)
        info = PassesInfo(planes=int(m["planes"]), fill_fraction=float(m["fill_fraction"]),
                          edge_fraction=float(m["edge_fraction"]), seconds=float(m["seconds"]))
        D = np.array(m["disparity_range"], np.float64)
        A = float(m["blur_parameter"])
        if D.shape != (2,) or not np.all(np.isfinite(D)) or not (A > 0 and math.isfinite(A)):
            raise EntryError("its disparity range or blur parameter is not valid")
        if m["pixel_model"] not in ("texel", "continuous"):
            raise EntryError(f"unknown pixel model {m['pixel_model']!r}")
        return BuiltMPI(mpi, bool(m["opaque"]), D, info, A, str(m["pixel_model"])), None
    except (OSError, ValueError, KeyError, TypeError, EOFError, OverflowError,
            zipfile.BadZipFile) as e:
        reason = str(e) if isinstance(e, EntryError) else f"it cannot be read ({type(e).__name__})"
        return None, f"MPI cache entry '{npz}' is not used: {reason}; rebuilding it"


def store(folder, key: str, built) -> list[Path]:
    """Write an entry (the layers first, then the JSON that makes it visible)."""
    from mpib_validate.runtime.io.atomic import write_text
    from mpib_validate.runtime.layers.mpi import save_mpi

    npz, meta = entry_paths(folder, key)
    save_mpi(built.mpi, npz)
    D = np.asarray(built.disparity)
    m = {"format": FORMAT, "key": key, "sha256": file_sha256(npz),
         "height": built.mpi.height, "width": built.mpi.width, "planes": built.info.planes,
         "fill_fraction": built.info.fill_fraction, "edge_fraction": built.info.edge_fraction,
         "seconds": built.info.seconds, "opaque": built.opaque,
         "disparity_range": [float(D.min()), float(D.max())],
         "blur_parameter": built.blur_parameter, "pixel_model": built.pixel_model}
    write_text(meta, json.dumps(m))
    return [npz, meta]


class DiskCache:
    """The MPIs of :func:`mpib_validate.runtime.refocus.refocus` kept in ``folder``: pass
    one as its ``cache`` (``refocus(request, cache=DiskCache(folder))``). The result equals a fresh refocus to the last bit; its info gains
    ``mpi_cache``: the entry's ``.npz`` path, whether the MPI came from it, and a
    ``notice`` when an entry was not used (see the module docstring)."""

    def __init__(self, folder):
        self.folder = Path(folder)

    def key(self, request) -> str:
        """The entry's name for ``request`` (:func:`cache_key` of its pixels, background,
        preset with its refinement, far limit and the ``A`` the MPI is built for, the
        aperture's reach: ``request.build_blur_parameter``; the aperture's shape changes
        only the blur)."""
        return cache_key(passes_digest(request.passes, request.background),
                         request.preset_key, request.far_limit, request.build_blur_parameter)

    def fetch(self, request, progress=None):
        """``(built, info)``: the cached MPI of ``request`` (checked against its passes),
        or a new build (then stored, unless the entry's path is not a regular file), and
        ``{"mpi_cache": {"entry": path, "reused": bool[, "notice": line]}}``."""
        from mpib_validate.runtime.refocus import build_mpi

        passes = request.passes
        key = self.key(request)
        npz = entry_paths(self.folder, key)[0]
        channels = None
        if passes.groups is None:  # a film alpha adds a fifth channel (refocus.build_mpi)
            channels = 4 if passes.alpha is None or bool(np.all(passes.alpha >= 1.0)) else 5
        built, notice = load(self.folder, key, passes.colour.shape[:2], channels)
        reused = built is not None
        if built is None:
            built = build_mpi(request, progress)
            if any(p.exists() and not p.is_file() for p in entry_paths(self.folder, key)):
                notice = (f"MPI cache entry '{npz}' is not a regular file; left as it is, the "
                          f"MPI is not cached")
            else:
                store(self.folder, key, built)
        info = {"entry": str(npz), "reused": reused}
        if notice is not None:
            info["notice"] = notice
        return built, {"mpi_cache": info}
