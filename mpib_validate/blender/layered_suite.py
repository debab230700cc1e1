"""Layered renders of the Blender scene suite (:mod:`mpib_validate.blender.scenes`).

For each scene (the sharp passes do not depend on the focus, so one render serves both
foci) the depth groups of :mod:`mpib_validate.runtime.blender.layers` are chosen automatically
(bounding boxes, refined by the suite's own sharp Z pass: the "last render"), one view
layer per group, and rendered as the suite's sharp passes are:

- colour: ``sharp_spp`` samples, the unbiased sample subset, depth of field off, only
  the group layers (the artist's view layer off);
- depth: a separate 1-spp render of the same layers (Z from sample 0, the pixel
  centre), as :func:`~mpib_validate.blender.scenes.render_sharp` does for the single
  pass.

``layers.exr``: ``mpib_group_<k>.Combined.R/G/B/A``, ``mpib_group_<k>.Depth.Z`` (and the
farthest group's ``Environment`` pass), with the suite's camera header, so that
:func:`mpib_validate.runtime.refocus.load_layered_passes` and ``mpib refocus`` read it.

Render cost: the layered colour render against the single-pass colour render of the
same scene and samples, timed in the same run as single, layered, single (A, B, A: the
mean of the two singles, so a drift of the machine's load over the three cancels to
first order); both wall time and the process's CPU time (``resource.getrusage``:
every Cycles thread), as ratios.

Cached: ``<out>/layered-<scene>-<W>x<H>-<sharp_spp>spp/`` with ``meta.json`` (its key:
the spec, samples, :data:`~mpib_validate.blender.scenes.BUILDER_VERSION` and
:data:`LAYERED_VERSION`) written last.
"""

from __future__ import annotations

import hashlib
import json
import resource
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

#: Bump when the grouping or the layered render settings change: part of the cache key.
LAYERED_VERSION = 1
#: Depth groups per scene at most (the extension's default).
MAX_GROUPS = 3


def _cpu_seconds() -> float:
    """CPU time of this process and its threads (user + system), seconds."""
    u = resource.getrusage(resource.RUSAGE_SELF)
    return u.ru_utime + u.ru_stime


