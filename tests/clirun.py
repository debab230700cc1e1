"""Run the ``mpib`` command in this process, as the tests of bad input do: exit status,
stdout and stderr, whatever happens (argparse's own exits included)."""

from __future__ import annotations

import io
import traceback
from contextlib import redirect_stderr, redirect_stdout

from mpib_validate import cli


def run(*args) -> tuple[int, str, str]:
    """``(status, stdout, stderr)`` of ``mpib ARGS``. An exception escaping ``main`` is
    returned as status -1 with its traceback in stderr (the tests then fail on it)."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            rc = cli.main([str(a) for a in args])
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else 2
        except BaseException:  # noqa: BLE001 - the test reports it
            traceback.print_exc(file=err)
            rc = -1
    return rc, out.getvalue(), err.getvalue()


def one_line_error(rc: int, err: str) -> str:
    """The single error line of a refused command (asserts the form)."""
    assert rc == 2, (rc, err)
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]
