"""The benchmark's own code paths on a tiny real run (the numbers come from `mpib bench`)."""

from __future__ import annotations

import math

import pytest

from mpib_validate.bench import compositor, report
from mpib_validate.cards.generate import GeneratorSettings, generate


@pytest.fixture(scope="module")
def rows():
    out = []
    for family in ("constant", "varying"):
        scene = generate(0, family, settings=GeneratorSettings(width=32, height=32))
        out += compositor._scene_rows(scene, f"{family}-0", family, ref_spp=64, repeats=1)
    return out


def test_compositor_rows_hold_every_method_and_metric(rows):
    methods = {r["method"] for r in rows}
    for m in ("eq1-adaptive", "eq1-uniform32", "middle-k2", "exact-1024spp", "path-plain",
              "path-fft", "path-crop"):
        assert m in methods
    assert any(m.startswith("trace-") for m in methods)
    for r in rows:
        if r["method"].startswith("reference"):
            continue
        assert r["seconds"] > 0 and not math.isnan(r["psnr"]) and "psnr_ob" in r and "ssim" in r
    # the fast paths change nothing but rounding
    for r in rows:
        if r["method"] in ("path-fft", "path-crop", "path-auto+crop"):
            assert abs(r["delta_psnr_vs_plain"]) < 1e-3


def test_pareto_plot_is_written(rows, tmp_path):
    pytest.importorskip("matplotlib")
    for family in ("constant", "varying"):
        p = tmp_path / f"{family}.png"
        report.pareto_plot(rows, family, p)
        assert p.stat().st_size > 10_000 and p.read_bytes()[:4] == b"\x89PNG"


def test_addon_bench_camera_reproduces_the_blur_parameter_and_focus():
    """The add-on suite sets a Blender lens so that the calibration gives the refocus
    suite's A and d_f; the camera model must agree to rounding."""
    from mpib_validate.bench.addon import _camera_for
    from mpib_validate.runtime.camera import blender_camera

    lens = _camera_for(74.3, 0.2514, 1920)
    cam = blender_camera(lens["lens_mm"], lens["sensor_mm"], 24.0, "HORIZONTAL", 1920, 1080,
                         lens["fstop"], lens["focus_distance"])
    assert math.isclose(cam.blur_parameter, 74.3, rel_tol=1e-12)
    assert math.isclose(cam.focus_disparity, 0.2514, rel_tol=1e-12)


def test_pareto_labels_never_overlap(tmp_path):
    """Points on top of each other still get numbers whose boxes are disjoint, and the
    key lists every method once."""
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    pts = [(1.0, 30.0, f"m{k}") for k in range(6)] + [(1.05, 30.02, "near"), (10.0, 20.0, "far")]
    ax.scatter([p[0] for p in pts], [p[1] for p in pts])
    ax.set_xscale("log")
    key = report.label_points(ax, pts)
    fig.canvas.draw()
    boxes = [t.get_window_extent() for t in ax.texts if t.get_text().isdigit()]
    assert len(boxes) == len(pts) and sorted(label for _, label in key) == sorted(p[2] for p in pts)
    for i in range(len(boxes)):
        for j in range(i):
            assert not boxes[i].overlaps(boxes[j]), (i, j)
    plt.close(fig)


def _child_peaks(_):
    import resource

    from mpib_validate.bench.machine import peak_rss_mb

    return peak_rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def test_a_workers_peak_memory_is_its_own():
    """getrusage's ru_maxrss survives execve, so a worker spawned by a large parent
    reported the parent's peak (every photo-size row of a full `mpib bench` read
    1.48 GB); peak_rss_mb reads the worker's own high-water mark. A parent holding
    400 MB more than its worker needs: the worker's peak must stay far below it."""
    import multiprocessing as mp

    import numpy as np

    big = np.ones(50_000_000)  # 400 MB, touched
    with mp.get_context("spawn").Pool(1) as pool:
        own, inherited = pool.apply(_child_peaks, (0,))
    assert big.sum() == 50_000_000
    assert own < 300, (own, inherited)  # a fresh interpreter with numpy: ~35 MB
