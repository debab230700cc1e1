"""The README's quick start runs as written.

The commands are the fenced ``sh`` blocks between the README's markers::

    <!-- quickstart -->
    ...
    <!-- /quickstart -->

Each command line runs in one fresh folder, in order, with ``mpib`` this checkout's
CLI (``python -m mpib_validate.cli``), and must exit 0 and write what it says. Only
sizes are changed, so that the run takes seconds (:func:`small`): ``mpib generate``
gets ``--size 128x96`` unless it names a size, ``mpib render`` at most 64 samples per
pixel, ``mpib dataset`` at most 2 scenes of 64x48. The inputs a reader brings,
``photo.jpg`` and ``disp.png`` (a photograph and its predicted disparity, 8-bit grey),
are put in the folder first: scikit-image's Middlebury motorcycle and its stereo
disparity, normalised to [0, 1], at 185x125. Lines of set-up (``make``, ``git``, ``pip``,
``cd``) are not run.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
BEGIN, END = "<!-- quickstart -->", "<!-- /quickstart -->"
SETUP_PREFIXES = ("make ", "git ", "pip ", "cd ", "python -m venv", "source ", ".venv/bin/activate")


def quickstart_blocks(text: str) -> list[str]:
    """The ``sh`` blocks between the markers; fails with what is missing."""
    if BEGIN not in text or END not in text:
        pytest.fail(f"README.md has no quick-start section: mark it with the lines {BEGIN} "
                    f"and {END} around its ```sh blocks (tests/test_quickstart.py runs them)")
    section = text[text.index(BEGIN) + len(BEGIN):text.index(END)]
    blocks = re.findall(r"```(?:sh|bash|console)\n(.*?)```", section, re.S)
    if not blocks:
        pytest.fail(f"README.md's quick-start section ({BEGIN} ... {END}) holds no ```sh block")
    return blocks


def commands(block: str) -> list[str]:
    """The command lines of a block: comments, blank and set-up lines left out,
    backslash continuations joined, a trailing ``# comment`` removed."""
    out, pending = [], ""
    for raw in block.splitlines():
        line = pending + raw.strip()
        pending = ""
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        line = line.lstrip("$ ").strip()
        if not line or line.startswith("#") or line.startswith(SETUP_PREFIXES):
            continue
        out.append(" ".join(shlex.split(line, comments=True)))
    return out


def _option(argv: list[str], name: str):
    return argv.index(name) if name in argv else None


def small(line: str) -> list[str]:
    """``line`` as argv with this checkout's CLI and small sizes."""
    argv = shlex.split(line)
    if argv[0] != "mpib":
        return argv
    sub = argv[1] if len(argv) > 1 else ""
    if sub == "generate" and _option(argv, "--size") is None:
        argv += ["--size", "128x96"]
    if sub == "render":
        i = _option(argv, "--spp")
        if i is None:
            argv += ["--spp", "64"]
        else:
            argv[i + 1] = str(min(int(argv[i + 1]), 64))
    if sub == "dataset":
        for name, value in (("--count", "2"), ("--size", "64x48"), ("--spp", "16")):
            i = _option(argv, name)
            if i is None:
                argv += [name, value]
            else:
                argv[i + 1] = value
    if sub == "bench":
        pytest.fail("the quick start runs `mpib bench`, which takes minutes: show it elsewhere")
    return [sys.executable, "-m", "mpib_validate.cli", *argv[1:]]


def write_photo_inputs(folder: Path) -> None:
    """``photo.jpg`` and ``disp.png``: the Middlebury motorcycle (scikit-image, shipped)
    at a quarter of its size and its stereo disparity normalised to [0, 1], 8-bit."""
    from PIL import Image
    from scipy import ndimage
    from skimage import data

    left, _, disp = data.stereo_motorcycle()
    known = np.isfinite(disp)
    _, (iy, ix) = ndimage.distance_transform_edt(~known, return_indices=True)
    disp = disp[iy, ix]
    d = (disp - disp.min()) / (disp.max() - disp.min())
    size = (left.shape[1] // 4, left.shape[0] // 4)
    Image.fromarray(left).resize(size, Image.LANCZOS).save(folder / "photo.jpg", quality=92)
    grey = Image.fromarray(np.round(d * 255).astype(np.uint8)).resize(size, Image.BILINEAR)
    grey.save(folder / "disp.png")


def test_the_marker_check_says_what_is_missing():
    with pytest.raises(pytest.fail.Exception, match="quick-start section"):
        quickstart_blocks("# README\n```sh\nmpib generate --out s\n```\n")
    assert commands("mpib a b  # note\n# comment\nmake demo\nmpib c \\\n  d\n") == [
        "mpib a b", "mpib c d"]
    assert small("mpib render s --spp 1024 -o r.exr")[-4:] == ["--spp", "64", "-o", "r.exr"]
    assert small("mpib generate --out s")[-2:] == ["--size", "128x96"]


def test_readme_quickstart_runs_as_written(tmp_path):
    blocks = quickstart_blocks(README.read_text(encoding="utf-8"))
    lines = [c for b in blocks for c in commands(b)]
    assert lines, "the quick-start blocks hold no command"
    write_photo_inputs(tmp_path)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    for line in lines:
        r = subprocess.run(small(line), cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, (f"README quick start: `{line}` exited {r.returncode}:\n"
                                   f"{r.stderr[-2000:]}")
        out = _output_of(shlex.split(line))
        assert out is None or (tmp_path / out).exists(), f"`{line}` did not write {out}"


def _output_of(argv: list[str]):
    for name in ("-o", "--output", "--out"):
        i = _option(argv, name)
        if i is not None:
            return argv[i + 1]
    return None
