"""Runs as a script inside a fresh Python with the bpy module (started by
:mod:`mpib_validate.bench.addon`); imports nothing of the project before the extension
is installed, so the code timed is the zip's own bundled copy.

Usage: python addon_session.py CONFIG_JSON; prints one JSON line.
"""

import json
import os
import sys
import tempfile
import time

import bpy

cfg = json.loads(sys.argv[1])
prefs = bpy.context.preferences
repo_dir = tempfile.mkdtemp(dir=cfg["work"])
prefs.extensions.repos.new(name="mpib_bench", module="mpib_bench", custom_directory=repo_dir,
                           source="USER")
bpy.ops.extensions.package_install_files(filepath=cfg["zip"], repo="mpib_bench",
                                         enable_on_install=True)

sc = bpy.context.scene
sc.render.resolution_x, sc.render.resolution_y = cfg["width"], cfg["height"]
sc.render.resolution_percentage = 100
sc.render.filepath = os.path.join(cfg["work"], "out") + os.sep
cam_data = bpy.data.cameras.new("bench")
cam_data.lens, cam_data.sensor_width, cam_data.sensor_fit = cfg["lens_mm"], cfg["sensor_mm"], "HORIZONTAL"
cam_data.dof.use_dof = True
cam_data.dof.aperture_fstop = cfg["fstop"]
cam_data.dof.focus_distance = cfg["focus_distance"]
cam = bpy.data.objects.new("bench", cam_data)
sc.collection.objects.link(cam)
sc.camera = cam
sc.mpib.save_exr = True

rows = {}
for preset in cfg["presets"]:
    sc.mpib.preset = preset
    times = []
    for _ in range(cfg["repeats"]):
        t0 = time.perf_counter()
        result = bpy.ops.mpib.refocus_file(filepath=cfg["input"])
        times.append(time.perf_counter() - t0)
    rows[preset] = {"seconds": times, "result": sorted(result), "message": sc.mpib.last_message}
print(json.dumps({"blender": bpy.app.version_string, "rows": rows}))
