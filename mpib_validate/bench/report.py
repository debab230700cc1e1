"""The benchmark's front page: Pareto plots, an image grid of boundary crops, headlines.

Everything on the page is computed from the suites' results; nothing is typed in.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mpib_validate.runtime.io.atomic import atomic_path, write_text
from mpib_validate.bench.machine import machine_info

#: Methods drawn in the Pareto plots, with a legend group each.
GROUPS = (
    ("Eq. 1, exact layers", ("eq1-",)),
    ("middle setting", ("middle-",)),
    ("exact MPI renderer", ("exact-",)),
    ("fast paths", ("path-",)),
    ("from colour + depth (MPI)", ("mpi-", "preset-")),
    ("classical baselines", ("rvr", "sterefo", "scatter", "gather")),
    ("Blender Defocus node", ("blender-defocus",)),
    ("ray tracer", ("trace-",)),
    ("Mitsuba 3", ("mitsuba-",)),
    ("Cycles", ("cycles-",)),
)


def _group(method: str) -> str | None:
    for name, prefixes in GROUPS:
        if method.startswith(prefixes):
            return name
    return None


def _mean_rows(rows, family):
    out = {}
    for r in rows:
        if r.get("family") != family or not (r.get("seconds", math.nan) > 0):
            continue  # no time (the input itself, a noise floor): no place on a time axis
        out.setdefault(r["method"], []).append(r)
    return {m: {k: float(np.mean([r[k] for r in rs])) for k in ("seconds", "psnr", "psnr_ob")}
            for m, rs in out.items()}


def label_points(ax, points, fontsize: float = 7.0) -> list[tuple[int, str]]:
    """Number the points ``[(x, y, label), ...]`` of ``ax`` and list the numbers beside
    the axes, so that labels never overlap however close the points are.

    Each number goes to the first of 8 positions around its point (just clear of its
    marker, then 8 and 16 points further out with a leader line) whose box overlaps no
    marker and no number placed before, in display coordinates; the key ``n  label``
    is a text column right of the axes. Call after the points are drawn and the axis
    scales are set. Returns the ``(number, label)`` pairs."""
    fig = ax.figure
    ax.autoscale_view()
    fig.canvas.draw()  # fixes the limits and transforms
    to_px = fig.dpi / 72.0
    xy = ax.transData.transform([(x, y) for x, y, _ in points]) if points else np.zeros((0, 2))
    marker = 3.5 * to_px
    taken = [(px - marker, py - marker, px + marker, py + marker) for px, py in xy]
    dirs = [(1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1)]
    order = sorted(range(len(points)), key=lambda i: (xy[i][0], xy[i][1]))
    key = []
    for n, i in enumerate(order, 1):
        px, py = xy[i]
        w, h = (0.62 * len(str(n)) + 0.4) * fontsize * to_px, 1.1 * fontsize * to_px
        best = None
        for extra in (0.0, 8.0, 16.0):
            for dx, dy in dirs:
                cx = px + dx * (marker + w / 2 + (1.0 + extra) * to_px)
                cy = py + dy * (marker + h / 2 + (1.0 + extra) * to_px)
                box = (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)
                if not any(box[0] < t[2] and t[0] < box[2] and box[1] < t[3] and t[1] < box[3]
                           for t in taken):
                    best = (cx, cy, box, extra)
                    break
            if best:
                break
        if best is None:  # everything taken: the outer ring, up and right
            cx, cy = px + marker + w / 2 + 17 * to_px, py + marker + h / 2 + 17 * to_px
            best = (cx, cy, (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), 16.0)
        cx, cy, box, extra = best
        taken.append(box)
        tx, ty = ax.transData.inverted().transform((cx, cy))
        arrow = {"arrowstyle": "-", "lw": 0.5, "color": "0.5"} if extra > 0 else None
        ax.annotate(str(n), (points[i][0], points[i][1]), xytext=(tx, ty), textcoords="data",
                    fontsize=fontsize, ha="center", va="center", arrowprops=arrow)
        key.append((n, points[i][2]))
    ax.text(1.02, 1.0, "\n".join(f"{n:>2}  {label}" for n, label in key), transform=ax.transAxes,
            va="top", ha="left", fontsize=fontsize, family="monospace")
    return key


def pareto_plot(rows, family: str, path: Path, metric: str = "psnr",
                reference: str = "the ray tracer", title: str | None = None) -> None:
    """Error against time, one point per method (mean over the family's scenes), each
    numbered (:func:`label_points`), coloured by its legend group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    means = _mean_rows(rows, family)
    fig, ax = plt.subplots(figsize=(10.5, 5.5))
    fig.subplots_adjust(left=0.08, right=0.69, top=0.93, bottom=0.1)
    points = []
    for name, _ in GROUPS:
        pts = [(m, v) for m, v in means.items() if _group(m) == name]
        if not pts:
            continue
        ax.scatter([v["seconds"] for _, v in pts], [min(v[metric], 80) for _, v in pts],
                   label=name, s=28)
        points += [(v["seconds"], min(v[metric], 80), m) for m, v in pts]
    ax.set_xscale("log")
    ax.set_xlabel("time (s, log scale)")
    ax.set_ylabel(f"{metric.upper().replace('_OB', '_ob')} against {reference} (dB)")
    ax.set_title(title or f"Error against time, {family} disparity")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    label_points(ax, points)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def crop_grid(path: Path, size: int = 192, crop: int = 48) -> list[str]:
    """For one scene per family: crops around the occlusion boundary where Eq. 1 on
    colour + depth errs most, each method beside the reference. Returns the methods."""
    from PIL import Image

    from mpib_validate.baselines import classical as baselines
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.runtime.compositor.composite import composite
    from mpib_validate.cards.evaluate import card_scene_mask
    from mpib_validate.cards.generate import FAMILIES, GeneratorSettings, generate
    from mpib_validate.cards.mpi import layers_from_cards
    from mpib_validate.runtime.layers.passes import PassesSettings, depth_to_disparity, layers_from_passes
    from mpib_validate.runtime.io.preview import to_uint8

    rows, names = [], None
    for family in FAMILIES:
        scene = generate(0, family, settings=GeneratorSettings(width=size, height=size))
        cam = scene.camera
        A, df = cam.blur_parameter, cam.focus_disparity
        res = trace.render(scene, samples.stratified(1024), notices=False)
        D = depth_to_disparity(res.depth)
        aif = res.all_in_focus[..., :3]
        imgs = {"reference (ray tracer)": res.bokeh[..., :3],
                "MPI exact layers": composite(layers_from_cards(scene), A, df)[..., :3],
                "MPI colour+depth+fill": composite(layers_from_passes(aif, D, A)[0], A, df)[..., :3],
                "MPI no fill": composite(layers_from_passes(aif, D, A, PassesSettings(fill=False))[0], A, df)[..., :3],
                "scatter": baselines.scatter(aif, D, A, df),
                "all in focus (input)": aif}
        try:
            from mpib_validate.baselines.defocus_node import defocus

            imgs["Blender Defocus node"] = defocus(aif, res.depth, cam.cycles_settings(), timing=False)[0]
        except ImportError:
            pass
        names = list(imgs)
        err = np.abs(imgs["MPI colour+depth+fill"] - imgs["reference (ray tracer)"]).sum(-1)
        err[~card_scene_mask(scene)] = 0
        h = crop // 2
        err[:h], err[-h:], err[:, :h], err[:, -h:] = 0, 0, 0, 0
        y, x = np.unravel_index(int(err.argmax()), err.shape)
        tiles = [to_uint8(im[y - h:y + h, x - h:x + h]) for im in imgs.values()]
        rows.append(np.concatenate([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=255)
                                    for t in tiles], axis=1))
    grid = np.concatenate(rows, axis=0)
    big = Image.fromarray(grid).resize((grid.shape[1] * 3, grid.shape[0] * 3), Image.NEAREST)
    with atomic_path(path) as tmp:
        big.save(tmp, format="PNG")
    return names


