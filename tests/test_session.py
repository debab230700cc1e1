"""Refocus from a cached MPI (mpib_validate.runtime.session) and `mpib refocus --mpi-cache`."""

from __future__ import annotations

import os

import numpy as np
import pytest

from clirun import one_line_error, run
from mpib_validate.runtime import samples
from mpib_validate.cards import trace
from mpib_validate.cards.generate import GeneratorSettings, generate
from mpib_validate.runtime.io.exr import read_exr, write_exr, channels_from_rgba
from mpib_validate.cards.render_io import write_render
from mpib_validate.metrics import psnr
from mpib_validate.runtime.refocus import load_passes, refocus
from mpib_validate.runtime.session import (REUSE_DOWN_TO, RefocusSession, downsample_mpi,
                                   passes_digest, preview_factor)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    """A varying-disparity card scene (tilted cards: many planes, edges, fill) as an
    mpib render with colour, depth and camera; 96x72 so that each build takes ~0.1 s."""
    d = tmp_path_factory.mktemp("session")
    scene = generate(1, "varying", settings=GeneratorSettings(width=96, height=72))
    res = trace.render(scene, samples.pinhole(1), notices=False)
    res.bokeh = res.all_in_focus
    write_render(d / "in.exr", res, scene, preview=False)
    return d, scene.camera


def test_a_new_focus_recomposites_the_cached_mpi_to_the_same_bits(scene_file):
    d, cam = scene_file
    passes = load_passes(d / "in.exr")
    A = cam.blur_parameter
    s = RefocusSession(passes)
    first = s.render(cam.focus_disparity, A)
    assert first.info["mpi"] == "built" and s.builds == 1
    for d_f in (0.5 * cam.focus_disparity, 1.7 * cam.focus_disparity):
        got = s.render(d_f, A)
        assert got.info["mpi"] == "cached" and s.builds == 1
        # the same function on the same layers: equal to the last bit
        assert np.array_equal(got.image, refocus(passes, A, d_f).image)
    assert s.cache_bytes > 0


def test_apertures_reuse_the_mpi_within_its_bounds_and_rebuild_beyond(scene_file):
    d, cam = scene_file
    passes = load_passes(d / "in.exr")
    A, d_f = cam.blur_parameter, cam.focus_disparity
    s = RefocusSession(passes)
    s.render(d_f, A)
    narrower = s.render(d_f, 0.7 * A)
    assert narrower.info["mpi"] == "cached" and narrower.info["mpi_blur_parameter"] == A
    # not bit-identical to a build at 0.7 A (finer planes, a wider fill, more edge
    # pixels unmixed), but the same image within the preset's tolerances: measured
    # 63.1 dB apart on this scene (94.9 dB at 0.9 A, 40.9 dB at the reuse limit 0.5 A);
    # 50 dB leaves room for the rounding of another platform's FFT
    fresh = refocus(passes, 0.7 * A, d_f).image
    assert psnr(np.clip(fresh[..., :3], 0, 1), np.clip(narrower.image[..., :3], 0, 1)) > 50.0
    too_narrow = s.render(d_f, 0.9 * REUSE_DOWN_TO * A)
    assert too_narrow.info["mpi"] == "built" and s.builds == 2
    wider = s.render(d_f, 1.2 * A)
    assert wider.info["mpi"] == "built" and s.builds == 3
    assert np.array_equal(wider.image, refocus(passes, 1.2 * A, d_f).image)
    exact = RefocusSession(passes, exact_aperture=True)
    exact.render(d_f, A)
    assert exact.render(d_f, 0.7 * A).info["mpi"] == "built"
    assert np.array_equal(exact.render(d_f, 0.7 * A).image, fresh)


def test_downsampling_keeps_each_layers_energy_and_box():
    rng = np.random.default_rng(3)
    rgba = rng.random((3, 18, 22, 4)).astype(np.float32)
    rgba[1, :5] = 0.0  # a layer that does not reach the top edge
    from mpib_validate.runtime.layers.mpi import MPI

    mpi = MPI.from_dense([0.1, 0.2, 0.3], rgba)
    small = downsample_mpi(mpi, 4)
    assert (small.height, small.width) == (5, 6)  # ceil(18/4), ceil(22/4)
    dense = small.dense()
    # interior blocks hold 16 canvas pixels, the cut ones at the bottom and right 2x4,
    # 4x2 and 2x2: summed with those weights, the layer's sum comes back exactly
    w = np.minimum(np.arange(1, 7) * 4, 22) - np.arange(6) * 4
    h = np.minimum(np.arange(1, 6) * 4, 18) - np.arange(5) * 4
    weights = (h[:, None] * w[None, :])[None, ..., None]
    np.testing.assert_allclose((dense * weights).sum(axis=(1, 2)), mpi.dense().sum(axis=(1, 2)),
                               rtol=1e-5)  # float32 sums of ~400 values
    assert small.layers[1].y0 == 1  # rows 5..17 -> blocks 1..4


