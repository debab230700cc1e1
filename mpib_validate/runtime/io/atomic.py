"""Atomic file output: write a temporary file beside the target, then rename it.

A reader never sees a half-written file, and a failed write leaves any existing
target untouched.

Outputs are regular files: a path that names anything else (a device such as
``/dev/null``, a FIFO, a socket, a directory) is refused, before the work
(:func:`check_outputs`) and again when the file is renamed into place
(:func:`replaceable`), so that a run never replaces a device node.

The outputs of one run appear together or not at all (:func:`together`): inside
that block every :func:`atomic_path` (and :func:`mpib_validate.runtime.io.exr.write_exr`)
writes its temporary file, and the renames happen only when the block ends
without an error; on an error (a full disk, an interruption) every temporary
file is removed and no target changes.

Inputs are regular files too (:func:`check_input`): opening a FIFO for reading
blocks until a writer comes, and a device such as ``/dev/zero`` never ends.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import secrets
import stat
from pathlib import Path


class OutputError(ValueError):
    """An output that would overwrite an input, or cannot be written."""


class InputError(ValueError):
    """An input path that is not a readable regular file; the message names it."""


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def check_input(path: str | os.PathLike, what: str = "input") -> Path:
    """``path`` as a :class:`Path` if it names a regular file (after symbolic links);
    else :class:`InputError` naming it and what it is. Never opens the file."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise InputError(f"cannot read {what} '{path}': file does not exist") from None
    except OSError as exc:
        raise InputError(f"cannot read {what} '{path}': {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"cannot read {what} '{path}': it is {_kind(st.st_mode)}, not a "
                         f"regular file")
    return p


def replaceable(path: str | os.PathLike, option: str = "output") -> None:
    """Raise :class:`OutputError` unless ``path`` is absent or a regular file (after
    symbolic links), i.e. unless renaming a new file onto it only replaces a file."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise OutputError(f"{option} '{path}': {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{option} '{path}' is {_kind(st.st_mode)}; an output must be a "
                          f"regular file or a new path")


class _Batch:
    """Temporary files written during :func:`together`, renamed at its end."""

    def __init__(self):
        self.pending: list[tuple[Path, Path]] = []  # (temporary, target)
        self.made_dirs: list[Path] = []

    def commit(self) -> None:
        """Rename every temporary file onto its target; on any failure undo the renames
        done so far (a replaced file is restored from a hard link kept beside it)."""
        done: list[tuple[Path, Path | None, bool]] = []  # (target, backup, existed)
        try:
            for tmp, target in self.pending:
                replaceable(target)
                existed, backup = target.exists(), None
                if existed:
                    backup = target.parent / f".{target.name}.old-{secrets.token_hex(4)}"
                    try:
                        os.link(target, backup)
                    except OSError:
                        backup = None
                os.replace(tmp, target)
                done.append((target, backup, existed))
        except BaseException:
            for target, backup, existed in reversed(done):
                with contextlib.suppress(OSError):
                    if backup is not None:
                        os.replace(backup, target)
                    elif not existed:
                        os.unlink(target)
            self.discard()
            raise
        for _, backup, _ in done:
            if backup is not None:
                with contextlib.suppress(OSError):
                    os.unlink(backup)
        self.pending.clear()

    def discard(self) -> None:
        for tmp, _ in self.pending:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        self.pending.clear()
        for d in reversed(self.made_dirs):  # folders made for outputs, if left empty
            with contextlib.suppress(OSError):
                d.rmdir()


_BATCH: contextvars.ContextVar[_Batch | None] = contextvars.ContextVar("mpib_outputs",
                                                                       default=None)


@contextlib.contextmanager
def together():
    """All files written by :func:`atomic_path` (and ``write_exr``) inside this block
    appear when it ends without an error, or none does (see the module docstring).
    Nested blocks join the outermost one."""
    if _BATCH.get() is not None:
        yield
        return
    batch = _Batch()
    token = _BATCH.set(batch)
    try:
        yield
    except BaseException:
        _BATCH.reset(token)
        batch.discard()
        raise
    _BATCH.reset(token)
    batch.commit()


@contextlib.contextmanager
def apart():
    """Files written inside this block are placed at once, even inside
    :func:`together`: what is not an output of the run but is read back as it goes
    (the MPI disk cache)."""
    token = _BATCH.set(None)
    try:
        yield
    finally:
        _BATCH.reset(token)


def _make_parents(directory: Path) -> None:
    """Make ``directory`` and its missing parents, remembered by the batch (if any) so
    that a failed run leaves no empty folder behind."""
    missing = []
    d = directory
    while not d.exists() and d != d.parent:
        missing.append(d)
        d = d.parent
    directory.mkdir(parents=True, exist_ok=True)
    batch = _BATCH.get()
    if batch is not None:
        batch.made_dirs.extend(reversed(missing))


def temporary_beside(path: str | os.PathLike, suffix: str | None = None) -> Path:
    """A fresh hidden temporary path in ``path``'s folder (made if missing)."""
    path = Path(path)
    _make_parents(path.parent)
    suffix = path.suffix if suffix is None else suffix
    return path.parent / f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}{suffix}"


def place(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Move the finished temporary file ``tmp`` onto ``path``: now, or at the end of
    the :func:`together` block this runs in. Refuses (and removes ``tmp``) when
    ``path`` has become something other than a regular file."""
    tmp, path = Path(tmp), Path(path)
    try:
        replaceable(path)
    except OutputError:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    batch = _BATCH.get()
    if batch is not None:
        batch.pending.append((tmp, path))
    else:
        os.replace(tmp, path)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path in the target's directory; move it onto ``path`` on
    success (:func:`place`)."""
    tmp = temporary_beside(path)
    try:
        yield tmp
        place(tmp, path)
    except OSError as exc:  # a full disk, a lost permission: named by the target
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise OutputError(f"cannot write '{path}': {exc.strerror or exc}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


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
    be written: none is an input (or the same file by another name), each is a regular
    file or absent (not a directory, device, FIFO or socket), no two are the same file,
    and each one's directory exists or can be made and is writable."""
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
        replaceable(out, "output")
        parent = out.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise OutputError(f"cannot write '{out}': '{parent}' is not a directory")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(f"cannot write '{out}': no permission to write in '{parent}'")
