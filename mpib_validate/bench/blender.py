"""Benchmark on ordinary 3D Blender scenes (:mod:`mpib_validate.blender.scenes`).

Inputs are what an artist renders with Cycles: the sharp Combined pass and the Z pass
(``passes.exr``, read by ``refocus.load_passes`` with its camera header, as ``mpib
refocus`` does). Truth: Cycles' own depth of field, mean of two seeds. Per scene and
focus, each method's time, PSNR, SSIM, PSNR_ob and SSIM_ob (colour clipped to [0, 1]):

- ``preset-<name>``: ``refocus.refocus()`` with the preset, scored as
  ``refocus.write_result`` writes it into the EXR (premultiplied,
  ``image[..., :3] * image[..., 3:4]``); ``preset-<name> (normalised)``: the colour
  before that product (a diagnostic row);
- ``blender-defocus-node``: Blender's Defocus node on the same passes (its own time);
- ``mpib-node-group (compositor)``: the extension's compositor node group on the same
  passes (:func:`node_group`), rendered by Blender;
- ``layered``: the default preset on the layered render of the same scene (one view
  layer per depth group, :mod:`mpib_validate.blender.layered_suite`; what nearer groups
  hide is rendered, not filled), read as ``mpib refocus`` reads it
  (``refocus.load_layered_passes``), premultiplied; scenes where the automatic grouping
  finds one group only have no such row (the single pass is what the extension
  renders there);
- ``sharp input``: the passes' colour itself;
- ``exact-mpi``: the default preset's MPI (``passes.layers_from_passes``, as
  ``refocus.refocus`` builds it, but with the over split, since additive groups have
  no card form) rendered through every aperture sample
  (``cards.mpi.render_exact``), premultiplied; ``exact-mpi (normalised)`` beside it;
- ``truth noise floor``: the PSNR of the truth's own noise, from the two seeds
  (``psnr(a, b) + 20 log10 2``: the mean's noise has a quarter of the pair's MSE).

PSNR_ob mask: boundaries where the sharp Z pass's disparity ``1/Z`` jumps by more
than ``1/A`` between 4-neighbours (a jump of 1 px in blur radius,
``metrics.boundaries_from_disparity``), dilated by the largest blur radius around
(``metrics.occlusion_mask``).

A second part checks blur radius and energy of isolated emitting disks (1 to 3 px
across) in front of and behind the focus plane against Cycles: radius from the second
moment of each emitter's window, ``r^2 = 2 (E_blurred - E_sharp)`` (the sharp render's
moment holds the disk's own size and the pixel box; convolution adds moments), and
energy = the window's sum, for the default preset and the Defocus node.

A third part replaces the Z pass by a degraded disparity, as a monocular estimator errs
(:func:`mpib_validate.cards.degrade.degrade_disparity`, the photos suite's defaults,
seeded per scene): the default preset without and with the guided refinement
(``refocus(..., refine="guided")``) and the Defocus node on the same degraded depth,
against the same truth; the exact depth's scores are the bound. It is the photos
suite's measurement on scenes that are not cards, with its loss decomposition (the
exact disparity given back to the guided result on the highlights, the uncertain band,
both: :func:`mpib_validate.bench.photos.oracle_disparities`), the re-scoped targets
(PSNR_ob outside HDR highlights and structures under 3 px wide, beside the unmasked one)
and the sharp remnants against Cycles (:func:`mpib_validate.bench.photos.scope_scores`).
``run(out, cache=..., degraded_only=True)`` runs this part alone on cached renders
(``blender-degraded.md``).

The Cycles renders are cached under ``<out>/blender-cache`` (see
:func:`blender_scenes.render_suite`): a re-run renders nothing.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mpib_validate.bench.machine import finish, machine_info, mean_table

#: Quick mode (``make demo``): 320x240, truth 64 spp x 2 seeds, sharp 32 spp, the
#: exact MPI renderer at 256 aperture samples (56 dB from its converged image at the
#: boundaries, measured on ground-near and suzanne-far); full mode: 512 x 2, 256 and
#: 1024. The truth's noise (PSNR of the mean of the two seeds, measured at 320x240,
#: 128 spp: 46-56 dB clipped on all but the bokeh scene; it falls 3 dB per halving of
#: the samples) is reported per scene in blender.md.
QUICK = {"width": 320, "height": 240, "spp": 64, "sharp_spp": 32, "exact_samples": 256}
FULL = {"width": 320, "height": 240, "spp": 512, "sharp_spp": 256, "exact_samples": 1024}
#: Scenes whose boundary crops are drawn (name, focus).
CROP_SCENES = (("suzanne", "far"), ("fence", "far"), ("bokeh", "near"), ("ground", "near"))
CROP = 64
DEFAULT = "preset-default"
LAYERED = "layered"
NODE = "blender-defocus-node"
GROUP = "mpib-node-group (compositor)"
DEGRADED = "default, degraded depth"
DEGRADED_GUIDED = "default, degraded depth + guided"
DEGRADED_THIN = "default, degraded depth + guided-thin"
NODE_DEGRADED = "Defocus node, degraded depth"
#: The rows compared with :data:`DEGRADED` (refinement off) in the photographs' remnant
#: region: those fed the same degraded depth.
VS_UNREFINED = (DEGRADED_GUIDED, DEGRADED_THIN, NODE_DEGRADED)


def boundary_mask(depth: np.ndarray, A: float, d_f: float, window: int = 9) -> np.ndarray:
    """PSNR_ob mask from a Z pass: disparity ``1/Z`` (0 at infinity) jumps of more than
    ``1/A`` (1 px of blur radius) between 4-neighbours, dilated by the largest blur
    radius in the ``window`` neighbourhood (``metrics.occlusion_mask``)."""
    from mpib_validate import metrics
    from mpib_validate.runtime.layers.passes import depth_to_disparity

    D = depth_to_disparity(depth)
    b = metrics.boundaries_from_disparity(D, 1.0 / A)
    return metrics.occlusion_mask(b, D, A, d_f, window)


def premultiplied(image: np.ndarray) -> np.ndarray:
    """What ``refocus.write_result`` writes into the EXR: colour times coverage."""
    return image[..., :3] * image[..., 3:4]


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def scene_passes(sc):
    """``(passes, A, d_f)`` of a :class:`SuiteScene`: its ``passes.exr`` and the blur
    parameter and focus that its camera header gives, as ``mpib refocus`` reads them."""
    from mpib_validate.runtime.io.camera_header import resolve
    from mpib_validate.runtime.refocus import load_passes

    path = sc.folder / "passes.exr"
    passes = load_passes(path)
    H, W = passes.depth.shape
    cam = resolve(passes.camera, {}, W, H, path).camera
    return passes, float(cam.blur_parameter), float(cam.focus_disparity)


def timed_refocus(passes, A: float, d_f: float, preset: str):
    """``(result, seconds)``: the refocus of ``passes`` with a preset, timed after an
    untimed warm-up run (the kernel caches)."""
    from mpib_validate.runtime.refocus import refocus
    from mpib_validate.runtime.request import RefocusRequest

    refocus(RefocusRequest(passes, A, d_f, preset))
    return _timed(lambda: refocus(RefocusRequest(passes, A, d_f, preset)))


def method_images(sc, exact_samples: int = 1024, layered=None, degraded: bool = True) -> dict:
    """``{method: (rgb (H, W, 3), seconds)}`` for one :class:`SuiteScene`; ``layered``:
    the path of its layered render (``layers.exr``), if any; ``degraded``: also the
    methods on a degraded depth (:func:`degraded_images`)."""
    from mpib_validate.runtime import samples
    from mpib_validate.blender.scenes import camera, lens
    from mpib_validate.cards.mpi import render_exact
    from mpib_validate.runtime.layers.passes import depth_to_disparity, layers_from_passes
    from mpib_validate.runtime.presets import PRESETS, get_preset
    from mpib_validate.runtime.refocus import load_layered_passes

    passes, A, d_f = scene_passes(sc)
    out = {}
    for name in PRESETS:
        res, seconds = timed_refocus(passes, A, d_f, name)
        out[f"preset-{name}"] = (premultiplied(res.image), seconds)
        out[f"preset-{name} (normalised)"] = (res.image[..., :3], seconds)
    if layered is not None and Path(layered).is_file():
        res, seconds = timed_refocus(load_layered_passes(layered), A, d_f, "default")
        out[LAYERED] = (premultiplied(res.image), seconds)
    import importlib.util

    if importlib.util.find_spec("bpy") is not None:
        from mpib_validate.baselines.defocus_node import defocus

        rgb, seconds = defocus(passes.colour, passes.depth, lens(sc.spec))
        out[NODE] = (rgb, seconds)
        out[GROUP] = node_group(passes, sc.spec, A)
    out["sharp input"] = (passes.colour, 0.0)
    if degraded:
        out.update(degraded_images(sc, passes, A, d_f))
    p = get_preset("default")

    def exact():
        D = depth_to_disparity(passes.depth, source=passes.depth_source)
        # the card form needs the over split (additive groups have none); the same
        # planes and edges as the preset otherwise
        mpi, _ = layers_from_passes(passes.colour, D, A, replace(p.passes, split="linear"))
        return render_exact(mpi, camera(sc.spec), samples.stratified(exact_samples))

    img, seconds = _timed(exact)
    out["exact-mpi"] = (premultiplied(img), seconds)
    out["exact-mpi (normalised)"] = (img[..., :3], seconds)
    return out


def degraded_part_images(sc) -> dict:
    """What the degraded-depth tables need of one scene, as :func:`method_images` makes
    it: the default preset on the exact depth (timed after a warm-up), the Defocus node
    on the exact depth (when bpy is there), the sharp input, and :func:`degraded_images`."""
    from mpib_validate.blender.scenes import lens

    passes, A, d_f = scene_passes(sc)
    res, seconds = timed_refocus(passes, A, d_f, "default")
    out = {DEFAULT: (premultiplied(res.image), seconds)}
    import importlib.util

    if importlib.util.find_spec("bpy") is not None:
        from mpib_validate.baselines.defocus_node import defocus

        out[NODE] = defocus(passes.colour, passes.depth, lens(sc.spec))
    out["sharp input"] = (passes.colour, 0.0)
    out.update(degraded_images(sc, passes, A, d_f))
    return out


def degraded_seed(sc) -> int:
    """The scene's seed for the degradation (the same map on every run)."""
    import zlib

    return zlib.crc32(f"{sc.spec.kind}-{sc.spec.seed}-{sc.spec.focus}".encode()) & 0xFFFF


