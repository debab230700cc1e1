"""Refocus from a cached MPI (mpib_validate.runtime.session) and `mpib refocus --mpi-cache`."""

from __future__ import annotations

import os
from pathlib import Path

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
from mpib_validate.runtime.request import RefocusRequest
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
        assert np.array_equal(got.image, refocus(RefocusRequest(passes, A, d_f)).image)
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
    fresh = refocus(RefocusRequest(passes, 0.7 * A, d_f)).image
    assert psnr(np.clip(fresh[..., :3], 0, 1), np.clip(narrower.image[..., :3], 0, 1)) > 50.0
    too_narrow = s.render(d_f, 0.9 * REUSE_DOWN_TO * A)
    assert too_narrow.info["mpi"] == "built" and s.builds == 2
    wider = s.render(d_f, 1.2 * A)
    assert wider.info["mpi"] == "built" and s.builds == 3
    assert np.array_equal(wider.image, refocus(RefocusRequest(passes, 1.2 * A, d_f)).image)
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


def _forge(cache, change):
    """Rewrite the one entry of ``cache``: ``change(arrays, meta)`` edits the layers and
    the description in place; the checksum is then made to match, as a careful forger
    (or a program that re-saves the files) would."""
    import json

    from mpib_validate.runtime.layers.cache import file_sha256

    (npz,) = cache.glob("*.npz")
    meta = npz.with_suffix(".json")
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    m = json.loads(meta.read_text())
    change(arrays, m)
    with open(npz, "wb") as fh:
        np.savez(fh, **arrays)
    m["sha256"] = file_sha256(npz)
    meta.write_text(json.dumps(m))


def _nan_layer(a, m):
    a["rgba0"] = a["rgba0"].copy()
    a["rgba0"][0, 0, 0] = np.nan


def _five_channels(a, m):
    for k in [k for k in a if k.startswith("rgba")]:
        a[k] = np.concatenate([a[k], a[k][..., 3:4]], axis=-1)


def _smaller_frame(a, m):
    a["meta"] = a["meta"].copy()
    a["meta"][:2] //= 2
    for k in [k for k in a if k.startswith("rgba")]:
        a[k] = a[k][::2, ::2]


def _outside_canvas(a, m):
    a["where0"] = a["where0"].copy()
    a["where0"][1] = 10_000


@pytest.mark.parametrize("damage", [
    "nan", "channels", "other-frame", "outside", "truncated", "other-key", "nested-json",
    "not-an-object"])
def test_cli_mpi_cache_checks_every_entry_before_use(scene_file, tmp_path, damage):
    """A cache folder is untrusted input: an entry with NaN layers, the wrong channel
    count, another frame's layers, a layer outside the canvas, a truncated file, another
    key's description or a hostile JSON is not used; the MPI is rebuilt with a one-line
    notice naming the entry, and the output equals a fresh one."""
    import json

    d, _ = scene_file
    cache = tmp_path / "cache"
    rc, stdout, err = run("refocus", d / "in.exr", "-o", tmp_path / "fresh.exr", "-q",
                          "--no-preview", "--mpi-cache", cache)
    assert rc == 0, err
    (npz,) = cache.glob("*.npz")
    meta = npz.with_suffix(".json")
    if damage == "nan":
        _forge(cache, _nan_layer)
    elif damage == "channels":
        _forge(cache, _five_channels)
    elif damage == "other-frame":
        _forge(cache, _smaller_frame)
    elif damage == "outside":
        _forge(cache, _outside_canvas)
    elif damage == "truncated":
        npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])
    elif damage == "other-key":
        m = json.loads(meta.read_text())
        m["key"] = "0" * 64
        meta.write_text(json.dumps(m))
    elif damage == "nested-json":
        meta.write_text("[" * 5000 + "]" * 5000)
    elif damage == "not-an-object":
        meta.write_text("[1, 2, 3]")
    rc, stdout, err = run("refocus", d / "in.exr", "-o", tmp_path / "again.exr", "-q",
                          "--no-preview", "--mpi-cache", cache)
    assert rc == 0, err
    assert "Traceback" not in err
    notices = [l for l in err.splitlines() if "MPI cache entry" in l]
    assert len(notices) == 1 and npz.name in notices[0] and "rebuilding" in notices[0], err
    assert "built the MPI" in stdout
    fresh = read_exr(tmp_path / "fresh.exr").channels
    again = read_exr(tmp_path / "again.exr").channels
    assert all(np.array_equal(fresh[k], again[k]) for k in fresh)


def test_cache_refuses_an_entry_that_declares_too_much_memory(scene_file, tmp_path):
    """The sizes an entry's archive declares are checked before anything is
    decompressed: a layer declared larger than the memory limit is refused from its
    header."""
    import io
    import json
    import zipfile

    from mpib_validate.runtime.layers import cache as C
    from mpib_validate.runtime.refocus import load_passes

    d, cam = scene_file
    passes = load_passes(d / "in.exr")
    folder = tmp_path / "cache"
    result = refocus(RefocusRequest(passes, cam.blur_parameter, cam.focus_disparity),
                     cache=C.DiskCache(folder))
    entry = Path(result.info["mpi_cache"]["entry"])
    H, W = passes.colour.shape[:2]
    margin = 0
    buf = io.BytesIO()
    header = {"descr": "<f4", "fortran_order": False, "shape": (40000, 40000, 4)}
    with zipfile.ZipFile(entry, "w") as zf:
        for name in ("meta", "where0"):
            b = io.BytesIO()
            np.save(b, np.array([H, W, margin, 1], np.int64) if name == "meta"
                    else np.array([0.5, 0, 0, -1.0]))
            zf.writestr(f"{name}.npy", b.getvalue())
        np.lib.format.write_array_header_1_0(buf, header)
        zf.writestr("rgba0.npy", buf.getvalue())  # the header alone: no data follows
    meta = entry.with_suffix(".json")
    m = json.loads(meta.read_text())
    m["sha256"] = C.file_sha256(entry)
    meta.write_text(json.dumps(m))
    built, notice = C.load(folder, entry.stem, (H, W), 4)
    assert built is None and "more than the limit" in notice, notice


def test_cli_mpi_cache_entry_that_is_not_a_file_is_left_alone(scene_file, tmp_path):
    """An entry path that is a folder (or any non-regular file) is neither used nor
    replaced: the refocus runs, says so in one line, and the folder stays."""
    d, _ = scene_file
    cache = tmp_path / "cache"
    rc, _, err = run("refocus", d / "in.exr", "-o", tmp_path / "fresh.exr", "-q",
                     "--no-preview", "--mpi-cache", cache)
    assert rc == 0, err
    (npz,) = cache.glob("*.npz")
    npz.unlink()
    npz.mkdir()
    rc, stdout, err = run("refocus", d / "in.exr", "-o", tmp_path / "again.exr", "-q",
                          "--no-preview", "--mpi-cache", cache)
    assert rc == 0 and "Traceback" not in err, err
    assert npz.is_dir() and sorted(p.name for p in cache.iterdir()) == sorted(
        [npz.name, npz.with_suffix(".json").name])
    assert "not a regular file" in err and "not cached" in err
