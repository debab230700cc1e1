"""Choosing a compute backend for the JIT kernels, by probing it safely.

Dr.Jit's LLVM backend needs an LLVM >= 16 shared library. drjit 1.5 refuses LLVM 14
with an ImportError but *aborts the whole process* on LLVM 15 at the first min/max
kernel ("Cannot select: fminimum"), and it loads the library when it is imported.
So the library is chosen before drjit is imported, and each candidate is tried in
a subprocess first: a failed probe costs a second, never the caller's process.

``resolve(name)`` maps a requested backend (``auto``, ``numpy``, ``llvm``, ``cuda``)
to the one that will run, plus a one-line notice when it had to fall back.
"""

from __future__ import annotations

import functools
import glob
import os
import re
import subprocess
import sys
from dataclasses import dataclass

MIN_LLVM = 16
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
)

_PROBE = r"""
import sys
import drjit as dr
backend = sys.argv[1]
if backend == "cuda":
    if not dr.has_backend(dr.JitBackend.CUDA):
        print("no CUDA device"); sys.exit(3)
    from drjit.cuda import Float
else:
    if not dr.has_backend(dr.JitBackend.LLVM):
        print("LLVM backend inactive"); sys.exit(3)
    from drjit.llvm import Float
x = dr.arange(Float, 64)
y = dr.sum(dr.minimum(dr.maximum(x, 2.0), 5.0))
dr.eval(y)
print("ok", float(y[0]))
"""


@dataclass(frozen=True)
class Backend:
    """The backend that will run: ``numpy``, ``llvm`` or ``cuda``, and why."""

    name: str
    notice: str = ""
    llvm_library: str = ""


def _llvm_version(path: str) -> int | None:
    m = re.search(r"LLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    if m is None:
        m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def llvm_candidates() -> list[str]:
    """LLVM shared libraries >= 16 found on this machine, newest first."""
    seen = {}
    for pattern in _LLVM_GLOBS:
        for p in glob.glob(pattern):
            real = os.path.realpath(p)
            v = _llvm_version(p) or _llvm_version(real)
            if v is not None and v >= MIN_LLVM and real not in seen.values():
                seen[p] = real
    return sorted(seen, key=lambda p: (-(_llvm_version(p) or 0), len(p)))


def run_probe(script: str, arg: str, env: dict | None = None, timeout: float = 120) -> tuple[bool, str]:
    """Run ``python -c script arg`` in a subprocess: ``(True, "")`` if it prints "ok...",
    else ``(False, why)``. A probe that crashes or aborts costs only its own process."""
    try:
        r = subprocess.run([sys.executable, "-c", script, arg], env=env or dict(os.environ),
                           capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"probe failed to run: {exc}"
    if r.returncode == 0 and r.stdout.startswith("ok"):
        return True, ""
    tail = (r.stdout + r.stderr).strip().splitlines()
    why = tail[-1] if tail else f"exit status {r.returncode}"
    if r.returncode < 0:
        why = f"probe process was killed by signal {-r.returncode} ({why})"
    return False, why


def _run_probe(backend: str, env: dict) -> tuple[bool, str]:
    return run_probe(_PROBE, backend, env)


def _drjit_installed() -> bool:
    import importlib.util

    return importlib.util.find_spec("drjit") is not None


@functools.lru_cache(maxsize=None)
def probe_llvm() -> Backend:
    """Find an LLVM library that Dr.Jit can run kernels with; sets ``DRJIT_LIBLLVM_PATH``."""
    if not _drjit_installed():
        return Backend("numpy", "Dr.Jit is not installed (pip install mpib-validate[jit])")
    if "drjit" in sys.modules and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        # Too late to choose a library: test the one drjit already loaded.
        import drjit as dr

        if dr.has_backend(dr.JitBackend.LLVM):
            return Backend("llvm")
        return Backend("numpy", "drjit was imported before its LLVM library was chosen")
    env = dict(os.environ)
    tried = []
    preset = os.environ.get("DRJIT_LIBLLVM_PATH")
    for lib in ([preset] if preset else []) + llvm_candidates():
        env["DRJIT_LIBLLVM_PATH"] = lib
        ok, why = _run_probe("llvm", env)
        if ok:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
            return Backend("llvm", llvm_library=lib)
        tried.append(f"{lib}: {why}")
    if not tried:
        return Backend("numpy", f"no LLVM >= {MIN_LLVM} shared library found "
                                f"(Debian: apt-get install libllvm19)")
    return Backend("numpy", "Dr.Jit LLVM backend failed its probe (" + "; ".join(tried) + ")")


@functools.lru_cache(maxsize=None)
def probe_cuda() -> Backend:
    import ctypes.util

    if not glob.glob("/dev/nvidia*") and ctypes.util.find_library("cuda") is None:
        return Backend("numpy", "no NVIDIA GPU driver on this machine")
    if not _drjit_installed():
        return Backend("numpy", "Dr.Jit is not installed")
    ok, why = _run_probe("cuda", dict(os.environ))
    return Backend("cuda") if ok else Backend("numpy", f"Dr.Jit CUDA backend unavailable: {why}")


def resolve(name: str = "auto") -> Backend:
    """Pick the backend for a request.

    ``auto`` prefers CUDA, then LLVM, then numpy; ``llvm``/``cuda`` fall back to
    numpy with a notice when they cannot run; ``numpy`` always runs.
    """
    if name == "numpy":
        return Backend("numpy")
    if name == "cuda":
        return probe_cuda()
    if name == "llvm":
        return probe_llvm()
    if name != "auto":
        raise ValueError(f"unknown backend {name!r}; choose auto, numpy, llvm or cuda")
    if os.environ.get("MPIB_NO_CUDA") != "1":
        cuda = probe_cuda()
        if cuda.name == "cuda":
            probe_llvm()  # keeps DRJIT_LIBLLVM_PATH consistent for later imports
            return cuda
    return probe_llvm()


def import_drjit():
    """Import drjit after the LLVM library has been chosen."""
    probe_llvm()
    import drjit

    return drjit


def notify(backend: Backend, stream=None) -> None:
    """Print the fallback notice, if any, as one line on stderr."""
    if backend.notice:
        print(f"mpib: {backend.notice}; using {backend.name}", file=stream or sys.stderr)