def degraded_images(sc, passes, A: float, d_f: float) -> dict:
    """The default preset on a degraded disparity (refinement off, guided and
    guided-thin) and the Defocus node on the same degraded depth (when bpy is there)."""
    import importlib.util

    from mpib_validate.bench.photos import (degraded_input, disparity_to_depth,
                                            oracle_disparities)
    from mpib_validate.blender.scenes import lens
    from mpib_validate.runtime.layers.passes import depth_to_disparity
    from mpib_validate.runtime.refocus import refocus
    from mpib_validate.runtime.request import RefocusRequest

    D = depth_to_disparity(passes.depth, source=passes.depth_source)
    Dg = degraded_input(D, degraded_seed(sc))
    depth_g = disparity_to_depth(Dg)
    pg = replace(passes, depth=depth_g, disparity=Dg)
    out = {}
    for name, refine in ((DEGRADED, None), (DEGRADED_GUIDED, "guided"),
                         (DEGRADED_THIN, "guided-thin")):
        res, seconds = _timed(lambda: refocus(RefocusRequest(pg, A, d_f, "default", refine=refine)))
        out[name] = (premultiplied(res.image), seconds)
    # where the loss lies: the exact disparity given back to the guided result on the
    # highlights, the uncertain band, both (the photos suite's decomposition)
    for name, D_o in oracle_disparities(passes.colour, D, Dg, A).items():
        po = replace(passes, depth=disparity_to_depth(D_o), disparity=D_o)
        res, seconds = _timed(lambda: refocus(RefocusRequest(po, A, d_f, "default")))
        out[name] = (premultiplied(res.image), seconds)
    if importlib.util.find_spec("bpy") is not None:
        from mpib_validate.baselines.defocus_node import defocus

        out[NODE_DEGRADED] = defocus(passes.colour, depth_g, lens(sc.spec))
    return out


