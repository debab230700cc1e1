"""Atomic file output: write a temporary file beside the target, then rename it.

A reader never sees a half-written file, and a failed write leaves any existing
target untouched.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path


class OutputError(ValueError):
    """An output that would overwrite an input, or cannot be written."""


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path in the target's directory; rename it onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}"
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def refuse_overwrite(output: str | os.PathLike, inputs) -> None:
    """Raise :class:`OutputError` if ``output`` is the same file as any of ``inputs``."""
    out = Path(output).resolve()
    for p in inputs:
        if Path(p).resolve() == out:
            raise OutputError(f"refusing to overwrite the input '{p}' with an output; "
                              f"choose another output path")


def _same_file(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(outputs, inputs=(), option: str = "-o") -> None:
    """Raise :class:`OutputError` before any work unless every path of ``outputs`` can
    be written: none is an input (or the same file by another name), none is a
    directory, no two are the same file, and each one's directory exists or can be
    made and is writable."""
    outs = [Path(p) for p in outputs]
    for i, out in enumerate(outs):
        for other in outs[:i]:
            if _same_file(out, other):
                raise OutputError(f"{option} '{out}': the EXR and its PNG preview would be the "
                                  f"same file; give the output a .exr name")
        for p in inputs:
            if _same_file(out, Path(p)):
                raise OutputError(f"refusing to overwrite the input '{p}' with an output; "
                                  f"choose another output path")
        if out.is_dir():
            raise OutputError(f"output '{out}' is a directory; give a file path")
        parent = out.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise OutputError(f"cannot write '{out}': '{parent}' is not a directory")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(f"cannot write '{out}': no permission to write in '{parent}'")
