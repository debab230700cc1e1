"""Benchmark of the Blender extension: its Refocus EXR File operator on a 1920x1080
multilayer EXR (colour + depth) inside Blender (the bpy module), per quality preset,
with the EXR read and the refocused EXR written (the round trip an artist runs).

The zip of this machine's platform is built by ``scripts/build_addon.py`` and installed into a throw-away
extension repository of a fresh bpy process; the operator is the blocking path that a
script or background mode takes (the interactive one runs the same work on a thread).
The camera is set so that the calibration gives the same blur parameter and focus as
the ``refocus`` suite's 1080p timing, which this one can be read beside.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from mpib_validate.bench.machine import finish, machine_info

ROOT = Path(__file__).resolve().parents[2]


def _camera_for(A: float, d_f: float, width: int, lens_mm=50.0, sensor_mm=36.0) -> dict:
    """Blender lens settings whose thin lens gives ``A = R f_px`` and ``d_f``:
    ``f_px = lens / sensor * W`` and ``R = lens / (2 N)``, so ``N = lens f_px / (2 A)``
    (lens in scene units, metres)."""
    f_px = lens_mm / sensor_mm * width
    return {"lens_mm": lens_mm, "sensor_mm": sensor_mm,
            "fstop": lens_mm * 1e-3 * f_px / (2.0 * A), "focus_distance": 1.0 / d_f}


def run(out: Path, quick: bool = True) -> dict:
    from mpib_validate.runtime.presets import PRESETS
    from mpib_validate.bench.refocus import _hd_input

    out.mkdir(parents=True, exist_ok=True)
    result = {"suite": "addon", "quick": quick, "machine": machine_info()}
    build = ROOT / "scripts" / "build_addon.py"
    if importlib.util.find_spec("bpy") is None or not build.exists():
        result["skipped"] = "needs the bpy module and the repository's scripts/build_addon.py"
        return finish(out, "addon", result, _markdown)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print("bench addon: building the extension zip ...", flush=True)
        r = subprocess.run([sys.executable, str(build), "--out", str(tmp / "dist")],
                           capture_output=True, text=True)
        sys.path.insert(0, str(build.parent))
        import check_addon  # scripts/: this machine's platform, as in the zip names

        zips = sorted((tmp / "dist").glob(f"*-{check_addon.host_platform()}.zip"))
        if r.returncode != 0 or not zips:
            result["error"] = (r.stderr or r.stdout).strip().splitlines()[-1:]
            return finish(out, "addon", result, _markdown)
        cam = _hd_input(tmp / "hd.exr")
        cfg = {"zip": str(zips[0]), "work": str(tmp), "input": str(tmp / "hd.exr"),
               "width": 1920, "height": 1080, "presets": list(PRESETS),
               "repeats": 2, **_camera_for(cam["A"], cam["d_f"], 1920)}
        print("bench addon: the operator at 1920x1080 in Blender ...", flush=True)
        env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"))
        r = subprocess.run([sys.executable, str(Path(__file__).with_name("addon_session.py")),
                            json.dumps(cfg)], capture_output=True, text=True, env=env, cwd=tmp)
        lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
        if r.returncode != 0 or not lines:
            result["error"] = (r.stderr or r.stdout).strip().splitlines()[-1:]
        else:
            result.update(json.loads(lines[-1]))
            result["blur_parameter"], result["focus_disparity"] = cam["A"], cam["d_f"]
    heads = []
    for preset, row in result.get("rows", {}).items():
        t = row["seconds"]
        heads.append(f"Blender operator, preset {preset}, 1920x1080 with EXR in and out: "
                     f"{t[0]:.2f} s the first time, {min(t[1:] or t):.2f} s after.")
    result["summary"] = {"headlines": heads}
    return finish(out, "addon", result, _markdown)


def _markdown(result) -> str:
    lines = ["# The Blender extension at 1920x1080", ""]
    if "skipped" in result or "error" in result:
        return "\n".join(lines + [f"Not run: {result.get('skipped') or result.get('error')}", ""])
    m = result["machine"]
    lines += [f"Blender {result['blender']} (bpy module), {m.get('processor')}, "
              f"{m.get('affinity_cores', m.get('cpu_count'))} cores. The Refocus EXR File "
              f"operator with Save EXR on, on the `refocus` suite's 1080p input "
              f"(A = {result['blur_parameter']:.1f} px, d_f = {result['focus_disparity']:.3f}).",
              "", "| preset | first call (s) | repeat (s) | status |", "|---|---|---|---|"]
    for preset, row in result["rows"].items():
        t = row["seconds"]
        lines.append(f"| {preset} | {t[0]:.2f} | {min(t[1:] or t):.2f} | {row['message'].split(', saved')[0]} |")
    return "\n".join(lines) + "\n"