def node_group(passes, spec, A: float):
    """The MPIB Refocus compositor node group (:mod:`mpib_validate.runtime.blender.nodegroup`) as the
    extension's operator makes it on 5.x (slices from this render's depth, Inpaint fill,
    Convolve blur, Bokeh Blur for slices of small radius at this focus), rendered by Blender's compositor on the same passes; its own time
    (the render op of the compositing tree)."""
    from mpib_validate.blender.scenes import lens
    from mpib_validate.blender.nodegroup_run import run_on_passes
    from mpib_validate.runtime.blender.nodegroup import describe, spec_from_render

    c = lens(spec)
    graph = describe(spec_from_render(passes.depth, A, blur="convolve",
                                      focus_disparity=1.0 / c["focus_distance"]))
    image = np.concatenate([passes.colour, np.ones(passes.depth.shape + (1,), np.float32)],
                           axis=-1)
    values = {"Focus Distance": c["focus_distance"], "F-Stop": c["fstop"],
              "Focal Length": c["lens_mm"], "Sensor Width": c["sensor_width_mm"],
              "Resolution X": float(spec.width), "Resolution Y": float(spec.height)}
    res = run_on_passes(image, passes.depth, graph, values)
    return res["Image"][..., :3], res["seconds"]


def scene_rows(sc, images: dict) -> list[dict]:
    """One row per method: time, PSNR, PSNR_ob, SSIM, SSIM_ob against Cycles' depth of
    field, and the re-scoped PSNR_ob and sharp remnants against it
    (:func:`mpib_validate.bench.photos.scope_scores`: outside the HDR highlights of the
    sharp pass and the structures under 3 px wide of its Z pass's disparity)."""
    from mpib_validate import metrics
    from mpib_validate.bench.photos import degraded_input, refined_input, scope_scores
    from mpib_validate.cards.evaluate import score
    from mpib_validate.runtime.layers.passes import depth_to_disparity

    m = sc.meta
    mask = boundary_mask(sc.depth, m["A"], m["d_f"])
    D = depth_to_disparity(sc.depth)
    excl = metrics.degraded_scope_exclusion(sc.colour, D, m["A"], m["d_f"])
    # the photographs' remnant region: where the degraded map and its refinement blur
    maps, unrefined = None, None
    if DEGRADED in images:
        Dg = degraded_input(D, degraded_seed(sc))
        maps, unrefined = (Dg, refined_input(sc.colour, Dg, m["A"])), images[DEGRADED][0]
    label = f"{sc.spec.kind}-{sc.spec.focus}"
    base = {"scene": label, "kind": sc.spec.kind, "focus": sc.spec.focus, "family": "blender"}
    rows = []
    for method, (img, seconds) in images.items():
        rows.append({**base, "method": method, "seconds": float(seconds),
                     **score(sc.truth, img, mask, with_flip=False),
                     **scope_scores(sc.truth, img, mask, excl, D, m["A"], m["d_f"], maps,
                                    unrefined if method in VS_UNREFINED else None)})
    a, b = (np.clip(s, 0, 1) for s in sc.seeds)
    gain = 20.0 * math.log10(2.0)
    rows.append({**base, "method": "truth noise floor", "seconds": 0.0,
                 "psnr": metrics.psnr(a, b) + gain, "psnr_ob": metrics.psnr(a, b, mask) + gain,
                 "ssim": math.nan, "ssim_ob": math.nan, "mask_fraction": float(mask.mean())})
    return rows


# --------------------------------------------------------------------------------------
# Emitters: radius and energy


