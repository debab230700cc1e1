"""Photo-sized refocus timings: a seeded stand-in for a photograph with a predicted depth.

A monocular depth predictor gives a *smooth* disparity: broad gradients (a ground
plane, a wall) with a few objects whose edges are soft (the network blurs them over a
few pixels). Cut into adaptive planes, such a map gives some 60 planes at the default
preset, nearly every one of them spread over most of the frame as a thin band (a level
set of the gradient): the worst case for per-plane bounding boxes, and the common one
for photographs. :func:`photo_passes` builds one (seeded, any size) together with a
textured colour image; nothing here is shipped data.

:func:`run` times ``refocus.refocus`` on them per preset (CPU time of this process,
which is single-threaded where ``OMP_NUM_THREADS=1``; wall time beside it) with the
peak resident memory of a fresh worker process per row.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import resource
import time
from pathlib import Path

import numpy as np

#: Disparity range of the generated map (1/scene-unit): 0.1 (10 units away) to 1.0.
D_FAR, D_NEAR = 0.1, 0.9
#: Blur-radius span across that range (px) at 2000 px width; scaled with the width,
#: as a real lens's ``A = R f_px`` is. 60 px with the default preset's 0.5 px
#: tolerance gives ~61 planes (the issue's photograph).
SPAN_PX_AT_2000 = 60.0


def _smooth_noise(rng, h: int, w: int, scale: float) -> np.ndarray:
    """Band-limited noise in [-1, 1]: white noise on a coarse grid, bilinear up."""
    from scipy import ndimage

    gh, gw = max(2, int(math.ceil(h / scale)) + 2), max(2, int(math.ceil(w / scale)) + 2)
    coarse = rng.standard_normal((gh, gw))
    ys = np.linspace(0, gh - 2, h)
    xs = np.linspace(0, gw - 2, w)
    out = ndimage.map_coordinates(coarse, np.meshgrid(ys, xs, indexing="ij"), order=3,
                                  mode="nearest")
    return out / max(float(np.abs(out).max()), 1e-12)


def photo_passes(seed: int, width: int, height: int, span_px: float | None = None):
    """``(colour (H, W, 3) float32, depth (H, W) float64, A, d_f)`` of a seeded photo-like
    input: disparity ``d`` from ``D_FAR`` at the top to ``D_NEAR`` at the bottom (a
    ground plane), bent by low-frequency noise, with three soft-edged objects (ellipses
    whose disparity rises over ~1 % of the width, as a predictor's edges do), and a
    multi-scale textured colour (linear radiance, a few highlights above 1). ``A`` spans
    :data:`SPAN_PX_AT_2000` px (scaled with the width; or ``span_px``) over the disparity
    range; the focus is in the middle of it."""
    rng = np.random.default_rng(seed)
    H, W = int(height), int(width)
    y = (np.arange(H) + 0.5)[:, None] / H
    x = (np.arange(W) + 0.5)[None, :] / W
    t = np.clip(0.15 + 0.7 * y + 0.08 * _smooth_noise(rng, H, W, 0.5 * max(H, W))
                + 0.03 * (x - 0.5), 0.0, 1.0)
    d = D_FAR + (D_NEAR - D_FAR) * 0.7 * t
    soft = 0.01 * W
    for _ in range(3):
        cy, cx = rng.uniform(0.3, 0.8) * H, rng.uniform(0.15, 0.85) * W
        ry, rx = rng.uniform(0.08, 0.2) * H, rng.uniform(0.05, 0.15) * W
        dist = (np.sqrt(((np.arange(H)[:, None] - cy) / ry) ** 2
                        + ((np.arange(W)[None, :] - cx) / rx) ** 2) - 1.0) * min(rx, ry)
        inside = 0.5 - 0.5 * np.tanh(dist / soft)
        d_obj = rng.uniform(0.75, 1.0) * D_NEAR
        d = d + inside * np.maximum(d_obj - d, 0.0)
    colour = np.empty((H, W, 3), np.float32)
    base = rng.uniform(0.1, 0.6, 3)
    for c in range(3):
        tex = (0.5 * _smooth_noise(rng, H, W, 0.2 * max(H, W))
               + 0.3 * _smooth_noise(rng, H, W, 16.0) + 0.2 * _smooth_noise(rng, H, W, 3.0))
        colour[..., c] = np.clip(base[c] * (1.0 + 0.8 * tex), 0.0, None)
    # a few small highlights (HDR), as lamps or glints in a photograph
    n = max(4, int(20 * H * W / 2000 / 1333))
    ys, xs = rng.integers(0, H - 3, n), rng.integers(0, W - 3, n)
    for yy, xx in zip(ys, xs):
        colour[yy:yy + 3, xx:xx + 3] = rng.uniform(2.0, 8.0)
    span = SPAN_PX_AT_2000 * (W / 2000.0) if span_px is None else float(span_px)
    A = span / (D_NEAR - D_FAR)
    d_f = 0.5 * (float(d.min()) + float(d.max()))
    return colour, 1.0 / d, A, d_f


def time_refocus(width: int, height: int, preset: str, seed: int = 0) -> dict:
    """One refocus of the generated input: CPU and wall seconds, planes, peak memory
    growth (max RSS of this process, which should be fresh, minus its RSS before)."""
    from mpib_validate.runtime import refocus as R
    from mpib_validate.runtime.request import RefocusRequest
    from mpib_validate.bench.machine import peak_rss_mb
    from mpib_validate.runtime.budget import estimate_request, format_bytes, memory_limit

    colour, depth, A, d_f = photo_passes(seed, width, height)
    passes = R.Passes(colour, depth, "generated", "generated", None, None)
    request = RefocusRequest(passes, A, d_f, preset)
    est = estimate_request(request)
    if est.bytes > memory_limit():  # as `mpib refocus` would refuse it
        return {"size": f"{width}x{height}", "preset": preset, "planes": est.planes,
                "estimate_bytes": est.bytes,
                "skipped": f"estimated {format_bytes(est.bytes)}, over the limit of "
                           f"{format_bytes(memory_limit())} (half of this machine)"}
    before = _rss_now()
    c0, w0 = time.process_time(), time.perf_counter()
    res = R.refocus(request)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    peak = peak_rss_mb() * 2 ** 20
    return {"size": f"{width}x{height}", "preset": preset, "planes": res.info["planes"],
            "largest_radius_px": res.info["largest_radius_px"], "cpu_s": cpu, "wall_s": wall,
            "peak_rss_bytes": int(peak), "rss_before_bytes": int(before),
            "estimate_bytes": est.bytes, "finite": bool(np.isfinite(res.image).all())}


def _rss_now() -> int:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * resource.getpagesize()
    except OSError:
        return 0


def _worker(args):
    return time_refocus(*args)


def run(out: Path, quick: bool = True) -> dict:
    """Time the presets on generated photographs, each in a fresh process (so that the
    peak memory is that row's); writes ``photosize.json`` and ``photosize.md``."""
    from mpib_validate.runtime.io.atomic import write_text
    from mpib_validate.bench.machine import machine_info

    out.mkdir(parents=True, exist_ok=True)
    cases = ([(1000, 667, "default"), (1000, 667, "best"), (2000, 1333, "default")] if quick
             else [(2000, 1333, "default"), (2000, 1333, "best"), (4096, 4096, "default"),
                   (6000, 4000, "default")])
    rows = []
    ctx = mp.get_context("spawn")
    for w, h, preset in cases:
        with ctx.Pool(1, maxtasksperchild=1) as pool:
            row = pool.apply(_worker, ((w, h, preset),))
        rows.append(row)
        if "skipped" in row:
            print(f"bench photosize: {row['size']} {preset}: skipped, {row['skipped']}",
                  flush=True)
            continue
        print(f"bench photosize: {row['size']} {preset}: {row['cpu_s']:.1f} s CPU, "
              f"{row['wall_s']:.1f} s wall, peak {row['peak_rss_bytes'] / 2**30:.2f} GB",
              flush=True)
    result = {"suite": "photosize", "quick": quick, "machine": machine_info(), "rows": rows}
    write_text(out / "photosize.json", json.dumps(result, indent=2) + "\n")
    lines = ["# Photo-sized refocus (generated smooth predicted-like disparity)", "",
             "Each row in a fresh process; CPU time of that process (its threads summed), "
             "wall time beside it; peak = max resident memory of the process.", "",
             "| size | preset | planes | largest radius (px) | CPU (s) | wall (s) | peak (GB) "
             "| estimate (GB) |", "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['size']} | {r['preset']} | {r['planes']} | skipped: {r['skipped']} | "
              f"| | | {r['estimate_bytes'] / 2**30:.2f} |" if "skipped" in r else
              f"| {r['size']} | {r['preset']} | {r['planes']} | {r['largest_radius_px']:.1f} | "
              f"{r['cpu_s']:.1f} | {r['wall_s']:.1f} | {r['peak_rss_bytes'] / 2**30:.2f} | "
              f"{r['estimate_bytes'] / 2**30:.2f} |" for r in rows]
    write_text(out / "photosize.md", "\n".join(lines) + "\n")
    return result
