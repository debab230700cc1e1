"""How Eq. 1 with the fast paths scales: with resolution, largest blur radius, plane count.

One generated 'varying' scene (seed 0) cut into 32 uniform planes; each measurement is
the median of three runs after a warm-up. Resolution: 256 to 1024 on a side (2048 in
full mode) at a largest radius of 10 % of the width. Radius and plane count at 512x512.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from mpib_validate.runtime.io.atomic import write_text
from mpib_validate.bench.machine import machine_info


def _time(fn, repeats=3):
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _scene(size: int, radius: float):
    from mpib_validate.cards.generate import GeneratorSettings, generate

    scene = generate(0, "varying", settings=GeneratorSettings(width=size, height=size))
    lo, hi = scene.disparity_range()
    df = scene.camera.focus_disparity
    return scene.with_camera(blur_parameter=radius / max(abs(hi - df), abs(lo - df)))


def run(out: Path, quick: bool = True) -> dict:
    from mpib_validate.runtime.compositor import composite as C
    from mpib_validate.runtime.layers import mpi as M
    from mpib_validate.cards import mpi as CM

    out.mkdir(parents=True, exist_ok=True)
    rows = []

    def measure(axis, value, size, radius, planes):
        scene = _scene(size, radius)
        cam = scene.camera
        mpi = CM.layers_from_cards(scene, planes=M.uniform_planes(planes, max(1.0, scene.disparity_range()[1])))
        t = _time(lambda: C.composite(mpi, cam.blur_parameter, cam.focus_disparity))
        rows.append({"axis": axis, "value": value, "size": size, "radius": radius,
                     "planes": planes, "nonempty_planes": len(mpi.layers), "seconds": t})
        print(f"bench scaling: {axis}={value}: {t:.3f} s", flush=True)

    for size in ((256, 512, 1024) if quick else (256, 512, 1024, 2048)):
        measure("resolution", size, size, 0.1 * size, 32)
    for radius in (4, 8, 16, 32, 64):
        measure("radius", radius, 512, radius, 32)
    for planes in (8, 16, 32, 64, 128):
        measure("planes", planes, 512, 32, planes)
    result = {"suite": "scaling", "quick": quick, "machine": machine_info(), "rows": rows}
    write_text(out / "scaling.json", json.dumps(result, indent=2) + "\n")
    try:
        plot(rows, out / "scaling.png")
    except ImportError:
        pass
    lines = ["# Scaling of Eq. 1 (fast paths)", "", "![scaling](scaling.png)", "",
             "| axis | value | size | radius (px) | planes | non-empty | time (s) |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['axis']} | {r['value']} | {r['size']} | {r['radius']:.0f} | {r['planes']} | "
              f"{r['nonempty_planes']} | {r['seconds']:.3f} |" for r in rows]
    write_text(out / "scaling.md", "\n".join(lines) + "\n")
    return result


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mpib_validate.runtime.io.atomic import atomic_path

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for ax, axis, label in zip(axes, ("resolution", "radius", "planes"),
                               ("image side (px), radius 10 % of it", "largest radius (px), 512x512",
                                "uniform planes, 512x512")):
        rs = [r for r in rows if r["axis"] == axis]
        ax.plot([r["value"] for r in rs], [r["seconds"] for r in rs], "o-")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("time (s)")
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
