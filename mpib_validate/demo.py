"""The README's main job: generate the embedded default scenes, render them, report.

For now the job covers the foundation: one scene per family (seed 0), the Eq. 15 ray
tracer's EXR (all passes) and PNG preview, and ``report.md`` with what ran and how long
it took. Later stages (compositor, Mitsuba, Cycles) add their rows to the same report.
"""

from __future__ import annotations

import json
import platform
from pathlib import Path

from . import __version__, samples
from .atomic import write_text
from .generate import FAMILIES, GeneratorSettings, generate
from .render_io import write_render
from .scene import save_scene
from .trace import render

DEFAULT_SEED = 0


def run_demo(out: Path, size: int = 256, spp: int = 1024, backend: str = "auto") -> dict:
    out = Path(out)
    rows = []
    for family in FAMILIES:
        scene = generate(DEFAULT_SEED, family, settings=GeneratorSettings(width=size, height=size))
        scene_dir = out / f"scene-{family}"
        save_scene(scene, scene_dir)
        result = render(scene, samples.stratified(spp), backend=backend, progress=True)
        files = write_render(out / f"trace-{family}.exr", result, scene)
        cam = scene.camera
        rows.append({
            "family": family, "scene": str(scene_dir), "files": [str(f) for f in files],
            "cards": len(scene.cards), "size": f"{cam.width}x{cam.height}",
            "blur_parameter": cam.blur_parameter, "focus_disparity": cam.focus_disparity,
            "max_blur_radius_px": scene.max_blur_radius(), **result.meta,
        })
        print(f"{family}: {len(scene.cards)} cards, largest blur {scene.max_blur_radius():.1f} px, "
              f"traced {result.meta['sample_count']} spp on {result.meta['backend']} "
              f"in {result.meta['seconds']:.2f} s -> {files[0]}")
    summary = {"version": __version__, "python": platform.python_version(),
               "machine": platform.machine(), "runs": rows}
    write_text(out / "demo.json", json.dumps(summary, indent=2) + "\n")
    lines = ["# mpib demo", "",
             f"mpib {__version__}, Python {platform.python_version()}, {platform.machine()}.", "",
             "| family | cards | size | A (px) | d_f | largest radius (px) | samples | backend | time (s) | preview |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        png = Path(r["files"][-1]).name
        lines.append(f"| {r['family']} | {r['cards']} | {r['size']} | {r['blur_parameter']:.2f} | "
                     f"{r['focus_disparity']:.4f} | {r['max_blur_radius_px']:.1f} | {r['sample_count']} | "
                     f"{r['backend']} | {r['seconds']:.2f} | ![{r['family']}]({png}) |")
    if any(r["backend_notice"] for r in rows):
        lines += ["", f"Backend notice: {rows[0]['backend_notice']}"]
    write_text(out / "report.md", "\n".join(lines) + "\n")
    print(f"wrote {out / 'report.md'}")
    return summary
