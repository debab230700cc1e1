"""``mpib dataset``: many generated card scenes with their ray-traced references.

Each sample is a folder ``sample-<seed>/`` holding the scene (``scene/``: JSON + EXR
textures) and its render (``render.exr``: defocused image, all-in-focus image, depth,
disparity, per-card hit layers), plus ``done.json``. A sample is built in a temporary
folder and renamed into place only when complete, so an interrupted run leaves no
half-written sample, and a rerun skips every sample that has its ``done.json``.
Samples are independent, so any executor (:mod:`mpib_validate.executor`) can build them;
the same seed gives the same scene and the same pixels whichever runs it.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import time
from pathlib import Path

FAMILIES = ("constant", "varying", "mixed")


def sample_dir(out, seed: int) -> Path:
    return Path(out) / f"sample-{seed:06d}"


def family_of(family: str, seed: int) -> str:
    return ("constant", "varying")[seed % 2] if family == "mixed" else family


def make_sample(item: tuple) -> dict:
    """Build one sample: ``item = (out, seed, family, width, height, spp)``."""
    from . import samples, trace
    from .atomic import write_text
    from .generate import GeneratorSettings, generate
    from .render_io import write_render
    from .scene import save_scene

    out, seed, family, width, height, spp = item
    final = sample_dir(out, seed)
    if (final / "done.json").exists():
        return {"seed": seed, "skipped": True}
    t0 = time.perf_counter()
    tmp = Path(out) / f".tmp-{final.name}-{os.getpid()}-{secrets.token_hex(4)}"
    try:
        scene = generate(seed, family_of(family, seed),
                         settings=GeneratorSettings(width=width, height=height))
        save_scene(scene, tmp / "scene")
        result = trace.render(scene, samples.stratified(spp, seed=seed), notices=False)
        write_render(tmp / "render.exr", result, scene, preview=False)
        info = {"seed": seed, "family": family_of(family, seed), "size": [width, height],
                "spp": spp, "cards": len(scene.cards), "backend": result.meta["backend"],
                "max_blur_radius_px": scene.max_blur_radius()}
        write_text(tmp / "done.json", json.dumps(info, indent=2) + "\n")
        if final.exists():  # an earlier run died after a rename could not happen
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return {**info, "skipped": False, "seconds": time.perf_counter() - t0}


def build_dataset(out, count: int, family: str = "mixed", size=(256, 256), spp: int = 1024,
                  start: int = 0, executor=None) -> dict:
    """Build (or complete) a dataset of ``count`` samples from seed ``start`` on."""
    from .atomic import write_text
    from .executor import make_executor

    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    if count < 1 or start < 0:
        raise ValueError("count must be >= 1 and start >= 0")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.glob(".tmp-sample-*"):  # left by an interrupted run
        shutil.rmtree(stale, ignore_errors=True)
    items = [(str(out), seed, family, int(size[0]), int(size[1]), int(spp))
             for seed in range(start, start + count)]
    executor = executor or make_executor()
    results = executor.map(make_sample, items)
    done = sorted(p.name for p in out.glob("sample-*") if (p / "done.json").exists())
    summary = {"count": len(done), "built": sum(not r["skipped"] for r in results),
               "skipped": sum(r["skipped"] for r in results), "executor": executor.kind,
               "samples": done}
    write_text(out / "index.json", json.dumps(summary, indent=2) + "\n")
    return summary
