"""`mpib refocus` and `mpib compare` on bad or extreme input: one line naming the file or
option, exit status 2, nothing written; or a finite result (issue 15)."""

from __future__ import annotations

import re

import numpy as np
import OpenEXR
import pytest
from clirun import one_line_error, run

from mpib_validate.runtime.io.exr import channels_from_rgba, read_exr, rgba_from, write_exr

H, W = 12, 16


def _passes(path, colour=None, depth=None):
    colour = np.full((H, W, 4), 0.5, np.float32) if colour is None else colour
    depth = np.full((H, W), 3.0, np.float32) if depth is None else depth
    depth = depth.astype(np.float32)
    depth[: H // 2, : W // 2] = np.minimum(depth[: H // 2, : W // 2], 1.5)  # an edge
    write_exr(path, {**channels_from_rgba(colour), "Depth.Z": depth})
    return path


LENS = ["--blur-parameter", 10, "--focus-depth", 2]


def _nothing_written(tmp_path, keep=()):
    left = sorted(p.name for p in tmp_path.iterdir() if p.name not in keep)
    assert left == [], left


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_colour_is_refused_with_the_pixel(tmp_path, bad):
    """One NaN in R used to blur into a whole NaN channel, written with exit 0."""
    colour = np.full((H, W, 4), 0.5, np.float32)
    colour[3, 4, 0] = bad
    src = _passes(tmp_path / "in.exr", colour)
    line = one_line_error(*run("refocus", src, "-o", tmp_path / "out.exr", *LENS)[::2])
    assert "in.exr" in line and "(row 3, column 4, channel R)" in line
    _nothing_written(tmp_path, {"in.exr"})


def test_negative_colour_is_clamped_with_a_notice(tmp_path):
    """Negative radiance (a denoiser's undershoot) is clamped to 0 and said so; the
    result is finite and non-negative."""
    colour = np.full((H, W, 4), 0.5, np.float32)
    colour[2, 5, 1] = -0.25
    src = _passes(tmp_path / "in.exr", colour)
    rc, out, err = run("refocus", src, "-o", tmp_path / "out.exr", *LENS, "-q")
    assert rc == 0, err
    assert "1 negative colour value(s)" in err and "clamped to 0" in err and "row 2, column 5" in err
    img = rgba_from(read_exr(tmp_path / "out.exr"))
    assert np.isfinite(img).all() and (img >= 0).all()


def test_radius_beyond_the_old_kernel_limit_gives_a_finite_image(tmp_path):
    """r = 1,400 px (A = 2000, a jump from d = 0.1 to 0.8): the kernel was NaN from
    1,388 px, so the image was all NaN with exit 0. A blur far wider than the image
    averages the replicated content: every output colour lies within the input's."""
    rng = np.random.default_rng(0)
    colour = np.ones((H, W, 4), np.float32)
    colour[..., :3] = rng.uniform(0.2, 0.8, (H, W, 3))
    depth = np.full((H, W), 10.0)
    depth[4:8, 4:8] = 1.25
    src = tmp_path / "in.exr"
    write_exr(src, {**channels_from_rgba(colour), "Depth.Z": depth.astype(np.float32)})
    rc, out, err = run("refocus", src, "-o", tmp_path / "out.exr", "--blur-parameter", 2000,
                       "--focus-disparity", 0.8, "--max-memory-gb", 8, "-q")
    assert rc == 0, err
    assert "largest blur radius 1400.0 px" in out
    img = rgba_from(read_exr(tmp_path / "out.exr"))
    assert np.isfinite(img).all()
    rgb = img[..., :3] / img[..., 3:4]
    assert (rgb >= 0.2 - 1e-4).all() and (rgb <= 0.8 + 1e-4).all()


@pytest.mark.parametrize("case", ["f/0.01", "c=1e-6"])
def test_huge_blur_is_refused_up_front(tmp_path, case):
    """f/0.01 asked numpy for 64.7 GiB and a card at depth 1e-6 for 821 TiB
    (MemoryError tracebacks); the estimate refuses both before any work. At 512 px,
    f/0.01 and 50 mm give A = 2.5 m x 711 px = 1778 px per unit disparity, a 2963 px
    radius for d = 2 against d_f = 1/3: an FFT over (512 + 2 x 2964)^2 float32 values
    of four channels (2.7 GB with its spectrum and output), past a 2 GB limit."""
    n = 512
    depth = np.full((n, n), 3.0, np.float32)
    if case == "f/0.01":
        args = ["--fstop", 0.01, "--focal-mm", 50, "--focus-depth", 3]
        depth[200:300, 200:300] = 0.5
    else:
        args = ["--blur-parameter", 10, "--focus-depth", 3]
        depth[200:300, 200:300] = 1e-6
    src = tmp_path / "in.exr"
    write_exr(src, {**channels_from_rgba(np.full((n, n, 4), 0.5, np.float32)), "Depth.Z": depth})
    line = one_line_error(*run("refocus", src, "-o", tmp_path / "out.exr", *args,
                               "--max-memory-gb", 2)[::2])
    assert "--max-memory-gb" in line and "largest blur radius" in line
    _nothing_written(tmp_path, {"in.exr"})


def test_colour_passed_as_depth_is_refused_up_front(tmp_path):
    """A colour image (values 0..1) as --depth gives d = 1/Z up to 1/min(colour): tens
    thousands of planes (it ran 5 minutes at 10.7 GB before being killed)."""
    rng = np.random.default_rng(1)
    colour = rng.uniform(0.001, 1.0, (256, 256, 4)).astype(np.float32)
    write_exr(tmp_path / "c.exr", channels_from_rgba(colour))
    rc, out, err = run("refocus", tmp_path / "c.exr", "--depth", tmp_path / "c.exr", "-o",
                       tmp_path / "out.exr", "--blur-parameter", 30, "--focus-depth", 0.5,
                       "--max-memory-gb", 16)
    line = one_line_error(rc, err)
    assert "planes" in line and "--max-memory-gb" in line
    planes = int(re.search(r"about (\d+) planes", line).group(1))
    assert planes > 1000  # 2578: d = 1/Z spans 1 to 1000, sparsely at the top
    _nothing_written(tmp_path, {"c.exr"})


def test_large_random_depth_is_refused_up_front(tmp_path):
    """2048 x 2048 random depth in [1, 10] at A = 50: 46 planes that each cover the
    whole frame, 46 x 4.2 Mpx x 16 B = 2.9 GB of layers (at 4096 x 4096 it ran 385 s
    to an 11.7 GB peak). Under a 2 GB limit it is refused before any work."""
    rng = np.random.default_rng(2)
    n = 2048
    write_exr(tmp_path / "in.exr", {**channels_from_rgba(np.full((n, n, 3), 0.5, np.float32)),
                                    "Depth.Z": rng.uniform(1, 10, (n, n)).astype(np.float32)})
    line = one_line_error(*run("refocus", tmp_path / "in.exr", "-o", tmp_path / "out.exr",
                               "--blur-parameter", 50, "--focus-depth", 2,
                               "--max-memory-gb", 2)[::2])
    assert "about 46 planes" in line and "layers" in line
    _nothing_written(tmp_path, {"in.exr"})


def test_plan_is_reported_before_the_work(tmp_path):
    src = _passes(tmp_path / "in.exr")
    rc, out, err = run("refocus", src, "-o", tmp_path / "out.exr", *LENS)
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].startswith(f"refocusing {W}x{H} (default): about ")
    assert "planes" in lines[0] and "largest blur radius" in lines[0] and "estimated memory" in lines[0]
    assert lines[1].startswith("refocused")


