"""``mpib bench``: speed and error measurements, written to a report folder."""

from __future__ import annotations

from pathlib import Path

SUITES = ("tracer", "compositor", "refocus")


def run_bench(out: Path, suite: str = "all", quick: bool = True) -> dict:
    results = {}
    for name in (SUITES if suite == "all" else (suite,)):
        if name == "tracer":
            from .tracer import run
        elif name == "compositor":
            from .compositor import run
        elif name == "refocus":
            from .refocus import run
        else:
            raise ValueError(f"unknown benchmark suite {name!r}; choose from {SUITES} or all")
        results[name] = run(Path(out), quick=quick)
    return results
