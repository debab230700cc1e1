"""Compositing time of the MPIB Refocus node group against Blender's Defocus node at
1920x1080, on the same passes, as a ratio measured in one process (A, B, A, B
interleaved: a ratio stays valid on a loaded machine, a time does not).

Passes: a scene of the Blender suite (its cached Cycles render, ``passes.exr``) scaled
up to 1920x1440 (nearest) and cut to 1920x1080; the f-stop is raised so that the
largest blur radius is ``--max-radius`` px. Each round renders: the tree without either
node (loading the EXR and writing the output: the baseline), the Defocus node
(``blur_max`` from its own radius), and the node group as the extension builds it (slices
from the depth, Inpaint fill, Convolve or Bokeh Blur). A method's time is its render op
minus the baseline; the report gives the median of the rounds and the ratio.

    python scripts/time_nodegroup.py --max-radius 8 --rounds 2 \\
        --scene out/bench-blender/blender-cache/spheres-s0-far-320x240-64spp
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True, help="a Blender suite cache folder")
    ap.add_argument("--max-radius", type=float, default=24.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--blur", default="convolve", choices=("convolve", "bokeh"))
    ap.add_argument("--max-slices", type=int, default=None, help="default: the operator's")
    ap.add_argument("--slab-px", type=float, default=None)
    ap.add_argument("--out", default=None, help="write the result as JSON here")
    a = ap.parse_args(argv)
    if not (Path(a.scene) / "passes.exr").is_file():
        print(f"time_nodegroup: --scene {a.scene}: no passes.exr there (a Blender suite "
              f"cache folder is needed)", file=sys.stderr)
        return 2
    if a.max_radius <= 0 or a.rounds < 1:
        print("time_nodegroup: --max-radius must be > 0 and --rounds >= 1", file=sys.stderr)
        return 2

    from mpib_validate.blender.nodegroup_run import run_on_passes
    from mpib_validate.runtime.blender import nodegroup as ng
    from mpib_validate.blender.scenes import lens, load_scene
    from mpib_validate.baselines.defocus_node import defocus
    from mpib_validate.runtime.layers.passes import depth_to_disparity
    from mpib_validate.runtime.refocus import load_passes

    sc = load_scene(Path(a.scene))
    passes = load_passes(sc.folder / "passes.exr")
    W, H = 1920, 1080
    k = -(-W // passes.depth.shape[1])
    colour = np.repeat(np.repeat(passes.colour, k, 0), k, 1)
    depth = np.repeat(np.repeat(passes.depth, k, 0), k, 1)
    y0 = (colour.shape[0] - H) // 2
    colour = np.ascontiguousarray(colour[y0:y0 + H, :W], np.float32)
    depth = np.ascontiguousarray(depth[y0:y0 + H, :W], np.float32)
    c = lens(sc.spec)
    D = depth_to_disparity(depth)
    f_px = c["lens_mm"] / c["sensor_width_mm"] * W
    spread = float(np.abs(D - c["focus_disparity"]).max())
    # A = f_mm 1e-3 / (2 N) * f_px: choose N for the largest radius A * spread
    fstop = c["lens_mm"] * 1e-3 * f_px * spread / (2.0 * a.max_radius)
    A = c["lens_mm"] * 1e-3 / (2.0 * fstop) * f_px
    cam = {"lens_mm": c["lens_mm"], "sensor_width_mm": c["sensor_width_mm"], "fstop": fstop,
           "focus_distance": c["focus_distance"]}
    spec = ng.spec_from_render(depth, A, blur=a.blur,
                               max_slices=a.max_slices or ng.DEFAULT_MAX_SLICES,
                               slab_px=ng.SLAB_PX if a.slab_px is None else a.slab_px,
                               focus_disparity=c["focus_disparity"])
    graph = ng.describe(spec)
    image = np.concatenate([colour, np.ones((H, W, 1), np.float32)], -1)
    values = {"Focus Distance": c["focus_distance"], "F-Stop": fstop,
              "Focal Length": c["lens_mm"], "Sensor Width": c["sensor_width_mm"],
              "Resolution X": float(W), "Resolution Y": float(H)}
    # the baseline: an empty group (its output is its image input) on the same passes
    empty = ng.Graph(spec, (), (("Image", ng.GroupIn("Image")), ("Alpha", ng.GroupIn("Depth"))))
    rows = {"baseline": [], "defocus": [], "group": []}
    for r in range(a.rounds):
        for name in ("baseline", "defocus", "group"):
            t0 = time.perf_counter()
            if name == "defocus":
                info = {}
                defocus(colour, depth, cam, timing=False, info=info)
                t = info["total_seconds"]
            else:
                t = run_on_passes(image, depth, graph if name == "group" else empty,
                                     values)["seconds"]
            rows[name].append(t)
            print(f"round {r}: {name} {t:.2f} s (call {time.perf_counter() - t0:.1f} s)",
                  flush=True)
    med = {k: statistics.median(v) for k, v in rows.items()}
    own = {k: med[k] - med["baseline"] for k in ("defocus", "group")}
    out = {"scene": sc.spec.name, "width": W, "height": H, "max_radius_px": a.max_radius,
           "blur": a.blur, "slices": len(spec.disparities), "slabs": len(set(spec.slabs)),
           "nodes": len(graph.ops), "seconds": rows, "median": med, "own_seconds": own,
           "ratio_group_to_defocus": own["group"] / own["defocus"],
           "ratio_total": med["group"] / med["defocus"]}
    print(json.dumps({k: out[k] for k in ("slices", "slabs", "nodes", "median",
                                           "ratio_group_to_defocus", "ratio_total")}))
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