def emitter_check(sc, images: dict) -> dict:
    """Radius and energy of each isolated emitter, per method, against Cycles."""
    from mpib_validate.blender.scenes import emitter_grid
    from mpib_validate.blender.cycles import dot_radii

    dots, step = emitter_grid(sc.spec)
    centres = [(e["row"], e["col"]) for e in dots]
    m = sc.meta

    def moment_radius(img):  # sqrt(2 E) per window (no box subtracted)
        return dot_radii(img, centres, step, boxes=0)

    def energy(img):
        lum = np.asarray(img, np.float64)[..., :3].mean(-1)
        h = step // 2
        return np.array([lum[max(0, y - h):y - h + step, max(0, x - h):x - h + step].sum()
                         for y, x in centres])

    r0 = moment_radius(sc.colour)
    expect = np.array([m["A"] * abs(1.0 / e["z"] - m["d_f"]) for e in dots])

    def radius(img):
        return np.sqrt(np.maximum(moment_radius(img) ** 2 - r0 ** 2, 0))

    r_truth, e_truth = radius(sc.truth), energy(sc.truth)
    # the truth's own noise per emitter, from its two seeds (standard error of the mean)
    r_se = np.abs(radius(sc.seeds[0]) - radius(sc.seeds[1])) / 2
    e_se = np.abs(energy(sc.seeds[0]) - energy(sc.seeds[1])) / 2
    groups = []
    for side in ("front", "behind"):
        for diam in sorted({e["diameter_px"] for e in dots}):
            sel = np.array([(("front" if 1.0 / e["z"] > m["d_f"] else "behind") == side)
                            and e["diameter_px"] == diam for e in dots])
            g = {"side": side, "diameter_px": diam, "n": int(sel.sum()),
                 "expected_radius": float(expect[sel].mean()),
                 "cycles_radius": float(r_truth[sel].mean()),
                 "cycles_vs_model": float((r_truth[sel] / expect[sel]).mean()),
                 # relative standard error of the group's mean ratio from the truth's noise
                 "radius_se": float(np.sqrt(((r_se[sel] / r_truth[sel]) ** 2).mean() / sel.sum())),
                 "energy_se": float(np.sqrt(((e_se[sel] / e_truth[sel]) ** 2).mean() / sel.sum()))}
            for method in (DEFAULT, NODE):
                if method not in images:
                    continue
                img = images[method][0]
                r = radius(img)
                g[f"{method}:radius_ratio"] = float((r[sel] / r_truth[sel]).mean())
                g[f"{method}:energy_ratio"] = float((energy(img)[sel] / e_truth[sel]).mean())
            # the sharp pass's own energy against the truth's: a refocus that conserves
            # energy inherits it (the sharp pass's samples differ from the truth's)
            g["input:energy_ratio"] = float((energy(sc.colour)[sel] / e_truth[sel]).mean())
            groups.append(g)
    return {"scene": f"{sc.spec.kind}-{sc.spec.focus}", "A": m["A"], "d_f": m["d_f"],
            "groups": groups}


# --------------------------------------------------------------------------------------
# Figures


def crop_strip(sc, images: dict, truth_name: str = "Cycles depth of field (truth)"):
    """Sharp, Defocus node, default preset and truth side by side: a ``CROP`` px square
    where the default preset errs most inside the boundary mask (9x9 mean error)."""
    from scipy import ndimage

    from mpib_validate.runtime.io.preview import to_uint8

    m = sc.meta
    mask = boundary_mask(sc.depth, m["A"], m["d_f"])
    err = np.abs(np.clip(images[DEFAULT][0], 0, 1) - np.clip(sc.truth, 0, 1)).sum(-1)
    err = ndimage.uniform_filter(np.where(mask, err, 0.0), 9)
    h = CROP // 2
    H, W = err.shape
    err[:h], err[H - h:], err[:, :h], err[:, W - h:] = 0, 0, 0, 0
    y, x = np.unravel_index(int(err.argmax()), err.shape)
    y, x = min(max(y, h), H - h), min(max(x, h), W - h)
    cols = [("sharp input", images["sharp input"][0]), ("Defocus node", images.get(NODE, (None,))[0]),
            ("mpib default", images[DEFAULT][0]), ("Cycles truth", sc.truth)]
    tiles = [(name, to_uint8(im[y - h:y + h, x - h:x + h])) for name, im in cols if im is not None]
    return tiles, (int(y), int(x))


def write_crops(path: Path, strips: list) -> None:
    from PIL import Image, ImageDraw

    from mpib_validate.runtime.io.atomic import atomic_path

    scale, pad, head = 3, 4, 14
    rows = []
    for label, tiles in strips:
        w = len(tiles) * (CROP * scale + pad) + pad
        canvas = Image.new("RGB", (w, CROP * scale + head + pad), "white")
        d = ImageDraw.Draw(canvas)
        for k, (name, t) in enumerate(tiles):
            x0 = pad + k * (CROP * scale + pad)
            canvas.paste(Image.fromarray(t).resize((CROP * scale, CROP * scale), Image.NEAREST),
                         (x0, head))
            d.text((x0, 1), f"{label}: {name}" if k == 0 else name, fill="black")
        rows.append(canvas)
    grid = Image.new("RGB", (max(r.width for r in rows), sum(r.height for r in rows)), "white")
    y = 0
    for r in rows:
        grid.paste(r, (0, y))
        y += r.height
    with atomic_path(path) as tmp:
        grid.save(tmp, format="PNG")


# --------------------------------------------------------------------------------------
# The suite