def photo_figure(path: Path) -> dict:
    """A real photograph with real disparity, refocused for the eye (no reference exists):
    scikit-image's Middlebury ``stereo_motorcycle`` left view and its disparity.

    The photo is linearised with the sRGB curve; unknown disparities (inf) take their
    nearest known value; disparity is normalised to [0, 1] (the paper's convention) and
    ``A`` set so that the largest blur is 2 % of the width. Rows: focus on the near
    (90th percentile) and the far (10th percentile) disparity; columns: the input, the
    MPI from colour + depth (default preset), scatter. Returns the settings and times.
    """
    import time

    from PIL import Image

    from mpib_validate.bench.photos import load_motorcycle
    from mpib_validate.baselines import classical as baselines
    from mpib_validate.runtime.compositor.composite import composite
    from mpib_validate.runtime.layers.passes import layers_from_passes
    from mpib_validate.runtime.io.preview import to_uint8

    rgb, D = load_motorcycle()
    A = 0.02 * rgb.shape[1]
    rows, info = [], {"width": int(rgb.shape[1]), "height": int(rgb.shape[0]), "A": A}
    t0 = time.perf_counter()
    mpi, pinfo = layers_from_passes(rgb, D, A)
    info["layers_seconds"] = time.perf_counter() - t0
    info["planes"] = pinfo.planes
    for name, d_f in (("near", float(np.quantile(D, 0.9))), ("far", float(np.quantile(D, 0.1)))):
        t0 = time.perf_counter()
        out = composite(mpi, A, d_f)[..., :3]
        info[f"{name}_seconds"] = time.perf_counter() - t0
        sc = baselines.scatter(rgb, D, A, d_f)
        rows.append(np.concatenate([to_uint8(rgb), to_uint8(out), to_uint8(sc)], axis=1))
    grid = np.concatenate(rows, axis=0)
    img = Image.fromarray(grid)
    img = img.resize((img.width // 2, img.height // 2), Image.LANCZOS)
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG")
    return info


def write_index(out: Path, results: dict) -> Path:
    """``index.md``: machine and versions, headline sentences, plots, links to each suite."""
    lines = ["# mpib benchmark", ""]
    m = machine_info()
    lines += [f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} cores, "
              f"{m.get('platform')}; Python {m['python']}; "
              + ", ".join(f"{k} {m[k]}" for k in ("numpy", "drjit", "OpenEXR", "scipy",
                                                  "scikit-image", "mitsuba", "bpy") if k in m) + ".",
              ""]
    lines += ["## Headlines", ""]
    # the speed story leads with the official renderer's own computation, timed beside
    # Eq. 1 in one process (suite `official`), when it ran
    order = sorted(results, key=lambda name: name != "official")
    for name in order:
        res = results[name]
        for h in res.get("summary", {}).get("headlines", []):
            lines.append(f"- {h}")
    lines.append("")
    rows = []
    for key in ("compositor", "refocus"):
        rows += results.get(key, {}).get("rows", [])
    if rows:
        try:
            for family in ("constant", "varying"):
                for metric in ("psnr", "psnr_ob"):
                    p = out / f"pareto-{family}-{metric}.png"
                    pareto_plot(rows, family, p, metric)
            lines += ["## Error against time", "",
                      "Each point is one method, averaged over the suite's scenes; higher is better, "
                      "further left is faster. The methods from colour + depth start from the "
                      "ray tracer's all-in-focus image and depth pass.", ""]
            for family in ("constant", "varying"):
                lines += [f"![{family}](pareto-{family}-psnr.png)",
                          f"![{family} ob](pareto-{family}-psnr_ob.png)", ""]
        except ImportError:
            lines += ["(matplotlib is not installed: no plots)", ""]
    try:
        names = crop_grid(out / "crops.png")
        lines += ["## At occlusion boundaries", "",
                  "Crops (48x48, x3) where the colour + depth MPI errs most inside the "
                  "occlusion-boundary mask; rows: constant, varying; columns: "
                  + "; ".join(names) + ".", "", "![crops](crops.png)", ""]
    except ImportError:
        pass
    try:
        ph = photo_figure(out / "photo.png")
        lines += ["## A real photograph (not scored)", "",
                  f"Middlebury motorcycle (scikit-image), {ph['width']}x{ph['height']}, with its "
                  f"stereo disparity; A = {ph['A']:.1f} px; {ph['planes']} planes built in "
                  f"{ph['layers_seconds']:.2f} s, each refocus {ph['near_seconds']:.2f} s. Rows: "
                  "focus near, focus far. Columns: input, MPI from colour + depth, scatter.", "",
                  "![photo](photo.png)", ""]
    except ImportError:
        pass
    if "blender" in results:
        b = results["blender"]
        lines += ["## Ordinary 3D Blender scenes", "",
                  "Against Cycles' own depth of field; inputs are Cycles' sharp Combined and Z "
                  "passes (see [blender.md](blender.md)).", ""]
        lines += [f"![blender]({p})" for p in b.get("plots", [])]
        if b.get("crops"):
            lines.append(f"![blender crops]({b['crops']})")
        lines.append("")
    if "photos" in results and results["photos"].get("figure"):
        lines += ["## Photographs and predicted disparity", "",
                  "The Middlebury motorcycle refocused from its exact stereo disparity, from "
                  "that disparity degraded as a monocular estimator errs, and with the guided "
                  "refinement; boundary crops below (see [photos.md](photos.md)).", "",
                  f"![photos]({results['photos']['figure']['path']})", ""]
    if "official" in results:
        o = results["official"]
        lines += ["## Against the official MPIB renderer", ""]
        if o.get("skipped"):
            lines += [f"The suite was {o['skipped']} (`make official` installs CPU torch).", ""]
        else:
            lines += ["Our Eq. 1 and the official renderer's computation (torch, CPU, 2 threads) "
                      "side by side on the same 32 planes ([official.md](official.md)):", ""]
            lines += [f"- {h}" for h in o["summary"]["headlines"]] + [""]
    if "scaling" in results:
        lines += ["## Scaling", "", "![scaling](scaling.png)", ""]
    lines += ["## Suites", ""]
    for name in results:
        lines.append(f"- [{name}]({name}.md) (raw results: [{name}.json]({name}.json))")
    path = out / "index.md"
    write_text(path, "\n".join(lines) + "\n")
    return path