def _block_aligned_passes(H=64, W=96):
    """Smooth textures, a foreground rectangle (1.5 m) before a wall (6 m) whose edges lie
    on the 4x4 block grid, so that no preview pixel straddles a depth edge."""
    from mpib_validate.runtime.refocus import Passes

    y, x = np.mgrid[0:H, 0:W] / 16.0
    bg = np.stack([0.5 + 0.3 * np.sin(x), 0.5 + 0.3 * np.cos(y), 0.4 + 0.2 * np.sin(x + y)], -1)
    fg = np.stack([0.9 + 0 * x, 0.3 + 0.2 * np.sin(2 * y), 0.1 + 0 * x], -1)
    inside = np.zeros((H, W), bool)
    inside[16:40, 24:56] = True
    colour = np.where(inside[..., None], fg, bg).astype(np.float32)
    return Passes(colour, np.where(inside, 1.5, 6.0), "colour", "depth")


@pytest.mark.parametrize("A, d_f", [(20.0, 1 / 6.0), (20.0, 1 / 1.5), (40.0, 0.4)])
def test_the_preview_is_the_full_render_at_a_quarter_of_the_resolution(A, d_f):
    passes = _block_aligned_passes()
    s = RefocusSession(passes)
    full = s.render(d_f, A).image
    prev = s.render(d_f, A, scale=0.25)
    assert prev.image.shape == (16, 24, 4) and prev.info["scale"] == 0.25
    assert s.builds == 1  # the preview is made from the kept MPI
    assert np.all(np.isfinite(prev.image)) and np.all(prev.image[..., 3] == 1.0)  # opaque in
    box = full.reshape(16, 4, 24, 4, 4).mean(axis=(1, 3))
    # with no block across an edge, the coarse layers blurred by A/4 differ from the box
    # average of the fine result only by the kernel's sampling on the coarse grid:
    # measured 64.9, 50.8 and 50.7 dB for these three cameras; 45 dB is 0.6 % rms. The
    # sharp input's box average is 27 to 38 dB away (so the preview is the blurred image)
    p = psnr(np.clip(box[..., :3], 0, 1), np.clip(prev.image[..., :3], 0, 1))
    sharp = passes.colour.reshape(16, 4, 24, 4, 3).mean(axis=(1, 3))
    assert p > 45.0 and p > psnr(np.clip(box[..., :3], 0, 1), np.clip(sharp, 0, 1)) + 10.0


@pytest.mark.parametrize("A, d_f", [(20.0, 1 / 6.0), (20.0, 1 / 1.5), (40.0, 0.4)])
def test_a_quick_preview_before_the_mpi_exists_shows_the_same_focus(A, d_f):
    passes = _block_aligned_passes()
    s = RefocusSession(passes)
    quick = s.quick_preview(d_f, A, 0.25)
    assert s.builds == 0 and s.cache_bytes == 0  # nothing built or kept for it
    assert quick.image.shape == (16, 24, 4) and np.all(quick.image[..., 3] == 1.0)
    prev = s.render(d_f, A, scale=0.25).image
    # from the block-centre pixels (not the block averages) built at A/4: on these
    # smooth textures measured 41.5 to 43.7 dB from the preview of the full MPI
    assert psnr(np.clip(prev[..., :3], 0, 1), np.clip(quick.image[..., :3], 0, 1)) > 38.0


def test_preview_sizes_round_up_and_scales_must_be_whole_fractions(scene_file):
    d, cam = scene_file
    passes = load_passes(d / "in.exr")
    from mpib_validate.runtime.refocus import Passes

    cut = Passes(passes.colour[:70, :93], passes.depth[:70, :93], "c", "d")
    s = RefocusSession(cut)
    assert s.render(cam.focus_disparity, cam.blur_parameter, 0.25).image.shape == (18, 24, 4)
    assert s.render(cam.focus_disparity, cam.blur_parameter, 0.5).image.shape == (35, 47, 4)
    assert s.quick_preview(cam.focus_disparity, cam.blur_parameter, 0.25).image.shape == (18, 24, 4)
    with pytest.raises(ValueError, match="scale"):
        s.render(cam.focus_disparity, cam.blur_parameter, scale=0.3)
    assert preview_factor(1.0) == 1 and preview_factor(0.25) == 4