def run(out: Path, quick: bool = True, config: dict | None = None, cache=None,
        degraded_only: bool = False) -> dict:
    """The suite; ``config`` (``width``, ``height``, ``spp``, ``sharp_spp``) replaces
    :data:`QUICK` / :data:`FULL` (tests run it tiny). ``cache``: the Cycles renders'
    folder (default ``<out>/blender-cache``; a cached scene is read, not rendered).
    ``degraded_only``: only the degraded-depth part (the default preset and the Defocus
    node on the exact and the degraded depth, the loss decomposition, the re-scoped
    targets, the sharp remnants: :func:`degraded_part_images`), without the emitters, the
    layered renders and the other methods; it writes ``blender-degraded.md`` and
    ``.json``."""
    from mpib_validate.blender.layered_suite import render_layered_suite
    from mpib_validate.blender.scenes import FOCI, SceneSpec, load_scene, render_suite, suite_specs
    from mpib_validate.bench.report import pareto_plot

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(cache) if cache is not None else out / "blender-cache"
    cfg = dict(config or (QUICK if quick else FULL))
    specs = suite_specs(cfg["width"], cfg["height"])
    emit_specs = ([] if degraded_only else
                  [SceneSpec("emitters", 0, cfg["width"], cfg["height"], f) for f in FOCI])
    t0 = time.perf_counter()
    folders = render_suite(cache, specs + emit_specs, cfg["spp"], sharp_spp=cfg["sharp_spp"])
    layered = ({} if degraded_only else
               render_layered_suite(cache, specs, cfg["sharp_spp"], folders[:len(specs)]))
    render_seconds = time.perf_counter() - t0
    rows, scenes, strips, emitters = [], [], [], []
    for folder in folders[:len(specs)]:
        sc = load_scene(folder)
        print(f"bench blender: {sc.spec.name} ...", flush=True)
        info = {"scene": f"{sc.spec.kind}-{sc.spec.focus}", "folder": folder.name,
                "A": sc.meta["A"], "d_f": sc.meta["d_f"], "fstop": sc.meta["fstop"],
                "focus_distance": sc.meta["focus_distance"], "noise": sc.meta["noise"],
                "render_seconds": sc.meta["seconds"],
                "truth_spp": sc.meta.get("truth_spp", sc.meta["spp"]),
                "largest_radius_px": _largest_radius(sc)}
        if degraded_only:
            rows += scene_rows(sc, degraded_part_images(sc))
            scenes.append(info)
            continue
        lfolder = layered[sc.spec.name]
        lmeta = json.loads((lfolder / "meta.json").read_text())
        images = method_images(sc, cfg.get("exact_samples", 1024), lfolder / "layers.exr")
        rows += scene_rows(sc, images)
        scenes.append({**info, "layered": {"groups": lmeta["groups"], "report": lmeta["report"],
                                           "seconds": lmeta["seconds"]}})
        if (sc.spec.kind, sc.spec.focus) in CROP_SCENES:
            tiles, at = crop_strip(sc, images)
            strips.append((f"{sc.spec.kind}-{sc.spec.focus} at ({at[1]}, {at[0]})", tiles))
    for folder in folders[len(specs):]:
        sc = load_scene(folder)
        print(f"bench blender: {sc.spec.name} (radius and energy) ...", flush=True)
        images = method_images(sc, cfg.get("exact_samples", 1024), degraded=False)
        emitters.append(emitter_check(sc, images))
    if strips:
        write_crops(out / "blender-crops.png", strips)
    result = {"suite": "blender", "quick": quick, **cfg, "machine": machine_info(),
              "render_seconds": render_seconds, "scenes": scenes, "rows": rows,
              "emitters": emitters, "crops": "blender-crops.png" if strips else None,
              "degraded_only": degraded_only}
    result["summary"] = _summarise(result)
    if degraded_only:
        result["plots"] = []
        return finish(out, "blender-degraded", result, _markdown)
    try:
        for metric in ("psnr", "psnr_ob"):
            pareto_plot(rows, "blender", out / f"pareto-blender-{metric}.png", metric,
                        reference="Cycles' depth of field",
                        title="Error against time, Blender scenes (mean over scenes and foci)")
        result["plots"] = [f"pareto-blender-{m}.png" for m in ("psnr", "psnr_ob")]
    except ImportError:
        result["plots"] = []
    return finish(out, "blender", result, _markdown)


def _largest_radius(sc) -> float:
    from mpib_validate.runtime.layers.passes import depth_to_disparity

    D = depth_to_disparity(sc.depth)
    return float(sc.meta["A"] * np.abs(D - sc.meta["d_f"]).max())


KEYS = ("seconds", "psnr", "psnr_ob", "ssim", "ssim_ob", "psnr_ob_scoped", "scoped_fraction")
#: The rows whose sharp remnants against Cycles the degraded-depth part gives (the
#: exact-depth ones are the control).
REMNANT_METHODS = (DEFAULT, DEGRADED, DEGRADED_GUIDED, DEGRADED_THIN, NODE_DEGRADED, NODE)


def _by_scene(rows) -> dict:
    """``{scene: {method: row}}`` of the suite's rows."""
    by = {}
    for r in rows:
        by.setdefault(r["scene"], {})[r["method"]] = r
    return by