@pytest.mark.parametrize("args, option", [
    (["--fstop", 2, "--focal-mm", 50, "--scene-unit-m", 0, "--focus-depth", 2], "--scene-unit-m"),
    (["--fstop", 2, "--focal-mm", 50, "--scene-unit-m", -1, "--focus-depth", 2], "--scene-unit-m"),
    # a lens whose aperture R f_px underflows to 0 (found by tests/test_cli_fuzz.py)
    (["--fstop", "1e308", "--focal-mm", 50, "--focus-depth", 2.5], "--fstop 1e+308"),
    ([*LENS, "--far-limit", "nan"], "--far-limit"),
    ([*LENS, "--far-limit", 0], "--far-limit"),
    (["--blur-parameter", 10, "--fstop", 2, "--focal-mm", 50, "--focus-depth", 2], "--blur-parameter"),
    (["--blur-parameter", 10, "--focus-pixel", "-1,10"], "outside the 16x12 image"),
    (["--blur-parameter", 10, "--focus-depth", 0], "--focus-depth"),
    ([*LENS, "--max-memory-gb", "inf"], "--max-memory-gb"),
])
def test_bad_options_name_the_option(tmp_path, args, option):
    src = _passes(tmp_path / "in.exr")
    line = one_line_error(*run("refocus", src, "-o", tmp_path / "out.exr", *args)[::2])
    assert option in line
    _nothing_written(tmp_path, {"in.exr"})


