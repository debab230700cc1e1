"""`mpib render`, `mpib generate` and scene.json on bad input: one line naming the file,
field or option, exit status 2, no input overwritten, no partial output (issue 15)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from clirun import one_line_error, run

from mpib_validate.cards.generate import GeneratorSettings, generate
from mpib_validate.cards.scene import save_scene

README = Path(__file__).resolve().parent.parent / "README.md"


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("guards") / "s"
    save_scene(generate(1, "constant", settings=GeneratorSettings(width=24, height=16)), d)
    return d


def _copy(scene_dir, tmp_path, edit=None):
    d = tmp_path / "s"
    shutil.copytree(scene_dir, d)
    if edit is not None:
        doc = json.loads((d / "scene.json").read_text())
        edit(doc, d)
        (d / "scene.json").write_text(json.dumps(doc))
    return d


def _files(d: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_an_input_texture_anywhere_is_not_overwritten(scene_dir, tmp_path):
    """A texture moved to tex/object1.exr was overwritten by `-o tex/object1.exr` (only
    cards/<name>.exr was protected) and the scene no longer loaded."""
    def move(doc, d):
        (d / "tex").mkdir()
        card = doc["cards"][1]
        (d / card["texture"]).rename(d / "tex" / "object1.exr")
        card["texture"] = "tex/object1.exr"

    d = _copy(scene_dir, tmp_path, move)
    before = _files(d)
    line = one_line_error(*run("render", d, "-o", d / "tex" / "object1.exr", "--spp", 4, "-q")[::2])
    assert "refusing to overwrite the input" in line and "object1.exr" in line
    # the preview beside an output must not land on an input either (an EXR named .png)
    (d / "tex" / "object1.exr").rename(d / "tex" / "img.png")
    doc = json.loads((d / "scene.json").read_text())
    doc["cards"][1]["texture"] = "tex/img.png"
    (d / "scene.json").write_text(json.dumps(doc))
    before = _files(d)
    line = one_line_error(*run("render", d, "-o", d / "tex" / "img.exr", "--spp", 4, "-q")[::2])
    assert "refusing to overwrite the input" in line and "img.png" in line
    assert _files(d) == before


def test_png_output_and_directory_preview_are_refused_before_any_work(scene_dir, tmp_path):
    """`-o r.png` wrote the EXR to r.png, then the preview over it ("wrote r.png"
    twice); a directory where the preview goes failed after the EXR was written."""
    out = tmp_path / "out"
    out.mkdir()
    line = one_line_error(*run("render", scene_dir, "-o", out / "r.png", "--spp", 4, "-q")[::2])
    assert "r.png" in line and "same file" in line
    (out / "r2.png").mkdir()
    line = one_line_error(*run("render", scene_dir, "-o", out / "r2.exr", "--spp", 4, "-q")[::2])
    assert "r2.png" in line and "is a directory" in line
    assert sorted(p.name for p in out.iterdir()) == ["r2.png"]  # nothing written
    rc, stdout, err = run("render", scene_dir, "-o", out / "r2.exr", "--spp", 4, "-q", "--no-preview")
    assert rc == 0, err


@pytest.mark.parametrize("edit, message", [
    (lambda doc: doc["cards"][0].__setitem__("texture", 5), "field 'texture': must be the path"),
    (lambda doc: doc["cards"][0].__setitem__("texture", None), "field 'texture': must be the path"),
    (lambda doc: doc.__setitem__("metadata", [1, 2]), "field 'metadata' must be an object"),
    (lambda doc: doc["cards"][1].__setitem__("ofset", [0, 0]),
     "unknown field 'ofset'; did you mean 'offset'?"),
    (lambda doc: doc["camera"].__setitem__("blur_paramter", 3.0),
     "unknown field 'blur_paramter'; did you mean 'blur_parameter'?"),
    (lambda doc: doc.__setitem__("camra", {}), "unknown field 'camra'; did you mean 'camera'?"),
    (lambda doc: doc["cards"][0].__setitem__("plane", {"a": 0, "b": 0, "c": 5, "d": 1}),
     "unknown field 'd'"),
    (lambda doc: doc["camera"].__setitem__("width", "24"), "camera field 'width'"),
])
def test_bad_scene_json_is_one_line(scene_dir, tmp_path, edit, message):
    """TypeError tracebacks ("texture": 5 or null, "metadata": [1, 2]); unknown keys
    were ignored, so a typo such as "ofset" silently recentred a card."""
    d = _copy(scene_dir, tmp_path, lambda doc, d: edit(doc))
    line = one_line_error(*run("render", d, "-o", tmp_path / "r.exr", "--spp", 4, "-q")[::2])
    assert message in line and "scene.json" in line
    assert not (tmp_path / "r.exr").exists()


@pytest.mark.parametrize("args, message", [
    (["--spp", 1_000_000_000], "--max-memory-gb"),
    (["--aperture", "grid", "--grid-side", 100_000], "--max-memory-gb"),
    (["--spp", 0], "argument --spp"),
    (["--grid-side", 0], "argument --grid-side"),
    (["--seed", -1], "argument --seed"),
])
def test_render_sample_counts_are_bounded(scene_dir, tmp_path, args, message):
    """--spp 1e9 and --grid-side 100000 were MemoryError tracebacks (32 GB and 160 GB of
    samples); --spp 0 did not name the option."""
    line = one_line_error(*run("render", scene_dir, "-o", tmp_path / "r.exr", *args,
                               "--max-memory-gb", 8, "-q")[::2])
    assert message in line
    assert not list(tmp_path.iterdir())


def test_enormous_width_is_one_line(scene_dir, tmp_path):
    """A camera 1e9 pixels wide gave Dr.Jit's RuntimeError (or a MemoryError)."""
    d = _copy(scene_dir, tmp_path, lambda doc, d: doc["camera"].__setitem__("width", 10 ** 9))
    line = one_line_error(*run("render", d, "-o", tmp_path / "r.exr", "--spp", 4, "-q")[::2])
    assert "1000000000x16" in line and ("32-bit" in line or "--max-memory-gb" in line)


