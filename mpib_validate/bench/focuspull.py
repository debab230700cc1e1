"""Benchmark of a focus pull: a new focus or f-stop on a cached MPI, against the full pipeline.

On the refocus suite's 1920x1080 input (EXR read beforehand), in one process, interleaved
(fresh, cached, f-stop, preview, quick preview; repeated): the full pipeline
(:func:`mpib_validate.runtime.refocus.refocus`: MPI build and Eq. 1), the re-composite of the
cached MPI at a new focus (:class:`mpib_validate.runtime.session.RefocusSession`), at a narrower
aperture (0.7 A, reusing the MPI), the quarter-resolution preview, and the quick preview
of a first pull (before the MPI exists, from subsampled passes). Each is timed by
wall clock and by CPU time (``time.process_time``, all threads of the process), and the
ratios to the full pipeline are reported: on a shared machine the ratios and the CPU
times hold, the wall times do not.
"""

from __future__ import annotations

import statistics
import time

from mpib_validate.bench.machine import peak_rss_mb, worker_main

#: Focus offsets (times d_f) visited by the timed renders, none equal to the build's.
FOCUS_STEPS = (0.6, 1.3, 0.85, 1.6, 1.1)


def _timed(fn):
    c, w = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def focus_pull_timings(cfg) -> dict:
    """``cfg``: ``input`` (EXR), ``A``, ``d_f``, ``preset``, ``repeats``. Returns the median
    wall and CPU seconds of each kind of render and their ratios to the full pipeline."""
    
    from mpib_validate.runtime.refocus import load_passes, refocus
    from mpib_validate.runtime.request import RefocusRequest
    from mpib_validate.runtime.session import RefocusSession

    passes = load_passes(cfg["input"])
    A, d_f, preset = cfg["A"], cfg["d_f"], cfg["preset"]
    session = RefocusSession(passes, preset)
    _, build_w, build_c = _timed(lambda: session.render(d_f, A))
    _, first_prev_w, first_prev_c = _timed(lambda: session.render(d_f, A, 0.25))
    runs = {"full pipeline": [], "new focus (cached MPI)": [], "new f-stop (0.7 A, cached MPI)": [],
            "quarter-resolution preview": [], "first preview (no MPI yet, subsampled passes)": []}
    steps = FOCUS_STEPS[:max(1, int(cfg.get("repeats", 3)))]
    for k, step in enumerate(steps):
        f = d_f * step
        kinds = (("full pipeline", lambda: refocus(RefocusRequest(passes, A, f, preset))),
                 ("new focus (cached MPI)", lambda: session.render(f, A)),
                 ("new f-stop (0.7 A, cached MPI)", lambda: session.render(f, 0.7 * A)),
                 ("quarter-resolution preview", lambda: session.render(f, A, 0.25)),
                 ("first preview (no MPI yet, subsampled passes)",
                  lambda: session.quick_preview(f, A, 0.25)))
        for name, fn in kinds:
            res, w, c = _timed(fn)
            if "cached" in name or name.startswith("quarter"):
                assert res.info["mpi"] == "cached", res.info["mpi"]
            runs[name].append((w, c))
    full_w = statistics.median(w for w, _ in runs["full pipeline"])
    full_c = statistics.median(c for _, c in runs["full pipeline"])
    rows = []
    for name, vals in runs.items():
        w = statistics.median(v[0] for v in vals)
        c = statistics.median(v[1] for v in vals)
        rows.append({"kind": name, "seconds": w, "cpu_seconds": c, "wall_ratio": w / full_w,
                     "cpu_ratio": c / full_c, "runs": len(vals)})
    return {"rows": rows, "build_seconds": build_w, "build_cpu_seconds": build_c,
            "first_preview_seconds": first_prev_w, "first_preview_cpu_seconds": first_prev_c,
            "cache_mb": session.cache_bytes / 1e6, "preset": preset,
            "peak_rss_mb": peak_rss_mb()}


def markdown(result: dict) -> list[str]:
    """The report's section (lines)."""
    if "rows" not in result:
        return ["## Focus pull at 1920x1080", "", f"failed: {result.get('error', '?')}", ""]
    lines = ["## Focus pull at 1920x1080 (cached MPI)", "",
             f"Preset {result['preset']}; one process, interleaved, medians of "
             f"{result['rows'][0]['runs']} runs; CPU time = process time of all threads. The "
             f"first render (MPI build and Eq. 1) took {result['build_seconds']:.2f} s "
             f"({result['build_cpu_seconds']:.2f} s CPU), the first preview (downsampling the MPI "
             f"once) {result['first_preview_seconds']:.2f} s; the session keeps "
             f"{result['cache_mb']:.0f} MB (MPI and preview), peak RSS "
             f"{result['peak_rss_mb']:.0f} MB.", "",
             "| render | time (s) | CPU (s) | time / full | CPU / full |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['kind']} | {r['seconds']:.3f} | {r['cpu_seconds']:.3f} | "
                     f"{r['wall_ratio']:.3f} | {r['cpu_ratio']:.3f} |")
    return lines + [""]


if __name__ == "__main__":
    worker_main(focus_pull_timings)
