"""``mpib bench``: speed and error measurements, written to a report folder."""

from __future__ import annotations

from pathlib import Path


def run_bench(out: Path, suite: str = "tracer", quick: bool = True) -> dict:
    if suite == "tracer":
        from .tracer import run

        return run(Path(out), quick=quick)
    raise ValueError(f"unknown benchmark suite {suite!r}")
