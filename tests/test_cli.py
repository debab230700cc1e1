"""The `mpib` command line, run as a user would run it (a real subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mpib_validate.runtime.io.exr import read_exr, rgba_from


def mpib(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "mpib_validate.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def test_every_subcommand_has_help():
    for sub in ("generate", "render", "refocus", "compare", "demo", "bench", "dataset", "backends"):
        r = mpib(sub, "--help")
        assert r.returncode == 0 and "usage: mpib " + sub in r.stdout


@pytest.mark.parametrize("family", ["constant", "varying"])
def test_generate_then_render(tmp_path, family):
    r = mpib("generate", "--seed", 3, "--family", family, "--size", "48x32", "--out", tmp_path / "scene")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "scene" / "scene.json").exists()
    out = tmp_path / "render" / "trace.exr"
    r = mpib("render", tmp_path / "scene", "--engine", "trace", "-o", out, "--spp", 16, "-q")
    assert r.returncode == 0, r.stderr
    img = read_exr(out)
    bokeh = rgba_from(img)
    assert bokeh.shape == (32, 48, 4) and np.isfinite(bokeh).all()
    for name in ("AllInFocus.R", "Depth.Z", "Disparity.Y", "Layer.Y", "Hit.background.A"):
        assert name in img.channels
    meta = json.loads(img.header["mpib"])
    assert meta["engine"] == "trace" and meta["sample_count"] == 16
    assert out.with_suffix(".png").exists()


def test_render_errors_are_one_clear_line(tmp_path):
    r = mpib("render", tmp_path / "missing", "-o", tmp_path / "x.exr")
    assert r.returncode == 2
    assert "scene file does not exist" in r.stderr and "Traceback" not in r.stderr
    r = mpib("generate", "--seed", 1, "--size", "24x24", "--out", tmp_path / "s")
    assert r.returncode == 0
    tex = tmp_path / "s" / "cards" / "background.exr"
    before = tex.read_bytes()
    r = mpib("render", tmp_path / "s", "-o", tex, "-q")
    assert r.returncode == 2 and "refusing to overwrite the input" in r.stderr
    assert tex.read_bytes() == before
    r = mpib("render", tmp_path / "s", "-o", tmp_path / "y.exr", "--blur-parameter", 0)
    assert r.returncode == 2 and "zero aperture" in r.stderr


def test_backends_reports_json():
    r = mpib("backends")
    assert r.returncode == 0
    report = json.loads(r.stdout)
    assert report["numpy"]["runs_as"] == "numpy"


def test_compare(tmp_path):
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    rng = np.random.default_rng(0)
    a = (0.8 * rng.random((20, 24, 4))).astype(np.float32)  # + 0.1 stays below 1
    b = a.copy()
    b[5:10, 5:10, :3] += 0.1
    write_exr(tmp_path / "a.exr", channels_from_rgba(a))
    write_exr(tmp_path / "b.exr", channels_from_rgba(b))
    mask = np.zeros((20, 24), np.float32)
    mask[5:10, 5:10] = 1
    write_exr(tmp_path / "m.exr", {"Y": mask})
    r = mpib("compare", tmp_path / "a.exr", tmp_path / "b.exr", "--mask", tmp_path / "m.exr", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    # inside the mask every colour value is off by 0.1: PSNR_ob = 20 dB (float32 rounding)
    assert res["psnr_ob"] == pytest.approx(20.0, abs=1e-4) and res["psnr"] > res["psnr_ob"]
    write_exr(tmp_path / "c.exr", channels_from_rgba(a[:10]))
    r = mpib("compare", tmp_path / "a.exr", tmp_path / "c.exr")
    assert r.returncode == 2 and "image sizes differ" in r.stderr and "c.exr" in r.stderr


@pytest.mark.parametrize("engine, spp", [("mitsuba", 16),
                                         pytest.param("cycles", 4, marks=pytest.mark.blender)])
def test_render_with_other_engines(tmp_path, engine, spp):
    pytest.importorskip({"mitsuba": "mitsuba", "cycles": "bpy"}[engine])
    r = mpib("generate", "--seed", 2, "--size", "32x24", "--out", tmp_path / "s")
    assert r.returncode == 0, r.stderr
    out = tmp_path / f"{engine}.exr"
    r = mpib("render", tmp_path / "s", "--engine", engine, "--spp", spp, "-o", out, "-q")
    assert r.returncode == 0, r.stderr
    img = read_exr(out)
    assert rgba_from(img).shape == (24, 32, 4) and "Depth.Z" in img.channels
    meta = json.loads(img.header["mpib"])
    assert meta["sample_count"] == spp and engine in (meta["engine"] + meta["backend"] + meta["samples"])


def test_dataset_command_builds_and_resumes(tmp_path):
    args = ("dataset", "--out", tmp_path / "ds", "--count", 2, "--size", "24x16", "--spp", 8)
    r = mpib(*args)
    assert r.returncode == 0, r.stderr
    assert "2 complete samples; built 2, skipped 0" in r.stdout
    r = mpib(*args)
    assert r.returncode == 0 and "built 0, skipped 2" in r.stdout
