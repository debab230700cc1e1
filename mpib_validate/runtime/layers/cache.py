"""An on-disk cache of built MPIs, for scripted focus pulls (``mpib refocus --mpi-cache DIR``).

An MPI depends on the passes' pixels, the preset, the far limit, the background render
and the blur parameter ``A``, not on the focus (see :mod:`mpib_validate.runtime.session`). The
cache key is the SHA-256 of all of these (the pixels by content:
:func:`passes_digest`, so a re-saved identical file still hits and
an edited one never does). ``A`` is part of the key exactly: a cached MPI gives the
output a fresh run gives, to the last bit. Each entry is two files, ``<key>.npz`` (the
layers, :func:`mpib_validate.runtime.layers.mpi.save_mpi`) and ``<key>.json`` (what the output's
header needs: the builder's info, opacity, disparity range), each written atomically;
an entry that cannot be read is rebuilt (and replaced). Size on disk: about the MPI's
memory (16 B per stored layer pixel; 166 MB for the 1920x1080 benchmark MPI).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

#: Bumped when the MPI builder or the entry format changes, so old entries miss.
FORMAT = 2  # 2: the entry records the input's pixel model


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


def load(folder, key: str):
    """The cached :class:`mpib_validate.runtime.refocus.BuiltMPI`, or None when absent or
    unreadable."""
    from mpib_validate.runtime.layers.mpi import load_mpi
    from mpib_validate.runtime.layers.passes import PassesInfo
    from mpib_validate.runtime.refocus import BuiltMPI

    npz, meta = entry_paths(folder, key)
    if not (npz.is_file() and meta.is_file()):
        return None
    try:
        m = json.loads(meta.read_text())
        mpi = load_mpi(npz)
        info = PassesInfo(planes=int(m["planes"]), fill_fraction=float(m["fill_fraction"]),
                          edge_fraction=float(m["edge_fraction"]), seconds=float(m["seconds"]))
        return BuiltMPI(mpi, bool(m["opaque"]), np.array(m["disparity_range"], np.float64),
                        info, float(m["blur_parameter"]), str(m["pixel_model"]))
    except (OSError, ValueError, KeyError, TypeError, EOFError):
        return None


def store(folder, key: str, built) -> list[Path]:
    """Write an entry (the layers first, then the JSON that makes it visible)."""
    from mpib_validate.runtime.io.atomic import write_text
    from mpib_validate.runtime.layers.mpi import save_mpi

    npz, meta = entry_paths(folder, key)
    save_mpi(built.mpi, npz)
    D = np.asarray(built.disparity)
    m = {"format": FORMAT, "planes": built.info.planes,
         "fill_fraction": built.info.fill_fraction, "edge_fraction": built.info.edge_fraction,
         "seconds": built.info.seconds, "opaque": built.opaque,
         "disparity_range": [float(D.min()), float(D.max())],
         "blur_parameter": built.blur_parameter, "pixel_model": built.pixel_model}
    write_text(meta, json.dumps(m))
    return [npz, meta]


def refocus_cached(passes, blur_parameter: float, focus_disparity: float, folder,
                   preset: str = "default", far_limit: float | None = None, background=None,
                   progress=None, refine: str | None = None):
    """:func:`mpib_validate.runtime.refocus.refocus` with the MPI taken from, or added to, the
    cache in ``folder``. Returns ``(result, reused, entry)``: the result (equal to a
    fresh refocus), whether the MPI came from the cache, and its ``.npz`` path."""
    import time

    from mpib_validate.runtime.layers.passes import DEFAULT_FAR_LIMIT
    from mpib_validate.runtime.refocus import (RefocusResult, _check_camera, build_mpi, render_built,
                                       result_info)

    far_limit = DEFAULT_FAR_LIMIT if far_limit is None else far_limit
    _check_camera(blur_parameter, focus_disparity)
    t0 = time.perf_counter()
    # the refinement changes the MPI: it is part of the preset's name in the key
    named = preset if refine in (None, "off") else f"{preset}+refine={refine}"
    key = cache_key(passes_digest(passes, background), named, far_limit, blur_parameter)
    built = load(folder, key)
    reused = built is not None
    second = None if progress is None else (lambda f: progress(0.5 + 0.5 * f))  # noqa: E731
    if built is None:
        first = None if progress is None else (lambda f: progress(0.5 * f))  # noqa: E731
        built = build_mpi(passes, blur_parameter, preset, far_limit, first, background,
                          refine)
        store(folder, key, built)
    img = render_built(built, blur_parameter, focus_disparity, preset, second)
    info = result_info(passes, built, preset, blur_parameter, focus_disparity,
                       time.perf_counter() - t0)
    info["mpi_cache"] = {"entry": str(entry_paths(folder, key)[0]), "reused": reused}
    return RefocusResult(img, info), reused, entry_paths(folder, key)[0]
