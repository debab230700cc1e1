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