def _summarise(result) -> dict:
    rows = result["rows"]
    table = mean_table(rows, "blender", KEYS)
    by = _by_scene(rows)
    margins = {s: g[DEFAULT]["psnr_ob"] - g[NODE]["psnr_ob"] for s, g in by.items()
               if DEFAULT in g and NODE in g}
    heads = []
    if margins:
        v = np.array(list(margins.values()))
        worst = min(margins, key=margins.get)
        heads.append(f"Blender scenes: the default preset is {v.mean():+.1f} dB PSNR_ob ahead of "
                     f"Blender's Defocus node on average over {len(v)} scenes and foci; it wins "
                     f"{int((v > 0).sum())} of {len(v)}; worst {worst} ({margins[worst]:+.1f} dB).")
    group_margins = {s: gr[GROUP]["psnr_ob"] - gr[NODE]["psnr_ob"] for s, gr in by.items()
                     if GROUP in gr and NODE in gr}
    if group_margins:
        v = np.array(list(group_margins.values()))
        worst = min(group_margins, key=group_margins.get)
        d = np.array([by[s][GROUP]["psnr_ob"] - by[s][DEFAULT]["psnr_ob"] for s in group_margins])
        heads.append(f"Blender scenes: the compositor node group is {v.mean():+.1f} dB PSNR_ob "
                     f"ahead of the Defocus node on average (wins {int((v > 0).sum())} of "
                     f"{len(v)}; worst {worst}, {group_margins[worst]:+.1f} dB) and "
                     f"{d.mean():+.1f} dB from the numpy default preset (worst {d.min():+.1f} dB).")
    layered = layered_table(result)
    if layered:
        d = np.array([r["layered_minus_default"] for r in layered])
        n = np.array([r["layered_minus_node"] for r in layered])
        hard = [r for r in layered if r["kind"] in LAYERED_HARD_KINDS]
        wall = np.array([r["wall_ratio"] for r in layered])
        cpu = np.array([r["cpu_ratio"] for r in layered])
        heads.append(
            f"Layered render (one view layer per depth group): {d.mean():+.1f} dB PSNR_ob over the "
            f"single-pass default on average (worst {d.min():+.1f} dB; thin, veil and bokeh scenes "
            f"{min(r['layered_minus_default'] for r in hard):+.1f} to "
            f"{max(r['layered_minus_default'] for r in hard):+.1f} dB, target +3) and "
            f"{n.mean():+.1f} dB over the Defocus node (worst {n.min():+.1f} dB, target +6) on "
            f"{len(layered)} scenes and foci; the layered colour render costs {wall.min():.2f}-"
            f"{wall.max():.2f}x the single pass's wall time ({cpu.min():.2f}-{cpu.max():.2f}x its "
            f"CPU time) at the same samples.")
    deg = degraded_table(result)
    if deg:
        mean = {k: float(np.mean([r[k] for r in deg])) for k in
                ("exact", "degraded", "guided", "thin", "node_degraded")}
        margin = np.array([r["guided"] - r["node_degraded"] for r in deg])
        heads.append(
            f"Blender scenes with a degraded depth (a monocular estimator's errors, as the "
            f"photos suite's): the default preset {mean['degraded']:.1f} dB PSNR_ob, "
            f"{mean['guided']:.1f} dB with the guided refinement, against "
            f"{mean['exact']:.1f} dB from the exact depth ({mean['guided'] - mean['exact']:+.1f} "
            f"dB) and {mean['node_degraded']:.1f} dB for the Defocus node on the same degraded "
            f"depth ({margin.mean():+.1f} dB; the refined default wins {int((margin > 0).sum())} "
            f"of {len(margin)}, worst {margin.min():+.1f} dB); with guided-thin "
            f"{mean['thin']:.1f} dB.")
        orc = {k: float(np.mean([r[f"oracle_{k}"] for r in deg]))
               for k in ("highlights", "band", "both")}
        if all(math.isfinite(v) for v in orc.values()):
            heads.append(
                f"Blender scenes, where the degraded depth loses (the exact disparity given "
                f"back to the guided result): on the highlights "
                f"{orc['highlights'] - mean['guided']:+.1f} dB, on the uncertain band "
                f"{orc['band'] - mean['guided']:+.1f} dB, on both "
                f"{orc['both'] - mean['guided']:+.1f} dB; the rest "
                f"{mean['exact'] - orc['both']:+.1f} dB to the exact bound.")
    from mpib_validate.bench.photos import remnant_summary, scope_summary

    scope = scope_summary(rows, "Blender scenes", DEFAULT, DEGRADED_GUIDED, NODE_DEGRADED)
    if scope:
        heads.append(scope["headline"])
    rem = remnant_summary(rows, "Blender scenes", REMNANT_METHODS, DEGRADED_GUIDED, DEFAULT)
    if rem.get("methods"):
        heads.append(rem["headline"])
    g = {r["method"]: r for r in table}
    if DEFAULT in g and "exact-mpi" in g:
        heads.append(f"Blender scenes: the same MPI rendered exactly reaches PSNR_ob "
                     f"{g['exact-mpi']['psnr_ob']:.1f} dB against {g[DEFAULT]['psnr_ob']:.1f} dB "
                     f"for Eq. 1 as written (normalised colour: "
                     f"{g[DEFAULT + ' (normalised)']['psnr_ob']:.1f} dB); truth noise floor "
                     f"{g['truth noise floor']['psnr_ob']:.1f} dB.")
    ratios = [(gr[f"{DEFAULT}:radius_ratio"], gr[f"{DEFAULT}:energy_ratio"],
               gr.get("input:energy_ratio", math.nan))
              for e in result["emitters"] for gr in e["groups"] if f"{DEFAULT}:radius_ratio" in gr]
    if ratios:
        rr, er, ir = np.array(ratios).T
        heads.append(f"Isolated emitters 1-3 px across: default preset / Cycles radius "
                     f"{rr.min():.3f}-{rr.max():.3f}, energy {er.min():.3f}-{er.max():.3f} "
                     f"(groups by side of the focus plane and size); the sharp input's own "
                     f"energy / Cycles' {ir.min():.3f}-{ir.max():.3f}, the default's energy / "
                     f"the input's {np.nanmin(er / ir):.3f}-{np.nanmax(er / ir):.3f}.")
    return {"headlines": heads, "table": table, "margins": margins, "scope": scope,
            "remnants": rem}


#: Scene kinds the layered target (+3 dB over the single pass) is for: thin structures,
#: a semi-transparent sheet, partly hidden bright emitters.
LAYERED_HARD_KINDS = ("fence", "veil", "bokeh")


def layered_table(result) -> list[dict]:
    """Per scene and focus with a layered row: groups, PSNR_ob of the layered path, the
    single-pass default and the Defocus node, the margins, and the render-cost ratios."""
    by = _by_scene(result["rows"])
    info = {s["scene"]: s for s in result["scenes"]}
    out = []
    for scene, g in by.items():
        if LAYERED not in g or DEFAULT not in g:
            continue
        lay = info[scene].get("layered", {})
        sec = lay.get("seconds", {})
        row = {"scene": scene, "kind": g[LAYERED]["kind"], "groups": len(lay.get("groups", [])),
               "layered": g[LAYERED]["psnr_ob"], "default": g[DEFAULT]["psnr_ob"],
               "node": g[NODE]["psnr_ob"] if NODE in g else math.nan,
               "floor": g["truth noise floor"]["psnr_ob"] if "truth noise floor" in g else math.nan,
               "wall_ratio": sec.get("wall_ratio", math.nan),
               "cpu_ratio": sec.get("cpu_ratio", math.nan)}
        row["layered_minus_default"] = row["layered"] - row["default"]
        row["layered_minus_node"] = row["layered"] - row["node"]
        out.append(row)
    return out


