"""The memory estimates of mpib_validate.runtime.budget against the peak resident memory of real
runs, each in a fresh process (the estimate must neither miss a large job nor refuse an
ordinary one)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mpib_validate.runtime import budget

MEASURE_REFOCUS = r"""
import json, os, sys
import numpy as np
from mpib_validate.runtime import budget
from mpib_validate.runtime.layers.passes import depth_to_disparity
from mpib_validate.runtime.refocus import Passes, refocus, write_result
from mpib_validate.runtime.request import RefocusRequest

case, n, A, preset, out = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4], sys.argv[5]
rng = np.random.default_rng(0)
if case == "random":
    depth = rng.uniform(1, 10, (n, n))
elif case == "tilted":
    y = np.arange(n)[:, None] / n
    depth = np.broadcast_to(1.0 / (0.05 + 0.9 * y), (n, n)).copy()
    depth[n // 4:n // 2, n // 4:n // 2] = 1.2
elif case != "photo":
    depth = np.full((n, n), 20.0)
    depth[n // 5:n // 2, n // 5:n // 2] = 2.0
    depth[n // 2:, n // 2:] = 5.0
if case == "photo":  # a smooth predicted-like depth: thin band-like (tiled) planes
    from mpib_validate.bench.photosize import photo_passes
    colour, depth, _, _ = photo_passes(0, n, 2 * n // 3, span_px=A)
    A = A / 0.8  # the generator's disparity range is 0.8
else:
    colour = rng.random((n, n, 3)).astype(np.float32)
D = depth_to_disparity(depth)
df = float(np.median(D))
request = RefocusRequest(Passes(colour, depth, "c", "d"), A, df, preset)
est = budget.estimate_request(request)
rss = lambda: int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
# the peak of this process's own memory (ru_maxrss would keep the forking parent's)
hwm = lambda: 1024 * int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])
base = rss()
res = refocus(request)
write_result(out, res)
peak = hwm()
print(json.dumps({"estimate": est.bytes - est.parts["inputs"], "used": peak - base,
                  "planes": res.info["planes"], "planes_estimate": est.planes}))
"""


@pytest.mark.parametrize("case, n, A, preset", [
    ("random", 512, 30.0, "default"),  # every plane covers the frame; 99 % edge pixels
    ("tilted", 512, 60.0, "best"),  # a slanted floor: thin planes, 2 x 2 sub-apertures
    ("cards", 256, 2000.0, "default"),  # three depths, a 900 px blur: one big FFT
    ("photo", 768, 40.0, "default"),  # smooth depth, 34 planes mostly stored as tiles
])
def test_refocus_estimate_tracks_the_measured_peak(tmp_path, case, n, A, preset):
    """Measured (2 cores): estimate / peak = 0.87, 1.17, 1.16 and 1.09 (photo, tiled
    layers) for these cases with float32 FFTs and the re-measured build constants (0.95
    to 1.19 over the eight calibration runs of 512^2 to 1500x1000). Allocator slack and other processes' pages make the peak noisy: we require
    0.7 to 1.6."""
    r = subprocess.run([sys.executable, "-c", MEASURE_REFOCUS, case, str(n), str(A), preset,
                        str(tmp_path / "out.exr")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)
    assert m["planes_estimate"] == m["planes"]  # exact plane placement below 4 Mpx
    assert 0.7 < m["estimate"] / m["used"] < 1.6, m


MEASURE_LAYERED = r"""
import json, os, sys
import numpy as np
from mpib_validate.runtime import budget
from mpib_validate.runtime.io import exr  # imported before the baseline, as the others
from mpib_validate.runtime.refocus import load_layered_passes, refocus, write_result
from mpib_validate.runtime.request import RefocusRequest

status = lambda key: 1024 * int(next(l for l in open("/proc/self/status")
                                     if l.startswith(key)).split()[1])
path, A, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
start = status("VmRSS")
passes = load_layered_passes(path)
kept = status("VmRSS") - start  # what the layered input holds
request = RefocusRequest(passes, A, float(np.median(1.0 / passes.depth)), "default")
est = budget.estimate_request(request)
base = status("VmRSS")
try:  # the peak from here on (the EXR read's own peak is budgeted before any decode)
    open("/proc/self/clear_refs", "w").write("5")
except OSError:
    print(json.dumps({"skip": "cannot reset the peak resident memory"}))
    sys.exit(0)
res = refocus(request)
write_result(out, res)
print(json.dumps({"estimate": est.bytes, "used": kept + status("VmHWM") - base,
                  "kept": kept, "inputs": est.parts["inputs"], "planes": res.info["planes"],
                  "planes_estimate": est.planes}))
"""


def _layered_exr(path, groups: int, W: int, H: int) -> None:
    """A layered render as Blender writes it (``mpib_group_<k>`` view layers, far to
    near, each with Combined and Depth; the farthest with the Environment pass): a
    wall at depth 20 filling the view with a box at 6 standing out of it (a depth
    jump inside the farthest group: edges, fill), and ``groups - 1`` textured discs at
    depths 2 / (k + 1) with anti-aliased rims, overlapping one another."""
    from mpib_validate.runtime.io.exr import write_exr

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    box = (np.abs(x - 0.3 * W) < 0.1 * W) & (np.abs(y - 0.55 * H) < 0.08 * H)
    layers = [(np.ones((H, W)), np.where(box, 6.0, 20.0))]
    for k in range(1, groups):
        cx, cy = rng.uniform(0.25, 0.75) * W, rng.uniform(0.3, 0.7) * H
        r = rng.uniform(0.12, 0.22) * min(W, H)
        a = np.clip(r - np.hypot(x - cx, y - cy) + 0.5, 0.0, 1.0)
        layers.append((a, np.where(a > 0, 2.0 / (k + 1), 1e10)))  # Cycles: 1e10 on nothing
    ch = {}
    for k, (a, z) in enumerate(layers):
        rgb = rng.random((H, W, 3)) * a[..., None]  # premultiplied
        for i, c in enumerate("RGBA"):
            ch[f"mpib_group_{k}.Combined.{c}"] = (rgb[..., i] if i < 3 else a).astype(np.float32)
        ch[f"mpib_group_{k}.Depth.Z"] = z.astype(np.float32)
    for c in "RGB":
        ch[f"mpib_group_0.Environment.{c}"] = np.zeros((H, W), np.float32)
    write_exr(path, ch)


def test_layered_estimate_tracks_the_measured_peak(tmp_path):
    """A layered render keeps every group's colour, alpha and depth (264 B/px for five
    groups, against the 28 B/px of a single pass) and builds a sheet per nearer group;
    its planes are planned over every group's content, hidden parts included. The
    estimate (its inputs and its work) against the resident memory the refocus adds to
    the process before the input is read (the inputs it keeps, then the peak of the
    work; the EXR read's own peak is checked from the header before, and excluded).
    Measured (2 cores): estimate / peak 0.91 here (5 groups, 1024x768); 0.73 to 1.11 at
    512x384 to 1024x768 and 0.91 to 1.10 at 1536x1152 and 3072x2304 over five scenes of
    2 to 5 groups (at the smaller sizes the allocator keeps what the build freed
    resident). The same bounds as the single-pass cases: 0.7 to 1.6."""
    path = tmp_path / "layered.exr"
    _layered_exr(path, 5, 1024, 768)
    r = subprocess.run([sys.executable, "-c", MEASURE_LAYERED, str(path), "40",
                        str(tmp_path / "out.exr")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)
    if "skip" in m:
        pytest.skip(m["skip"])
    assert m["planes_estimate"] == m["planes"]  # every group's planes, hidden ones too
    assert 0.7 < m["estimate"] / m["used"] < 1.6, m


def test_layers_dominate_for_random_depth():
    """Random depth: every plane covers the frame (the reported 11.7 GB peak of a 4096^2
    random depth, predicted from the depth alone). With the default preset's additive
    slabs a plane whose two intervals fall in different slabs holds two layers, each
    over the frame: 46 planes are 68 full-frame layers at A = 50. The estimate of the
    layers is the bytes of the MPI actually built (256^2; measured within 0.6 %: a
    random pixel may miss a layer's last row or column)."""
    from mpib_validate.runtime.layers.passes import layers_from_passes
    from mpib_validate.runtime.presets import PRESETS

    rng = np.random.default_rng(0)
    D = 1.0 / rng.uniform(1, 10, (1024, 1024))
    est = budget.refocus_estimate(D, 50.0, 0.5, PRESETS["default"])
    assert est.planes == 46
    assert est.largest_part() == "layers"
    small = 1.0 / rng.uniform(1, 10, (256, 256))
    mpi, _ = layers_from_passes(rng.random((256, 256, 3)).astype(np.float32), small, 50.0,
                                PRESETS["default"].passes)
    built = sum(l.nbytes for l in mpi.layers)
    est_small = budget.refocus_estimate(small, 50.0, 0.5, PRESETS["default"])
    assert est_small.parts["layers"] == pytest.approx(built, rel=0.02)


def test_binned_intervals_agree_with_the_exact_ones():
    """Beyond 4 Mpx the content intervals come from bins one plane step wide."""
    rng = np.random.default_rng(3)
    D = np.concatenate([np.full(1000, 0.05), rng.uniform(0.3, 0.5, 5000), np.full(10, 0.9)])
    step = 2 * 0.5 / 40.0
    from mpib_validate.runtime.layers import passes

    exact = passes.content_intervals(D, step)
    old = passes.EXACT_INTERVALS_PX
    try:
        passes.EXACT_INTERVALS_PX = 0
        binned = passes.content_intervals(D[None, :], step, exact=False)
    finally:
        passes.EXACT_INTERVALS_PX = old
    assert len(binned) == len(exact) == 3
    for (a, b), (c, d) in zip(exact, binned):
        assert c <= a + 1e-12 and d >= b - 1e-12 and d - c <= b - a + step + 1e-12


def test_check_names_the_option_and_the_largest_part():
    est = budget.Estimate("rendering 10x10 with trace", {"sample set": 5 << 30, "textures": 1 << 20})
    with pytest.raises(budget.BudgetError) as exc:
        budget.check(est, 1 << 30)
    msg = str(exc.value)
    assert "--max-memory-gb" in msg and "largest part: sample set 5.0 GB" in msg
    assert budget.check(est, 6 << 30) is est
    assert budget.memory_limit(2.5) == int(2.5 * (1 << 30))
    assert budget.memory_limit() == int(budget.DEFAULT_FRACTION * budget.machine_memory())


def test_sample_set_estimate():
    """A 2^20-point Sobol set: measured ~150 B per sample while it is made."""
    code = ("import os; from mpib_validate.runtime import samples\n"
            "rss = int(open('/proc/self/statm').read().split()[1]) * os.sysconf('SC_PAGE_SIZE')\n"
            "s = samples.stratified(1 << 20)\n"
            "hwm = next(l for l in open('/proc/self/status') if l.startswith('VmHWM'))\n"
            "print(1024 * int(hwm.split()[1]) - rss)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    used = int(r.stdout)
    _, est = budget.samples_estimate("sobol", 1 << 20, 0)
    assert 0.7 < est / used < 1.6, (est, used)


def test_tiled_blur_constants_follow_the_compositor_batch():
    """budget does not import the compositor's kernels; its batch-sized constants must
    still equal the batch the compositor uses."""
    from mpib_validate.runtime.compositor import kernels

    assert budget.TILED_OUTPUT_BYTES == kernels.BATCH_BYTES
    assert budget.TILED_BLUR_BYTES == 4 * kernels.BATCH_BYTES