def test_generate_refusals(tmp_path):
    """--case grazing made a tilted card in the constant family; --out silently
    replaced an existing scene."""
    line = one_line_error(*run("generate", "--family", "constant", "--case", "grazing",
                               "--size", "24x16", "--out", tmp_path / "g")[::2])
    assert "--case grazing" in line and "--family varying" in line
    assert not (tmp_path / "g").exists()
    rc, out, err = run("generate", "--seed", 2, "--size", "24x16", "--out", tmp_path / "s")
    assert rc == 0, err
    before = _files(tmp_path / "s")
    line = one_line_error(*run("generate", "--seed", 5, "--size", "24x16", "--out", tmp_path / "s")[::2])
    assert "already holds a scene" in line and "--force" in line
    assert _files(tmp_path / "s") == before
    rc, out, err = run("generate", "--seed", 5, "--size", "24x16", "--out", tmp_path / "s", "--force")
    assert rc == 0, err and _files(tmp_path / "s") != before
    (tmp_path / "file").write_text("x")
    line = one_line_error(*run("generate", "--size", "24x16", "--out", tmp_path / "file")[::2])
    assert "is a file" in line


def test_help_has_no_restructuredtext():
    """The top-level help showed ``mpib`` (reStructuredText literals)."""
    for sub in ([], ["generate"], ["render"], ["refocus"], ["compare"], ["demo"], ["bench"],
                ["dataset"], ["backends"]):
        r = subprocess.run([sys.executable, "-m", "mpib_validate.cli", *sub, "--help"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0 and "`" not in r.stdout, (sub, r.stdout)


def test_argparse_errors_are_one_line():
    rc, out, err = run("render")
    line = one_line_error(rc, err)
    assert line.startswith("mpib render: error:") and "scene" in line


def test_readme_examples_fit_their_images():
    """The README refocused pixel 320,200 of the 256 x 256 images its own examples make,
    and called the demo "seconds" (it takes minutes)."""
    text = README.read_text()
    size = GeneratorSettings()
    for x, y in re.findall(r"--focus-pixel (\d+),(\d+)", text):
        assert int(x) < size.width and int(y) < size.height, (x, y)
    demo = re.search(r"`mpib demo` \(([^)]*)\)", text).group(1)
    assert "minute" in demo and "second" not in demo
