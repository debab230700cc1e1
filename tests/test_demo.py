"""`mpib demo` on tiny inputs: the gallery's pictures exist, are images, and show the run.

One real run (card scene traced, the Blender scene rendered by Cycles on the CPU, mpib
and the Defocus node) at 48x48 and 64x48 with a few samples, about 10 s; the checks
read what it wrote: every picture the pages name opens and is not blank, every figure
in the pages equals the one recomputed from the EXR files of the run, each preview is
its EXR, and the hero picture holds the run's images. Bad options are refused in one
line before any output.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from PIL import Image

from clirun import one_line_error, run
from mpib_validate import metrics
from mpib_validate.runtime.io.exr import read_exr, rgba_from
from mpib_validate.runtime.io.preview import to_uint8

TINY = ("--size", "64x48", "--spp", "2", "--sharp-spp", "2", "--card-size", "48",
        "--trace-spp", "16")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    pytest.importorskip("bpy")
    pytest.importorskip("matplotlib")  # the gallery's plot (the `report` extra)
    base = tmp_path_factory.mktemp("demo")
    out, hero = base / "gallery", base / "hero.png"
    rc, stdout, stderr = run("demo", "--out", out, "--hero", hero, *TINY)
    assert rc == 0, stderr
    return out, hero, stdout


def _pictures(out):
    """Every picture index.html and index.md show (paths relative to ``out``)."""
    page = (out / "index.html").read_text()
    md = (out / "index.md").read_text()
    html_imgs = re.findall(r"<img src='([^']+)'", page)
    md_imgs = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert html_imgs and sorted(set(html_imgs)) == sorted(set(md_imgs))
    return sorted(set(html_imgs))


def _rgb(path):
    return np.asarray(rgba_from(read_exr(path)), np.float64)[..., :3]


@pytest.mark.blender
def test_gallery_pictures_exist_and_are_images(demo):
    out, _, stdout = demo
    assert str((out / "index.html").resolve()) in stdout  # it says where the gallery is
    pics = _pictures(out)
    # per scene and focus: inputs, 3 presets + node, reference, crops, error maps; the
    # hero and the speed-against-error plot
    assert len(pics) == 2 + 4 * 9, pics
    for rel in pics:
        path = out / rel
        assert path.is_file() and path.stat().st_size > 0, rel
        with Image.open(path) as im:
            im.verify()
        with Image.open(path) as im:
            a = np.asarray(im.convert("RGB"))
        assert a.shape[0] > 0 and a.shape[1] > 0, rel
        assert len(np.unique(a.reshape(-1, 3), axis=0)) > 8, f"{rel} is blank"


@pytest.mark.blender
def test_figures_are_the_runs(demo):
    """Each PSNR in the pages equals the PSNR recomputed from the EXR files the run wrote
    (colour clipped to [0, 1]); each preview is its EXR in sRGB."""
    out, _, _ = demo
    summary = json.loads((out / "demo.json").read_text())
    md = (out / "index.md").read_text()
    rows = summary["rows"]
    assert {(r["scene"], r["focus"]) for r in rows} == {(s, f) for s in ("cards", "blender")
                                                        for f in ("near", "far")}
    assert {r["method"] for r in rows} == {"sharp input", "Defocus node", "mpib draft",
                                           "mpib default", "mpib best"}
    for r in rows:
        case = f"{r['scene']}-{r['focus']}"
        img, ref = _rgb(out / r["file"]), _rgb(out / case / "reference.exr")
        # float32 EXR against the float64 score: equal to 1e-6 dB and better
        assert abs(metrics.psnr(np.clip(ref, 0, 1), np.clip(img, 0, 1)) - r["psnr"]) < 1e-3
        # the page's table row (2 decimals) is the run's
        time = "-" if r["method"] == "sharp input" else f"{r['seconds']:.3f}"
        line = f"| {r['method']} | {time} | {r['psnr']:.2f} | {r['psnr_ob']:.2f} |"
        assert line in md, line
        png = np.asarray(Image.open(out / r["file"].replace(".exr", ".png")).convert("RGB"))
        assert np.array_equal(png, to_uint8(np.clip(img, 0, None)))


@pytest.mark.blender
def test_hero_holds_the_runs_images(demo):
    """The hero's panels are the run's sharp input, Defocus node, mpib default and
    Cycles truth of the Blender scene focused far; its figures are the run's."""
    out, hero, _ = demo
    info = json.loads(hero.with_suffix(".json").read_text())
    rows = {r["method"]: r for r in json.loads((out / "demo.json").read_text())["rows"]
            if r["scene"] == "blender" and r["focus"] == "far"}
    pic = np.asarray(Image.open(hero).convert("RGB"))
    files = {"sharp input": "sharp-input", "Defocus node": "Defocus-node",
             "mpib default": "mpib-default", "reference": "reference"}
    assert [p["method"] for p in info["panels"]] == list(files)
    for p in info["panels"]:
        x, y, w, h = p["box"]
        want = np.asarray(Image.open(out / "blender-far" / f"{files[p['method']]}.png").convert("RGB"))
        same = (pic[y:y + h, x:x + w] == want).all(-1).mean()
        # the crop outlines (1 px rectangles) are drawn over the frame: all else is equal
        assert want.shape[:2] == (h, w) and same > 0.8, (p["method"], same)
        if p["method"] != "reference":
            assert math.isclose(p["psnr"], rows[p["method"]]["psnr"])
            assert math.isclose(p["psnr_ob"], rows[p["method"]]["psnr_ob"])
    assert "--hero" in info["command"]


@pytest.mark.parametrize("args, words", [
    (("--hero", "{tmp}/no/such/folder/hero.jpg"), "does not exist"),
    (("--hero", "{tmp}/hero.gif"), ".jpg, .jpeg or .png"),
    (("--size", "8x8"), "--size"),
    (("--card-size", "9"), "--card-size"),
    (("--out", "{tmp}/file"), "is a file"),
])
def test_bad_options_are_refused_before_any_output(tmp_path, args, words):
    (tmp_path / "file").write_text("x")
    before = sorted(tmp_path.iterdir())
    args = [a.format(tmp=tmp_path) for a in args]
    out = [] if "--out" in args else ["--out", tmp_path / "gallery"]
    line = one_line_error(*run("demo", *out, *args)[::2])
    assert words in line
    assert sorted(tmp_path.iterdir()) == before
