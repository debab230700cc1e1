"""Choosing the Mitsuba variant by probing it in a subprocess first.

Order of preference: ``cuda_ad_rgb`` (a GPU), ``llvm_ad_rgb`` (an LLVM >= 16 library
that Dr.Jit can run kernels with), ``scalar_rgb`` (always, slow: the Python integrator
then runs once per sample). The LLVM library is chosen by
:func:`mpib_validate.runtime.compositor.backend.probe_llvm` *before* mitsuba or drjit is imported here
(drjit loads it at import and aborts the process on LLVM 15), and every variant is
tried in a subprocess that renders a 4x4 image: a failed probe costs a second, never
the caller's process.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from dataclasses import dataclass, field

from mpib_validate.runtime.compositor import backend as _backend

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")

_PROBE = r"""
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "path", "max_depth": 2},
    "sensor": {"type": "thinlens", "fov": 40.0, "aperture_radius": 0.01,
               "focus_distance": 2.0,
               "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}},
               "sampler": {"type": "independent", "sample_count": 4}},
    "card": {"type": "rectangle", "flip_normals": True,
             "to_world": mi.ScalarTransform4f().translate([0, 0, 2]),
             "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
})
img = mi.render(scene, spp=4)
total = sum(float(v) for v in mi.TensorXf(img).numpy().ravel())
print("ok", total)
"""


class MitsubaUnavailable(RuntimeError):
    """Mitsuba is not installed, or no variant (or not the requested one) runs here."""


@dataclass(frozen=True)
class Variant:
    """The variant that will run and why (one line per variant tried)."""

    name: str
    reason: str
    tried: tuple = field(default_factory=tuple)
    llvm_library: str = ""


def mitsuba_installed() -> bool:
    return importlib.util.find_spec("mitsuba") is not None


def _probe(variant: str) -> tuple[bool, str]:
    ok, why = _backend.run_probe(_PROBE, variant, dict(os.environ), timeout=300)
    return ok, "ok" if ok else why


def _precheck(variant: str) -> tuple[bool, str, str]:
    """Cheap reasons not to try a variant: ``(worth probing, why not, llvm library)``."""
    llvm = _backend.probe_llvm()  # sets DRJIT_LIBLLVM_PATH before any drjit import
    lib = llvm.llvm_library or os.environ.get("DRJIT_LIBLLVM_PATH", "")
    if variant == "cuda_ad_rgb":
        if os.environ.get("MPIB_NO_CUDA") == "1":
            return False, "disabled by MPIB_NO_CUDA=1", lib
        cuda = _backend.probe_cuda()
        if cuda.name != "cuda":
            return False, cuda.notice, lib
    if variant == "llvm_ad_rgb" and llvm.name != "llvm":
        return False, llvm.notice, lib
    return True, "", lib


@functools.lru_cache(maxsize=None)
def choose_variant(requested: str | None = None) -> Variant:
    """The Mitsuba variant to use: ``requested``, or the best one that passes its probe.

    Raises :class:`MitsubaUnavailable` if Mitsuba is not installed, or if the requested
    variant (or, with ``None``, every variant) fails its probe; the message says why.
    """
    if not mitsuba_installed():
        raise MitsubaUnavailable("Mitsuba 3 is not installed (pip install 'mpib-validate[mitsuba]' "
                                 "-c constraints.txt)")
    if requested is not None and requested not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS} or None, got {requested!r}")
    candidates = (requested,) if requested else VARIANTS
    tried = []
    lib = ""
    for v in candidates:
        worth, why, lib = _precheck(v)
        if worth:
            ok, why = _probe(v)
            if ok:
                note = f"{v}: passed its probe" + (f" (LLVM library {lib})" if v != "scalar_rgb"
                                                   and lib else "")
                earlier = "; ".join(tried)
                reason = note + (f"; not {earlier}" if earlier else "")
                return Variant(v, reason, tuple(tried), lib)
        tried.append(f"{v}: {why}")
    raise MitsubaUnavailable("no Mitsuba variant runs here: " + "; ".join(tried))


def set_variant(requested: str | None = None):
    """Choose (probe) a variant, make it current, return ``(mitsuba module, Variant)``."""
    chosen = choose_variant(requested)
    import mitsuba as mi

    if mi.variant() != chosen.name:
        mi.set_variant(chosen.name)
    return mi, chosen