def test_changed_inputs_are_noticed(scene_file, tmp_path):
    d, cam = scene_file
    path = tmp_path / "in.exr"
    path.write_bytes((d / "in.exr").read_bytes())
    s = RefocusSession.from_files(path)
    assert s.is_current()
    before = passes_digest(s.passes)
    img = read_exr(path)
    ch = dict(img.channels)
    ch["AllInFocus.R"] = ch["AllInFocus.R"] * 0.5
    write_exr(path, ch)
    assert not s.is_current()
    assert passes_digest(load_passes(path)) != before
    s.render(cam.focus_disparity, cam.blur_parameter)
    s.drop()
    assert s.cache_bytes == 0 and s.built_for is None


def test_a_session_keeps_no_mpi_over_its_memory_bound(scene_file):
    d, cam = scene_file
    s = RefocusSession(load_passes(d / "in.exr"), max_cache_bytes=1000)
    r = s.render(cam.focus_disparity, cam.blur_parameter)
    assert r.info["mpi"].startswith("built, not kept") and s.cache_bytes == 0
    s.render(cam.focus_disparity, cam.blur_parameter)
    assert s.builds == 2


def test_cli_mpi_cache_reuses_the_mpi_and_writes_the_same_output(scene_file, tmp_path):
    d, cam = scene_file
    cache = tmp_path / "cache"
    outs = []
    for i, extra in enumerate((["--mpi-cache", cache], ["--mpi-cache", cache], [])):
        out = tmp_path / f"out{i}.exr"
        rc, stdout, err = run("refocus", d / "in.exr", "-o", out, "-q", "--no-preview",
                              "--focus-disparity", 0.8 * cam.focus_disparity, *extra)
        assert rc == 0, err
        outs.append(read_exr(out).channels)
        if i == 0:
            assert "built the MPI and cached it" in stdout
        if i == 1:
            assert "reused the cached MPI" in stdout
    assert len(list(cache.glob("*.npz"))) == 1
    for k in outs[0]:
        assert np.array_equal(outs[0][k], outs[1][k]) and np.array_equal(outs[0][k], outs[2][k])
    # another aperture is another entry
    rc, stdout, err = run("refocus", d / "in.exr", "-o", tmp_path / "o3.exr", "-q",
                          "--blur-parameter", 0.8 * cam.blur_parameter, "--no-preview",
                          "--mpi-cache", cache)
    assert rc == 0 and "built the MPI" in stdout, err
    # a damaged entry is rebuilt, not trusted
    for f in cache.glob("*.npz"):
        f.write_bytes(b"broken")
    rc, stdout, err = run("refocus", d / "in.exr", "-o", tmp_path / "o4.exr", "-q",
                          "--no-preview", "--mpi-cache", cache)
    assert rc == 0 and "built the MPI" in stdout, err


def test_cli_mpi_cache_must_be_a_folder(scene_file, tmp_path):
    d, _ = scene_file
    rc, _, err = run("refocus", d / "in.exr", "-o", tmp_path / "o.exr", "--mpi-cache",
                     d / "in.exr")
    assert "--mpi-cache" in one_line_error(rc, err)
    assert not (tmp_path / "o.exr").exists()


def test_the_focus_pull_bench_times_every_kind_of_render(scene_file):
    """The bench worker on a small input (the numbers are the bench's, not checked here):
    every kind is timed, the re-composites really use the cached MPI (the worker
    asserts it), and the report has its table."""
    from mpib_validate.bench.focuspull import focus_pull_timings, markdown

    d, cam = scene_file
    res = focus_pull_timings({"input": str(d / "in.exr"), "A": cam.blur_parameter,
                              "d_f": cam.focus_disparity, "preset": "default", "repeats": 1})
    kinds = [r["kind"] for r in res["rows"]]
    assert kinds == ["full pipeline", "new focus (cached MPI)",
                     "new f-stop (0.7 A, cached MPI)", "quarter-resolution preview",
                     "first preview (no MPI yet, subsampled passes)"]
    assert all(r["seconds"] > 0 and r["cpu_ratio"] > 0 for r in res["rows"])
    text = "\n".join(markdown(res))
    assert "| new focus (cached MPI) |" in text and "cached MPI" in text
