"""Lens axis of the Blender scene suite: the aperture's shape (issue 29).

The suite's scenes (:mod:`mpib_validate.blender.scenes`) rendered by Cycles with three
lenses: a disk, 6 blades rotated 15 degrees, and a disk of ratio 1.5; the truth is
Cycles' depth of field with that lens (two seeds), the input its sharp passes, whose
header carries the lens (``mpib refocus`` reads it from there, as here). Per scene, focus
and lens: PSNR_ob (and PSNR) of the default preset, and of Blender's Defocus node given
its matching Bokeh Type (HEXAGON for 6 blades) at the best of four angles (the rotation,
its opposite, each plus 30 degrees: the node's angle convention is not Cycles'), which
has no ratio. Targets: the default beats the node on every scene, focus and lens, and
stays within 0.5 dB of its own disk figure.

Quick: two kinds (spheres, suzanne) at 320x240, 64 spp truths; full: every suite kind.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from mpib_validate.bench.machine import finish, machine_info

#: The lenses: name -> SceneSpec fields (blades, rotation in degrees, ratio).
LENSES = {"disk": {}, "6 blades 15 deg": {"blades": 6, "rotation_deg": 15.0},
          "ratio 1.5": {"ratio": 1.5}}
QUICK = {"width": 320, "height": 240, "spp": 64, "sharp_spp": 32,
         "kinds": ("spheres", "suzanne")}
FULL = {"width": 320, "height": 240, "spp": 256, "sharp_spp": 128, "kinds": None}
NODE_BOKEH = {0: "CIRCLE", 3: "TRIANGLE", 4: "SQUARE", 5: "PENTAGON", 6: "HEXAGON",
              7: "HEPTAGON", 8: "OCTAGON"}


def scene_row(spec, folder) -> dict:
    """The default preset and the Defocus node on one rendered scene with its lens."""
    from mpib_validate import metrics
    from mpib_validate.baselines.defocus_node import defocus
    from mpib_validate.bench.blender import boundary_mask, premultiplied
    from mpib_validate.blender.scenes import lens, load_scene
    from mpib_validate.cards.evaluate import score
    from mpib_validate.runtime.io.camera_header import resolve
    from mpib_validate.runtime.refocus import load_passes, refocus
    from mpib_validate.runtime.request import RefocusRequest

    sc = load_scene(folder)
    path = folder / "passes.exr"
    passes = load_passes(path)
    H, W = passes.depth.shape
    cam = resolve(passes.camera, {}, W, H, path).camera  # as mpib refocus reads it
    t0 = time.perf_counter()
    res = refocus(RefocusRequest(passes, cam.blur_parameter, cam.focus_disparity, "default",
                                 aperture=cam.aperture))
    seconds = time.perf_counter() - t0
    mask = boundary_mask(sc.depth, sc.meta["A"], sc.meta["d_f"])
    ours = score(sc.truth, premultiplied(res.image), mask, with_flip=False)
    ap = spec.aperture
    angles = [0.0] if ap.blades == 0 else [
        r + o for r in (ap.rotation, -ap.rotation) for o in (0.0, math.pi / 6)]
    node = []
    for a in angles:
        rgb, _ = defocus(passes.colour, passes.depth, lens(spec),
                         bokeh=NODE_BOKEH.get(ap.blades, "CIRCLE"), angle=a, timing=False)
        node.append((score(sc.truth, rgb, mask, with_flip=False), a))
    best, angle = max(node, key=lambda t: t[0]["psnr_ob"])
    a, b = (np.clip(s, 0, 1) for s in sc.seeds)
    gain = 20.0 * math.log10(2.0)
    return {"scene": f"{spec.kind}-{spec.focus}", "lens": ap.describe(),
            "aperture_read": cam.aperture.describe(),
            "default_psnr_ob": ours["psnr_ob"], "default_psnr": ours["psnr"],
            "default_seconds": seconds, "node_psnr_ob": best["psnr_ob"],
            "node_psnr": best["psnr"], "node_angle_deg": math.degrees(angle),
            "truth_floor_psnr_ob": metrics.psnr(a, b, mask) + gain}


def run(out: Path, quick: bool = True, config: dict | None = None) -> dict:
    from mpib_validate.blender.scenes import FOCI, SUITE_KINDS, SceneSpec, render_suite

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = dict(config or (QUICK if quick else FULL))
    kinds = cfg.get("kinds") or SUITE_KINDS
    specs = [SceneSpec(k, 0, cfg["width"], cfg["height"], f, **v)
             for k in kinds for f in FOCI for v in LENSES.values()]
    t0 = time.perf_counter()
    folders = render_suite(out / "blender-cache", specs, cfg["spp"], sharp_spp=cfg["sharp_spp"])
    render_seconds = time.perf_counter() - t0
    rows = []
    for spec, folder in zip(specs, folders):
        print(f"bench lens: {spec.name} ...", flush=True)
        rows.append(scene_row(spec, folder))
    result = {"suite": "lens", "quick": quick, **{k: v for k, v in cfg.items() if k != "kinds"},
              "kinds": list(kinds), "machine": machine_info(), "render_seconds": render_seconds,
              "rows": rows}
    result["summary"] = summarise(rows)
    return finish(out, "lens", result, _markdown)


def summarise(rows) -> dict:
    """Whether the targets hold: the default above the node on every row, and within
    0.5 dB of its disk figure on each scene and focus."""
    disk = {r["scene"]: r["default_psnr_ob"] for r in rows if r["lens"] == "disk"}
    beats = all(r["default_psnr_ob"] > r["node_psnr_ob"] for r in rows)
    drops = [disk[r["scene"]] - r["default_psnr_ob"] for r in rows
             if r["lens"] != "disk" and r["scene"] in disk]
    worst = max(drops) if drops else math.nan
    heads = [f"lens axis: the default preset beats the Defocus node on "
             f"{sum(r['default_psnr_ob'] > r['node_psnr_ob'] for r in rows)}/{len(rows)} rows; "
             f"largest loss against its own disk figure {worst:.2f} dB (target <= 0.5)"]
    return {"beats_node_everywhere": beats, "worst_drop_from_disk_db": worst,
            "within_half_db": bool(drops) and worst <= 0.5, "headlines": heads}


def _markdown(result) -> str:
    lines = ["# Lens axis (Blender scenes)", "",
             f"{result['width']}x{result['height']}, truth {result['spp']} spp x 2 seeds "
             f"(Cycles with the lens), sharp passes {result['sharp_spp']} spp. PSNR_ob in dB; "
             f"the Defocus node at its best angle, no ratio.", "",
             "| scene | lens | default | Defocus node (angle) | truth noise floor |",
             "|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['scene']} | {r['lens']} | {r['default_psnr_ob']:.2f} | "
                     f"{r['node_psnr_ob']:.2f} ({r['node_angle_deg']:.0f} deg) | "
                     f"{r['truth_floor_psnr_ob']:.2f} |")
    lines += ["", *result["summary"]["headlines"], ""]
    return "\n".join(lines)
