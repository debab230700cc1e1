"""Backend probing: a bad LLVM library must cost a notice, never the process."""

from __future__ import annotations

import glob
import os
import subprocess
import sys

import pytest

from mpib_validate.runtime.compositor import backend


def test_numpy_always_runs():
    assert backend.resolve("numpy").name == "numpy"


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="unknown backend"):
        backend.resolve("metal")


def test_llvm_version_parsing():
    assert backend._llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert backend._llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert backend._llvm_version("/usr/lib/llvm-16/lib/libLLVM.so") == 16
    assert all((backend._llvm_version(p) or 0) >= 16 for p in backend.llvm_candidates())


@pytest.mark.parametrize("lib", sorted(glob.glob("/usr/lib/*/libLLVM-1[45].so*"))[:2] + ["/nonexistent/libLLVM.so"])
def test_bad_llvm_fails_the_probe_not_the_process(lib):
    """LLVM 14 is refused at import and LLVM 15 aborts at the first min/max kernel
    (drjit 1.5); both must come back as a failed probe with a reason."""
    pytest.importorskip("drjit")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=lib)
    ok, why = backend._run_probe("llvm", env)
    assert not ok and why


def test_fallback_prints_one_line_notice():
    """In a fresh process with only a broken library on offer, the tracer falls back to
    numpy with one line on stderr and still renders."""
    code = (
        "import mpib_validate.runtime.compositor.backend as b\n"
        "b.llvm_candidates = lambda: []\n"
        "from mpib_validate.cards import trace, generate\n"
        "from mpib_validate.runtime import samples\n"
        "s = generate.generate(0, settings=generate.GeneratorSettings(width=16, height=16))\n"
        "img, meta = trace.trace(s, samples.pinhole(1), backend='llvm')\n"
        "print(meta['backend'])\n")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "numpy"
    lines = [l for l in r.stderr.splitlines() if l.startswith("mpib:")]
    assert len(lines) == 1 and "using numpy" in lines[0]