def degraded_table(result) -> list[dict]:
    """Per scene and focus: PSNR_ob of the default preset on the exact and the degraded
    depth (refinement off, guided, guided-thin), of the Defocus node on both, and of the
    loss decomposition's rows (``oracle_highlights``, ``oracle_band``, ``oracle_both``:
    the guided result with the exact disparity given back there)."""
    from mpib_validate.bench.photos import ORACLES

    by = _by_scene(result["rows"])
    out = []
    for scene, g in by.items():
        if DEGRADED not in g or DEFAULT not in g:
            continue
        out.append({"scene": scene, "exact": g[DEFAULT]["psnr_ob"],
                    "degraded": g[DEGRADED]["psnr_ob"], "guided": g[DEGRADED_GUIDED]["psnr_ob"],
                    "thin": g[DEGRADED_THIN]["psnr_ob"] if DEGRADED_THIN in g else math.nan,
                    "node_exact": g[NODE]["psnr_ob"] if NODE in g else math.nan,
                    "node_degraded": (g[NODE_DEGRADED]["psnr_ob"] if NODE_DEGRADED in g
                                      else math.nan),
                    **{f"oracle_{k}": g[name]["psnr_ob"] if name in g else math.nan
                       for k, name in ORACLES.items()}})
    return out


def _fmt(v, nd=2):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def _markdown(result) -> str:
    from mpib_validate.bench.photos import HIGHLIGHT_GROW_PX

    m = result["machine"]
    lines = ["# Refocusing ordinary 3D Blender scenes", "",
             f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} cores; "
             f"Python {m['python']}, bpy {m.get('bpy', '-')}. "
             f"{'Quick' if result['quick'] else 'Full'} mode: {result['width']}x{result['height']}, "
             f"85 mm on a 36 mm sensor; input = Cycles' sharp Combined ({result['sharp_spp']} spp, "
             f"Box filter) + Z pass; truth = Cycles' depth of field, mean of two seeds at "
             f"{result['spp']} spp each; exact MPI renderer at {result.get('exact_samples', 1024)} aperture samples (Cycles renders: {result['render_seconds']:.0f} s this run, "
             f"0 when cached). Scores on colour clipped to [0, 1]; PSNR_ob mask from the Z pass "
             f"(disparity jumps of 1 px blur radius, dilated by the blur radius).", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    lines += ["## Mean over scenes and foci", "",
              "| method | time (s) | PSNR | PSNR_ob | PSNR_ob re-scoped | SSIM | SSIM_ob |",
              "|---|---|---|---|---|---|---|"]
    for r in result["summary"]["table"]:
        lines.append(f"| {r['method']} | {_fmt(r['seconds'], 3)} | {_fmt(r['psnr'])} | "
                     f"{_fmt(r['psnr_ob'])} | {_fmt(r.get('psnr_ob_scoped'))} | "
                     f"{_fmt(r['ssim'], 4)} | {_fmt(r['ssim_ob'], 4)} |")
    lines += ["", "## PSNR_ob per scene and focus", "",
              "| scene | max radius (px) | f-stop | sharp input | Defocus node | node group "
              "| default (EXR as written) | default, normalised | exact MPI | draft | best "
              "| truth noise floor | default - node |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    by = _by_scene(result["rows"])
    info = {s["scene"]: s for s in result["scenes"]}
    for scene, g in by.items():
        def v(name):
            return _fmt(g[name]["psnr_ob"]) if name in g else "-"
        mg = result["summary"]["margins"].get(scene)
        lines.append(f"| {scene} | {_fmt(info[scene]['largest_radius_px'], 1)} | "
                     f"{_fmt(info[scene]['fstop'], 2)} | {v('sharp input')} | {v(NODE)} | "
                     f"{v(GROUP)} | {v(DEFAULT)} | {v(DEFAULT + ' (normalised)')} | {v('exact-mpi')} | "
                     f"{v('preset-draft')} | {v('preset-best')} | {v('truth noise floor')} | "
                     f"{_fmt(mg)} |")
    layered = layered_table(result)
    if layered:
        lines += ["", "## Layered render (one view layer per depth group)", "",
                  "PSNR_ob of the default preset on the layered render (what nearer groups hide "
                  "is rendered by Cycles, not filled) against the single pass and the Defocus "
                  "node; render cost = the layered colour render over the single-pass colour "
                  "render, same samples, timed single, layered, single in one run (wall and "
                  "CPU time ratios; the 1-spp depth renders are not counted). Targets: layered "
                  "- default >= +3 dB on the thin (fence), veil and bokeh scenes and >= 0 "
                  "elsewhere; layered - node >= +6 dB everywhere.", "",
                  "| scene | groups | layered | single-pass default | Defocus node | "
                  "layered - default | layered - node | truth noise floor | render wall ratio | "
                  "render CPU ratio |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in layered:
            lines.append(f"| {r['scene']} | {r['groups']} | {_fmt(r['layered'])} | "
                         f"{_fmt(r['default'])} | {_fmt(r['node'])} | "
                         f"{r['layered_minus_default']:+.2f} | {r['layered_minus_node']:+.2f} | "
                         f"{_fmt(r['floor'])} | {_fmt(r['wall_ratio'])} | {_fmt(r['cpu_ratio'])} |")
        lines += ["", "Groups per scene (automatic, far to near): " + "; ".join(
            f"{s['scene'].rsplit('-', 1)[0]}: {s['layered']['report']}" for s in result["scenes"]
            if s["scene"].endswith("-far") and "layered" in s) + "."]
    deg = degraded_table(result)
    if deg:
        lines += ["", "## Degraded depth (a monocular estimator's errors)", "",
                  "PSNR_ob against Cycles' depth of field when the Z pass is replaced by a "
                  "degraded disparity (the photos suite's: Gaussian blur of 2 px, 4x down and "
                  "bilinear up, 2 % multiplicative noise per low-resolution pixel, a 1.5 px "
                  "shift; seeded per scene). The exact depth's scores are the bound.", "",
                  "| scene | default, exact | default, degraded | default, degraded + guided "
                  "| default, degraded + guided-thin | Defocus node, exact "
                  "| Defocus node, degraded | guided - node (degraded) |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in deg:
            lines.append(f"| {r['scene']} | {_fmt(r['exact'])} | {_fmt(r['degraded'])} | "
                         f"{_fmt(r['guided'])} | {_fmt(r['thin'])} | {_fmt(r['node_exact'])} | "
                         f"{_fmt(r['node_degraded'])} | {r['guided'] - r['node_degraded']:+.2f} |")
        keys = ("exact", "degraded", "guided", "thin", "node_exact", "node_degraded")
        mean = {k: float(np.mean([r[k] for r in deg])) for k in keys}
        lines.append("| mean | " + " | ".join(_fmt(mean[k]) for k in keys) +
                     f" | {mean['guided'] - mean['node_degraded']:+.2f} |")
        from mpib_validate.bench.photos import scope_markdown

        lines += [""] + scope_markdown(result["summary"].get("scope", {}),
                                       result["summary"].get("remnants", {}),
                                       result["rows"], REMNANT_METHODS)
        rm = [m for m in REMNANT_METHODS if any(r["method"] == m for r in result["rows"])]
        if rm:
            lines += ["Sharp remnants against Cycles per scene (count / must-blur pixels where "
                      "the truth is smooth enough to count):", "",
                      "| scene | " + " | ".join(rm) + " |", "|---" * (len(rm) + 1) + "|"]
            for scene, g in by.items():
                if DEGRADED not in g:
                    continue
                lines.append(f"| {scene} | " + " | ".join(
                    f"{g[m]['remnants']} / {g[m]['must_blur_smooth']}" if m in g else "-"
                    for m in rm) + " |")
            lines.append("")
        okeys = ("oracle_highlights", "oracle_band", "oracle_both")
        if all(math.isfinite(r[k]) for r in deg for k in okeys):
            lines += ["", "Where the loss lies: the guided result with the exact disparity "
                      "given back on the HDR highlights (all-in-focus > 1, grown "
                      f"{HIGHLIGHT_GROW_PX} px), on the refinement's uncertain band, on both "
                      "(PSNR_ob, dB).", "",
                      "| scene | guided | + exact on highlights | + exact on band "
                      "| + exact on both | exact (bound) |", "|---|---|---|---|---|---|"]
            for r in deg + [{"scene": "mean", **{k: float(np.mean([x[k] for x in deg]))
                                                 for k in ("guided", "exact") + okeys}}]:
                lines.append(f"| {r['scene']} | {_fmt(r['guided'])} | "
                             + " | ".join(_fmt(r[k]) for k in okeys)
                             + f" | {_fmt(r['exact'])} |")
    lines += ["", "## Every method per scene", "",
              "| scene | method | time (s) | PSNR | PSNR_ob | SSIM | SSIM_ob |",
              "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['scene']} | {r['method']} | {_fmt(r['seconds'], 3)} | {_fmt(r['psnr'])} | "
                     f"{_fmt(r['psnr_ob'])} | {_fmt(r.get('ssim'), 4)} | {_fmt(r.get('ssim_ob'), 4)} |")
    lines += ["", "## Truth noise and Cycles times", "",
              "| scene | A (px) | d_f (1/m) | truth spp per seed | noise RMSE of the mean | "
              "noise PSNR (clipped) | truth render (s, per seed) | sharp (s) |",
              "|---|---|---|---|---|---|---|---|"]
    for s in result["scenes"]:
        t = s["render_seconds"]
        lines.append(f"| {s['scene']} | {_fmt(s['A'], 1)} | {_fmt(s['d_f'], 4)} | "
                     f"{s['truth_spp']} | {s['noise']['rmse']:.4f} | {_fmt(s['noise']['psnr_clipped'])} | "
                     f"{', '.join(_fmt(x, 1) for x in t['truth'])} | {_fmt(t['sharp'], 1)} |")
    lines += ["", "## Isolated emitters: radius and energy against Cycles", "",
              "Radius from the second moment of each emitter's window, r^2 = 2 (E - E_sharp); "
              "energy = the window's sum. Ratios are method / Cycles, mean over the group; "
              "\u00b1 the truth's noise (standard error of the group mean, from its two seeds). "
              "The sharp input's energy over the truth's is the bound of a refocus that "
              "conserves energy: the sharp pass has its own samples.", "",
              "| scene | side of focus | diameter (px) | n | A\\|d - d_f\\| (px) | Cycles radius (px) | "
              "default: radius ratio | default: energy ratio | sharp input: energy ratio | "
              "node: radius ratio | node: energy ratio |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in result["emitters"]:
        for g in e["groups"]:
            lines.append(f"| {e['scene']} | {g['side']} | {g['diameter_px']:g} | {g['n']} | "
                         f"{_fmt(g['expected_radius'])} | {_fmt(g['cycles_radius'])} | "
                         f"{_fmt(g.get(DEFAULT + ':radius_ratio'), 3)} \u00b1 {_fmt(g['radius_se'], 3)} | "
                         f"{_fmt(g.get(DEFAULT + ':energy_ratio'), 3)} \u00b1 {_fmt(g['energy_se'], 3)} | "
                         f"{_fmt(g.get('input:energy_ratio'), 3)} | "
                         f"{_fmt(g.get(NODE + ':radius_ratio'), 3)} | "
                         f"{_fmt(g.get(NODE + ':energy_ratio'), 3)} |")
    if result.get("crops"):
        lines += ["", "## At occlusion boundaries", "",
                  f"Crops ({CROP}x{CROP}, x3) where the default preset errs most inside the mask; "
                  "columns: sharp input, Defocus node, default preset (as written), Cycles truth.",
                  "", f"![crops]({result['crops']})"]
    for p in result.get("plots", []):
        lines += ["", f"![pareto]({p})"]
    return "\n".join(lines) + "\n"
