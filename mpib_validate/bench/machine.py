"""What a benchmark ran on (machine, versions), and the helpers every suite shares."""

from __future__ import annotations

import os
import platform


def machine_info() -> dict:
    info = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": _cpu_name(),
        "cpu_count": os.cpu_count(),
    }
    try:
        info["affinity_cores"] = len(os.sched_getaffinity(0))
    except AttributeError:
        pass
    from importlib import metadata

    for pkg in ("numpy", "drjit", "OpenEXR", "scipy", "scikit-image", "mitsuba", "bpy"):
        try:
            info[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return info


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def mean_table(rows, family: str, keys) -> list[dict]:
    """One row per method (first-seen order): the mean of ``keys`` over the family's scenes."""
    import math

    import numpy as np

    methods = []
    for r in rows:
        if r["family"] == family and r["method"] not in methods:
            methods.append(r["method"])
    table = []
    for m in methods:
        rs = [r for r in rows if r["family"] == family and r["method"] == m]
        table.append({"method": m, **{
            k: float(np.mean([r[k] for r in rs if k in r])) if any(k in r for r in rs) else math.nan
            for k in keys}})
    return table


def finish(out, name: str, result: dict, markdown) -> dict:
    """Write ``<name>.json`` and ``<name>.md`` (atomically) and print the headlines."""
    import json

    from mpib_validate.runtime.io.atomic import write_text

    write_text(out / f"{name}.json", json.dumps(result, indent=2, default=float) + "\n")
    write_text(out / f"{name}.md", markdown(result))
    for line in result.get("summary", {}).get("headlines", []):
        print(line)
    print(f"wrote {out / (name + '.md')}")
    return result


def peak_rss_mb() -> float:
    """Peak resident memory of this process image, in MB: ``VmHWM`` of
    ``/proc/self/status``. Not ``getrusage``'s ``ru_maxrss``: that survives ``execve``,
    so a worker started from a large parent (``subprocess``, multiprocessing's
    ``spawn``) reports the parent's peak at the fork (all the photo-size rows of a
    ``mpib bench`` run read 1.48 GB). Falls back to ``ru_maxrss`` where ``/proc`` is
    absent."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def peak_python_mb(fn) -> float:
    """Peak memory that ``fn()`` allocates through Python and numpy (tracemalloc), in MB.

    Run separately from the timed calls (tracing slows them down). Memory that C or JIT
    libraries allocate themselves (scipy.fft's work buffers, Dr.Jit, Cycles) is not
    counted; the 1920x1080 runs report the whole process's peak instead."""
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 2 ** 20
    finally:
        tracemalloc.stop()


def run_worker(module: str, cfg: dict) -> dict:
    """Run one measurement in a fresh process (``python -m module --worker JSON``), so its
    peak memory is its own; returns the JSON it printed last, or ``{"error": line}``."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", module, "--worker", json.dumps(cfg)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        return {"error": ((r.stderr or r.stdout).strip().splitlines() or ["failed"])[-1]}
    return json.loads(r.stdout.strip().splitlines()[-1])


def worker_main(fn) -> None:
    """The ``--worker JSON`` entry point of a suite module: print ``fn(cfg)`` as JSON."""
    import argparse
    import json

    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", required=True)
    print(json.dumps(fn(json.loads(ap.parse_args().worker))))