def layered_key(spec, sharp_spp: int) -> str:
    from mpib_validate.blender.scenes import BUILDER_VERSION

    blob = json.dumps({"spec": replace(spec, focus="far").to_dict(), "sharp_spp": int(sharp_spp),
                       "v": BUILDER_VERSION, "layered": LAYERED_VERSION,
                       "max_groups": MAX_GROUPS}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def folder_name(spec, sharp_spp: int) -> str:
    return f"layered-{spec.kind}-s{spec.seed}-{spec.width}x{spec.height}-{int(sharp_spp)}spp"


def _build_layered(spec, spp, depth_pass, unbiased, depth, threads):
    """The suite scene with its group layers (the artist's layer off); ``(bl, names,
    report)``. The artist's layer keeps rendering when there is one group only."""
    from mpib_validate.runtime.blender import layers
    from mpib_validate.blender.scenes import build

    bl = build(spec, spp, 0, dof=False, depth_pass=depth_pass, unbiased=unbiased,
               threads=threads)
    names, report = layers.prepare(bl, MAX_GROUPS, depth=depth)
    if names:
        layers.artist_layer(bl).use = False
    for n in names:
        bl.view_layers[n].use_pass_z = depth_pass
    return bl, names, report


def _timed_render(bl, path):
    from mpib_validate.blender import cycles

    c0 = _cpu_seconds()
    wall = cycles.render_exr(bl, path)
    return wall, _cpu_seconds() - c0


def render_layered(spec, sharp_spp: int, depth, threads: int = 0) -> dict:
    """Layered colour and depth renders of ``spec`` (see the module docstring) and the
    single-pass colour render's times around it: ``{"channels", "names", "report",
    "seconds"}``. ``depth``: the single pass's Z (refines the grouping)."""
    from mpib_validate.blender.scenes import build
    from mpib_validate.runtime.io.exr import read_exr

    with tempfile.TemporaryDirectory(prefix="mpib-layered-") as tmp:
        tmp = Path(tmp)
        times = {"single_wall": [], "single_cpu": []}
        bl, names, report = _build_layered(spec, sharp_spp, False, True, depth, threads)
        single = build(spec, sharp_spp, 0, dof=False, threads=threads)
        w, c = _timed_render(single, tmp / "single0.exr")
        times["single_wall"].append(w)
        times["single_cpu"].append(c)
        bl, names, report = _build_layered(spec, sharp_spp, False, True, depth, threads)
        times["layered_wall"], times["layered_cpu"] = _timed_render(bl, tmp / "layers.exr")
        single = build(spec, sharp_spp, 0, dof=False, threads=threads)
        w, c = _timed_render(single, tmp / "single1.exr")
        times["single_wall"].append(w)
        times["single_cpu"].append(c)
        colour = read_exr(tmp / "layers.exr")
        bl, names_z, _ = _build_layered(spec, 1, True, False, depth, threads)
        if names_z != names:
            raise RuntimeError(f"{spec.name}: the depth render's groups {names_z} differ from "
                               f"the colour render's {names}")
        times["depth_wall"], times["depth_cpu"] = _timed_render(bl, tmp / "depth.exr")
        zimg = read_exr(tmp / "depth.exr")
    channels = {}
    for n in names:
        for c in "RGBA":
            channels[f"{n}.Combined.{c}"] = colour.channels[f"{n}.Combined.{c}"]
        if f"{n}.Environment.R" in colour.channels:
            for c in "RGB":
                channels[f"{n}.Environment.{c}"] = colour.channels[f"{n}.Environment.{c}"]
        channels[f"{n}.Depth.Z"] = zimg.channels[f"{n}.Depth.Z"]
    s = times
    s["wall_ratio"] = s["layered_wall"] / float(np.mean(s["single_wall"]))
    s["cpu_ratio"] = s["layered_cpu"] / float(np.mean(s["single_cpu"]))
    return {"channels": channels, "names": names, "report": report, "seconds": s}


def render_layered_suite(out_dir, specs, sharp_spp: int, suite_folders, threads: int = 0,
                         log=print) -> dict:
    """``{spec.name: folder}`` of the layered renders (one per scene, shared by its
    foci), rendered unless cached. ``suite_folders``: each spec's folder of
    :func:`~mpib_validate.blender.scenes.render_suite`, whose sharp Z pass refines the
    grouping. A scene with one group has no ``layers.exr`` (``meta.json`` says so)."""
    from mpib_validate.blender.scenes import passes_header
    from mpib_validate.runtime.io.atomic import write_text
    from mpib_validate.runtime.io.exr import read_exr, write_exr

    out_dir = Path(out_dir)
    found = {}
    for spec, src in zip(specs, suite_folders):
        key = layered_key(spec, sharp_spp)
        folder = out_dir / folder_name(spec, sharp_spp)
        found[spec.name] = folder
        meta_path = folder / "meta.json"
        if meta_path.is_file():
            try:
                if json.loads(meta_path.read_text()).get("key") == key:
                    continue
            except ValueError:
                pass
        depth = np.asarray(read_exr(Path(src) / "passes.exr").channels["ViewLayer.Depth.Z"], np.float64)
        log(f"blender scenes: {spec.name}: layered render ({sharp_spp} spp) ...")
        res = render_layered(spec, sharp_spp, depth, threads)
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        if len(res["names"]) >= 2:
            head = passes_header(replace(spec, focus="far"))
            write_exr(folder / "layers.exr", {k: np.asarray(v, np.float32)
                                              for k, v in res["channels"].items()},
                      attributes={"mpib": json.dumps(head)})
        meta = {"key": key, "spec": replace(spec, focus="far").to_dict(),
                "sharp_spp": int(sharp_spp), "groups": res["names"], "report": res["report"],
                "seconds": res["seconds"], "layered_version": LAYERED_VERSION}
        write_text(meta_path, json.dumps(meta, indent=2, default=float) + "\n")
    return found

