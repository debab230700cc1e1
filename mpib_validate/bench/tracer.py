"""Benchmark of the Eq. 15 ray tracer: numpy against Dr.Jit, side by side.

The scene is the official generator's example (three fronto-parallel cards at
disparities 0.01, 0.5, 0.9, ``A = 50``, ``d_f = 0.5``) with the official 51-per-side
aperture grid (1,957 samples). Each configuration runs in its own subprocess, so that
its peak memory (``VmHWM``, :func:`~mpib_validate.bench.machine.peak_rss_mb`) is its own; times are the median of the repeats after
a warm-up (the first Dr.Jit run also compiles its kernel, reported separately).
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from mpib_validate.runtime.io.atomic import write_text
from mpib_validate.bench.machine import machine_info, peak_rss_mb, run_worker, worker_main

TARGET_SPEEDUP = 20.0
TARGET_LLVM_SECONDS = 10.0
TARGET_PEAK_MB = 2048.0


def _worker(cfg: dict) -> dict:
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.cards.generate import official_example

    scene = official_example(cfg["size"])
    smp = samples.grid(cfg["grid_side"], pixel="centre")
    times, meta = [], {}
    for i in range(cfg["warmup"] + cfg["repeats"]):
        t0 = time.perf_counter()
        img, meta = trace.trace(scene, smp, backend=cfg["backend"], notices=False)
        dt = time.perf_counter() - t0
        if i == 0:
            first = dt
        if i >= cfg["warmup"]:
            times.append(dt)
    if cfg.get("save"):
        np.save(cfg["save"], img)
    return {"backend_ran": meta["backend"], "notice": meta.get("backend_notice", ""),
            "first_seconds": first, "seconds": times, "median_seconds": statistics.median(times),
            "peak_rss_mb": peak_rss_mb(),
            "samples": len(smp), "cards": len(scene.cards)}


def _run_worker(cfg: dict) -> dict:
    return run_worker("mpib_validate.bench.tracer", cfg)


def run(out: Path, quick: bool = True) -> dict:
    from mpib_validate.runtime.compositor import backend

    out.mkdir(parents=True, exist_ok=True)
    jit = [b for b in ("llvm", "cuda") if backend.resolve(b).name == b]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        plan = [dict(size=512, grid_side=51, backend="numpy", warmup=0, repeats=1)]
        plan += [dict(size=512, grid_side=51, backend=b, warmup=1, repeats=3) for b in jit]
        plan += [dict(size=1024, grid_side=51, backend=b, warmup=0, repeats=1) for b in jit]
        if not quick:
            plan.append(dict(size=1024, grid_side=51, backend="numpy", warmup=0, repeats=1))
        for cfg in plan:
            cfg["save"] = str(Path(tmp) / f"{cfg['backend']}-{cfg['size']}.npy")
            print(f"bench tracer: {cfg['backend']} at {cfg['size']}^2, {cfg['grid_side']}-grid ...",
                  flush=True)
            res = _run_worker(cfg)
            rows.append({**{k: v for k, v in cfg.items() if k != "save"}, **res})
        # agreement with numpy at 512^2
        ref_path = Path(tmp) / "numpy-512.npy"
        for row in rows:
            p = Path(tmp) / f"{row['backend']}-{row['size']}.npy"
            if row["backend"] != "numpy" and row["size"] == 512 and p.exists() and ref_path.exists():
                diff = np.abs(np.load(p) - np.load(ref_path))
                row["max_abs_diff_vs_numpy"] = float(diff.max())

    summary = _summarise(rows)
    result = {"suite": "tracer", "quick": quick, "machine": machine_info(), "rows": rows,
              "summary": summary}
    write_text(out / "tracer.json", json.dumps(result, indent=2) + "\n")
    write_text(out / "tracer.md", _markdown(result))
    for line in summary["headlines"]:
        print(line)
    print(f"wrote {out / 'tracer.md'}")
    return result


def _find(rows, backend, size):
    for r in rows:
        if r["backend"] == backend and r["size"] == size and "median_seconds" in r:
            return r
    return None


def _summarise(rows) -> dict:
    heads = []
    numpy512 = _find(rows, "numpy", 512)
    llvm512 = _find(rows, "llvm", 512)
    s = {"headlines": heads}
    if numpy512 and llvm512:
        speedup = numpy512["median_seconds"] / llvm512["median_seconds"]
        s["speedup_llvm_vs_numpy_512"] = speedup
        heads.append(
            f"At 512x512 with 3 cards and 1,957 aperture samples, Dr.Jit LLVM takes "
            f"{llvm512['median_seconds']:.2f} s against numpy's {numpy512['median_seconds']:.1f} s: "
            f"{speedup:.1f}x faster (target >= {TARGET_SPEEDUP:.0f}x: "
            f"{'met' if speedup >= TARGET_SPEEDUP else 'NOT met'}; "
            f"target < {TARGET_LLVM_SECONDS:.0f} s: "
            f"{'met' if llvm512['median_seconds'] < TARGET_LLVM_SECONDS else 'NOT met'}).")
    for r in rows:
        if r["size"] == 1024 and "peak_rss_mb" in r:
            ok = r["peak_rss_mb"] < TARGET_PEAK_MB
            heads.append(f"At 1024x1024, {r['backend']} peaks at {r['peak_rss_mb']:.0f} MB "
                         f"(target < {TARGET_PEAK_MB:.0f} MB: {'met' if ok else 'NOT met'}).")
    for r in rows:
        if "max_abs_diff_vs_numpy" in r:
            heads.append(f"{r['backend']} and numpy differ by at most {r['max_abs_diff_vs_numpy']:.3g} "
                         f"per pixel at 512x512.")
    return s


def _markdown(result) -> str:
    m = result["machine"]
    lines = ["# Ray tracer benchmark (Eq. 15)", "",
             f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} cores; "
             f"Python {m['python']}, numpy {m.get('numpy')}, drjit {m.get('drjit', '-')}.", "",
             "Scene: the official example (3 fronto-parallel cards at d = 0.01, 0.5, 0.9; "
             "A = 50; d_f = 0.5); the official 51-per-side aperture grid (1,957 samples), "
             "pixel centres.", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    lines += ["| backend | size | samples | first run (s) | median (s) | repeats | peak RSS (MB) | note |",
              "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        if "error" in r:
            lines.append(f"| {r['backend']} | {r['size']} | - | - | - | - | - | failed: {r['error']} |")
            continue
        lines.append(f"| {r['backend_ran']} | {r['size']}x{r['size']} | {r['samples']} | "
                     f"{r['first_seconds']:.2f} | {r['median_seconds']:.2f} | {len(r['seconds'])} | "
                     f"{r['peak_rss_mb']:.0f} | {r['notice']} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    worker_main(_worker)
