"""``mpib bench``: speed and error of every renderer, written to a report folder.

Suites (each writes ``<suite>.md`` and ``<suite>.json``): ``tracer`` (numpy against
Dr.Jit), ``compositor`` (Eq. 1, the middle setting, the exact renderer, the fast paths,
and the ray tracer, Mitsuba and Cycles at a sweep of sample counts, on exact layers),
``refocus`` (from colour + depth: the MPI with and without the fill, the presets, the
classical baselines, Blender's Defocus node; ``mpib refocus`` at 1920x1080), ``photos``
(the same from a degraded, predicted-looking disparity, with and without the guided
refinement, against the Defocus node fed it; a real photograph), ``addon``
(the Blender extension's operator at 1920x1080, per preset), ``blender`` (ordinary 3D
Blender scenes against Cycles' depth of field: every preset, the Defocus node, the
exact MPI renderer; emitter radius and energy),
``hardcases`` (each named generator case, per method), ``references`` (Mitsuba and
Cycles time and noise against samples per pixel), ``scaling``, ``photosize``
(``mpib refocus`` per preset on generated photographs with a smooth predicted-like
depth, 1000x667 to 6000x4000, CPU time and peak memory) and ``official`` (the
official MPIB renderer's computation in CPU torch on the same 32 planes, side by side;
skipped when the optional torch extra is absent). ``index.md`` gathers the headlines, Pareto plots and boundary crops.
"""

from __future__ import annotations

import importlib
from pathlib import Path

SUITES = ("tracer", "compositor", "refocus", "photos", "addon", "hardcases", "references",
          "scaling", "photosize", "blender", "official", "lens")


def run_bench(out: Path, suite: str = "all", quick: bool = True, executor=None) -> dict:
    """Run the suites; ``executor`` (see :mod:`mpib_validate.executor`) spreads the
    per-scene work of the compositor and refocus suites. Their results are the same on
    any executor, but times are only comparable when each scene had the machine alone
    (the default, in-process)."""
    import inspect

    out = Path(out)
    names = SUITES if suite == "all" else (suite,)
    results = {}
    for name in names:
        if name not in SUITES:
            raise ValueError(f"unknown benchmark suite {name!r}; choose from {SUITES} or all")
        module = importlib.import_module(f"{__name__}.{name}")
        kw = {"executor": executor} if "executor" in inspect.signature(module.run).parameters else {}
        results[name] = module.run(out, quick=quick, **kw)
    from mpib_validate.bench.report import write_index

    print(f"wrote {write_index(out, results)}")
    return results
