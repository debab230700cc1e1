"""PSNR_ob of the MPIB Refocus node group against Blender's Defocus node and the numpy
refocus (preset "default"), on small Cycles scenes (tests/blender/nodegroup_session.py).

For each scene and focus: Cycles renders sharp passes (depth of field off) and the
truth (Cycles' own depth of field, ``--dof-spp`` samples); the node group (added by
the extension's operator, rendered in the compositor), the Defocus node and the numpy
refocus all start from the same sharp passes. Scores: PSNR and PSNR_ob (the
occlusion-boundary mask of the supplement, from the Z pass) on values clipped to [0, 1].

    python scripts/measure_nodegroup.py --out out/nodegroup [--size 128 96] [--dof-spp 1024]

Writes ``results.json`` and ``table.md`` under ``--out``; no timings (the machine is
shared). ``--bpy-python`` runs the sessions with another Blender's Python (e.g. 4.2).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: (scene, focus distance m, f-stop): the foreground in focus, the background in focus.
CASES = (("cards", 6.0, 1.0), ("cards", 1.5, 1.0), ("sphere", 7.0, 1.0), ("sphere", 2.5, 1.0),
         ("tilted", 9.0, 1.4), ("tilted", 1.8, 1.4))


def session(python, args: dict, env=None) -> dict:
    env = dict(os.environ if env is None else env)
    if python != sys.executable and subprocess.run([python, "-c", "import OpenEXR, scipy"],
                                                   capture_output=True).returncode != 0:
        import site  # another bpy of the same Python version: lend it this venv's packages

        env["MPIB_EXTRA_SITE"] = site.getsitepackages()[0]
    r = subprocess.run([python, str(ROOT / "tests" / "blender" / "nodegroup_session.py"), "render",
                        json.dumps(args)], capture_output=True, text=True, timeout=1800, env=env)
    lines = [l for l in r.stdout.splitlines() if l.startswith("RESULT ")]
    if r.returncode != 0 or not lines:
        raise RuntimeError(r.stdout[-3000:] + r.stderr[-3000:])
    return json.loads(lines[-1][7:])


def score_case(res: dict, fstop: float, focus: float) -> dict:
    from mpib_validate.runtime.camera import blender_camera
    from mpib_validate.baselines.defocus_node import defocus
    from mpib_validate.runtime.io.exr import find_pass, read_exr, rgba_from
    from mpib_validate.metrics import boundaries_from_disparity, occlusion_mask, psnr
    from mpib_validate.runtime.refocus import Passes, refocus
    from mpib_validate.runtime.request import RefocusRequest

    f = res["frames"]["1"]
    img = read_exr(f["path"])
    layer = next(p for p in {n.split(".")[0] for n in img.channels} if p != "Composite")
    sharp = rgba_from(img, f"{layer}.Combined.")[..., :3]
    node = rgba_from(img, "Composite.Combined.")[..., :3]
    depth = img.channels[find_pass(img, "Depth")].astype(np.float64)
    truth = rgba_from(read_exr(res["dof"]), f"{layer}.Combined.")[..., :3]
    H, W = depth.shape
    cam = blender_camera(100.0, 36.0, 24.0, "HORIZONTAL", W, H, fstop, focus)
    A, d_f = cam.blur_parameter, cam.focus_disparity
    lens = {"lens_mm": 100.0, "sensor_width_mm": 36.0, "fstop": fstop, "focus_distance": focus}
    defocused, _ = defocus(sharp, depth.astype(np.float32), lens, timing=False)
    passes = Passes(sharp, depth, "sharp", "depth")
    numpy_default = refocus(RefocusRequest(passes, A, d_f, "default")).image[..., :3]
    D = np.where(depth < 1e9, 1.0 / depth, 0.0)
    mask = occlusion_mask(boundaries_from_disparity(D, 1.0 / A), D, A, d_f)
    ref = np.clip(truth, 0, 1)
    out = {"blur_parameter": A, "largest_radius_px": float(A * np.abs(D - d_f).max()),
           "mask_fraction": float(mask.mean()), "slices": len(res["spec"]["disparities"]),
           "node_message": res["message"]}
    for name, test in (("node_group", node), ("defocus_node", defocused),
                       ("numpy_default", numpy_default), ("sharp", sharp)):
        t = np.clip(test, 0, 1)
        out[name] = {"psnr": psnr(ref, t), "psnr_ob": psnr(ref, t, mask)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/nodegroup")
    ap.add_argument("--size", type=int, nargs=2, default=(128, 96))
    ap.add_argument("--spp", type=int, default=64, help="samples of the sharp passes")
    ap.add_argument("--dof-spp", type=int, default=1024, help="samples of the DOF truth")
    ap.add_argument("--max-slices", type=int, default=8)
    ap.add_argument("--fill", default="INPAINT", choices=("INPAINT", "OFF"))
    ap.add_argument("--blur", default="AUTO", choices=("AUTO", "CONVOLVE", "BOKEH"))
    ap.add_argument("--bpy-python", default=sys.executable)
    ap.add_argument("--cases", default="all", help="comma-separated indices into CASES")
    a = ap.parse_args(argv)
    out_dir = Path(a.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    cases = CASES if a.cases == "all" else [CASES[int(i)] for i in a.cases.split(",")]
    rows = []
    for scene, focus, fstop in cases:
        work = out_dir / f"{scene}_{focus:g}"
        work.mkdir(exist_ok=True)
        res = session(a.bpy_python, {"out_dir": str(work), "scene": scene, "size": list(a.size),
                                     "spp": a.spp, "root": str(ROOT), "focus": focus,
                                     "fstop": fstop, "dof_spp": a.dof_spp,
                                     "max_slices": a.max_slices, "fill": a.fill, "blur": a.blur})
        r = score_case(res, fstop, focus)
        r.update(scene=scene, focus=focus, fstop=fstop, blender=res["version"])
        rows.append(r)
        print(json.dumps({k: r[k] for k in ("scene", "focus", "node_group", "defocus_node",
                                             "numpy_default")}), flush=True)
    (out_dir / "results.json").write_text(json.dumps(rows, indent=1, default=float))
    lines = ["| scene | focus (m) | largest blur (px) | slices | PSNR_ob node group | "
             "Defocus node | numpy default | sharp | node - Defocus | numpy - node |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n, dn, nd, s = (r[k]["psnr_ob"] for k in ("node_group", "defocus_node", "numpy_default",
                                                   "sharp"))
        lines.append(f"| {r['scene']} | {r['focus']:g} | {r['largest_radius_px']:.1f} | "
                     f"{r['slices']} | {n:.2f} | {dn:.2f} | {nd:.2f} | {s:.2f} | {n - dn:+.2f} | "
                     f"{nd - n:+.2f} |")
    (out_dir / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    raise SystemExit(main())