def _two_view_layers(path, colours, depth):
    parts = []
    for name, c in colours.items():
        comb = {f"{name}.Combined.{k}": np.full((H, W), v, np.float32) for k, v in zip("RGB", c)}
        comb[f"{name}.Combined.A"] = np.ones((H, W), np.float32)
        parts.append(OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION}, comb, f"{name}.Combined"))
        parts.append(OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION},
                                  {f"{name}.Depth.Z": depth}, f"{name}.Depth"))
    OpenEXR.File(parts).write(str(path))


def test_two_view_layers_need_view_layer(tmp_path):
    """A Blender file with two view layers gave "no colour channels"."""
    depth = np.full((H, W), 3.0, np.float32)
    _two_view_layers(tmp_path / "two.exr", {"Front": (0.9, 0.1, 0.1), "Back.001": (0.1, 0.2, 0.8)}, depth)
    line = one_line_error(*run("refocus", tmp_path / "two.exr", "-o", tmp_path / "o.exr", *LENS)[::2])
    assert "2 view layers (Back.001, Front)" in line and "--view-layer" in line
    line = one_line_error(*run("refocus", tmp_path / "two.exr", "-o", tmp_path / "o.exr", *LENS,
                               "--view-layer", "Side")[::2])
    assert "no view layer 'Side'" in line and "Back.001, Front" in line
    rc, out, err = run("refocus", tmp_path / "two.exr", "-o", tmp_path / "o.exr", *LENS,
                       "--view-layer", "Back.001", "-q")
    assert rc == 0, err
    img = rgba_from(read_exr(tmp_path / "o.exr"))
    # uniform colour in, uniform colour out (up to float32 rounding of the blur)
    np.testing.assert_allclose(img[..., :3] / img[..., 3:4], np.broadcast_to([0.1, 0.2, 0.8], (H, W, 3)),
                               rtol=1e-5)


# -- compare -------------------------------------------------------------------------


def _image(path, rgba):
    write_exr(path, channels_from_rgba(np.asarray(rgba, np.float32)))
    return path


def test_compare_refuses_a_nan_image(tmp_path):
    a = np.full((16, 16, 4), 0.5, np.float32)
    b = a.copy()
    b[7, 9, 2] = np.nan
    line = one_line_error(*run("compare", _image(tmp_path / "a.exr", a), _image(tmp_path / "b.exr", b))[::2])
    assert "b.exr" in line and "(row 7, column 9, channel B)" in line


def test_compare_peak_must_be_positive(tmp_path):
    a = _image(tmp_path / "a.exr", np.full((16, 16, 4), 0.5))
    line = one_line_error(*run("compare", a, a, "--peak", 0)[::2])
    assert "--peak" in line


@pytest.mark.parametrize("side", [1, 8])
def test_compare_small_images_print_no_nan(tmp_path, side):
    """1x1 printed nan and 8x8 raised scikit-image's window error: SSIM needs 11x11."""
    a = _image(tmp_path / "a.exr", np.full((side, side, 4), 0.5))
    b = _image(tmp_path / "b.exr", np.full((side, side, 4), 0.6))
    rc, out, err = run("compare", a, b)
    assert rc == 0, err
    assert "nan" not in out.lower() and "-inf" not in out
    assert "n/a  (undefined on images smaller than 11x11" in out
    rc, out, err = run("compare", a, a, "--json")
    assert rc == 0, err
    import json

    res = json.loads(out)  # strict JSON: no NaN or Infinity
    assert res["psnr"] is None and res["notes"]["psnr"] == "identical images"


def test_compare_empty_mask_is_refused(tmp_path):
    a = _image(tmp_path / "a.exr", np.full((16, 16, 4), 0.5))
    write_exr(tmp_path / "m.exr", {"Y": np.zeros((16, 16), np.float32)})
    line = one_line_error(*run("compare", a, a, "--mask", tmp_path / "m.exr")[::2])
    assert "m.exr" in line and "selects no pixel" in line
