"""Benchmark of refocusing from colour + a *predicted-looking* disparity, against the ray tracer.

A photograph comes with a disparity predicted by a monocular network, not a renderer's
exact depth. On the card scenes of the refocus suite (same seeds and sizes), the
tracer's exact disparity is degraded as an estimator errs
(:func:`mpib_validate.cards.degrade.degrade_disparity`: blur, 4x down and bilinear up,
smooth multiplicative noise, a 1.5 px shift; seeded by the scene's seed), and every
preset refocuses colour + that disparity, without and with the edge-aware refinement
(:mod:`mpib_validate.runtime.layers.refine`, ``PassesSettings(refine="guided")``, and for the
default preset ``"guided-thin"``); Blender's
Defocus node gets the same degraded depth. The exact-depth scores are the bound, and
the refinement is also run on exact depth (it must not hurt there). The boundary mask
is the true one (:func:`mpib_validate.cards.evaluate.card_scene_mask`).

Also: the refinement's CPU time at 1920x1080 against the rest of the default pipeline
(one process, ``time.process_time``: all threads' CPU time, so a ratio that holds on a
loaded machine), and the Middlebury motorcycle (scikit-image) refocused near and far
with exact and with degraded disparity, with boundary crops beside the input.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from mpib_validate.bench.machine import finish, machine_info, mean_table

#: the refocus suite's scenes (bench/refocus.py): 8 seeds per family
SEEDS = range(8)


def degraded_input(disparity: np.ndarray, seed: int) -> np.ndarray:
    """The suite's degraded disparity of a scene: the default degradation, seeded by the
    scene's seed."""
    from mpib_validate.cards.degrade import degrade_disparity

    return degrade_disparity(disparity, seed)


def disparity_to_depth(disparity: np.ndarray) -> np.ndarray:
    """Planar depth ``1/d`` for Blender's Defocus node; 1e10 (Cycles' sky) where ``d = 0``."""
    d = np.asarray(disparity, np.float64)
    return np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1e10)


def _methods(scene, res, seed):
    from mpib_validate.runtime.compositor.composite import render_subapertures
    from mpib_validate.runtime.layers.passes import depth_to_disparity, layers_from_passes
    from mpib_validate.runtime.presets import PRESETS

    cam = scene.camera
    A, df = cam.blur_parameter, cam.focus_disparity
    aif = res.all_in_focus[..., :3]
    exact = depth_to_disparity(res.depth)
    degraded = degraded_input(exact, seed)

    def passes(D, preset, refine):
        settings = dataclasses.replace(preset.passes, refine=refine)

        def run():
            mpi, _ = layers_from_passes(aif, D, A, settings)
            return render_subapertures(mpi, A, df, preset.subapertures, preset.composite)
        return run

    methods = {}
    for name, p in PRESETS.items():
        methods[f"{name} exact (bound)"] = passes(exact, p, "off")
        methods[f"{name} degraded"] = passes(degraded, p, "off")
        methods[f"{name} degraded + guided"] = passes(degraded, p, "guided")
    methods["default degraded + guided-thin"] = passes(degraded, PRESETS["default"],
                                                       "guided-thin")
    methods.update(_oracle_methods(aif, exact, degraded, A, passes, PRESETS["default"]))
    methods["default exact + guided"] = passes(exact, PRESETS["default"], "guided")
    methods["default exact + guided-thin"] = passes(exact, PRESETS["default"], "guided-thin")
    import importlib.util

    if importlib.util.find_spec("bpy") is not None:
        from mpib_validate.baselines.defocus_node import defocus

        settings = cam.cycles_settings()
        methods["defocus-node exact"] = lambda: defocus(aif, res.depth, settings, timing=False)
        methods["defocus-node degraded"] = lambda: defocus(aif, disparity_to_depth(degraded),
                                                           settings, timing=False)
    return methods


#: The loss decomposition's rows (:func:`_oracle_methods`): the guided refinement of the
#: degraded disparity with the exact disparity given back on one region.
ORACLES = {"highlights": "oracle: guided + exact on highlights",
           "band": "oracle: guided + exact on the band",
           "both": "oracle: guided + exact on both"}
#: A highlight, for the loss decomposition: an all-in-focus pixel brighter than 1 in
#: some channel, grown by this many pixels (its anti-aliased rim).
HIGHLIGHT_GROW_PX = 2


def oracle_disparities(aif, exact, degraded, A) -> dict:
    """Where the degraded depth's loss lies: ``{row name: disparity}``, the guided
    refinement of the degraded disparity with the exact disparity put back (a) on the
    HDR highlights (the degradation erases the depth of a light smaller than its blur,
    and the colour cannot tell it back), (b) on the refinement's uncertain band (the
    edges it moves), (c) on both. What (c) leaves below the exact-depth bound lies
    elsewhere: structures whose predicted edge is too weak to make a band. Used by this
    suite on the cards and by ``mpib bench --suite blender`` on its scenes."""
    from scipy import ndimage

    from mpib_validate.runtime.layers.refine import refine_disparity, uncertain_band

    refined = refine_disparity(aif, degraded, A)
    lights = ndimage.binary_dilation(np.asarray(aif)[..., :3].max(axis=-1) > 1.0,
                                     iterations=HIGHLIGHT_GROW_PX)
    band = uncertain_band(degraded, A)
    regions = {"highlights": lights, "band": band, "both": lights | band}
    return {ORACLES[k]: np.where(sel, exact, refined) for k, sel in regions.items()}


def _oracle_methods(aif, exact, degraded, A, passes, preset) -> dict:
    """The default preset (refinement off) on each of :func:`oracle_disparities`."""
    return {name: passes(D, preset, "off")
            for name, D in oracle_disparities(aif, exact, degraded, A).items()}


def scene_rows(scene, label, family, seed, ref_spp, only=None) -> list[dict]:
    """One row per method: PSNR, PSNR_ob, SSIM, SSIM_ob against the ray tracer at
    ``ref_spp`` samples, and the method's time (CPU seconds of this process; the Defocus
    node's is Blender's whole render op, not comparable)."""
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.cards.evaluate import card_scene_mask, score

    res = trace.render(scene, samples.stratified(ref_spp, seed=11), notices=False)
    mask = card_scene_mask(scene)
    rows = []
    for name, fn in _methods(scene, res, seed).items():
        if only is not None and name not in only:
            continue
        t0 = time.process_time()
        out = fn()
        seconds = time.process_time() - t0
        if isinstance(out, tuple):
            out = out[0]
            seconds = math.nan
        rows.append({"scene": label, "family": family, "method": name, "cpu_seconds": seconds,
                     **score(res.bokeh, out, mask, with_flip=False)})
    return rows


def _scene_task(item) -> list[dict]:
    from mpib_validate.cards.generate import GeneratorSettings, generate

    seed, family, size, ref_spp = item
    print(f"bench photos: {family}-{seed} ({size}x{size}) ...", flush=True)
    scene = generate(seed, family, settings=GeneratorSettings(width=size, height=size))
    return scene_rows(scene, f"{family}-{seed}", family, seed, ref_spp)


def refine_cost() -> dict:
    """CPU seconds (``time.process_time``, one run, this process) of the refinement and of
    the rest of the default pipeline (layers + Eq. 1) on the refocus suite's 1080p scene
    with its degraded disparity."""
    from mpib_validate.bench.compositor import hd_scene
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.runtime.compositor.composite import render_subapertures
    from mpib_validate.runtime.layers.passes import depth_to_disparity, layers_from_passes
    from mpib_validate.runtime.layers.refine import refine_disparity
    from mpib_validate.runtime.presets import PRESETS

    scene = hd_scene()
    res = trace.render(scene, samples.pinhole(2), notices=False)
    cam = scene.camera
    A, df = cam.blur_parameter, cam.focus_disparity
    aif = res.all_in_focus[..., :3]
    D = degraded_input(depth_to_disparity(res.depth), 0)
    p = PRESETS["default"]
    t0 = time.process_time()
    w0 = time.perf_counter()
    R = refine_disparity(aif, D, A)
    t_ref, w_ref = time.process_time() - t0, time.perf_counter() - w0
    t0 = time.process_time()
    w0 = time.perf_counter()
    mpi, _ = layers_from_passes(aif, R, A, p.passes)
    render_subapertures(mpi, A, df, p.subapertures, p.composite)
    t_rest, w_rest = time.process_time() - t0, time.perf_counter() - w0
    return {"width": cam.width, "height": cam.height, "refine_cpu_s": t_ref, "rest_cpu_s": t_rest,
            "ratio": t_ref / t_rest, "refine_wall_s": w_ref, "rest_wall_s": w_rest}


def load_motorcycle():
    """scikit-image's Middlebury ``stereo_motorcycle`` left view and its disparity, as the
    refocus figures use them: ``(linear rgb (H, W, 3) float32, disparity in [0, 1])``.

    The photo is linearised with the sRGB curve; unknown disparities (inf) take their
    nearest known value; the disparity is normalised to [0, 1] (the paper's convention).
    """
    from scipy import ndimage
    from skimage import data

    from mpib_validate.cards.textures import srgb_to_linear

    left, _, disp = data.stereo_motorcycle()
    known = np.isfinite(disp)
    _, (iy, ix) = ndimage.distance_transform_edt(~known, return_indices=True)
    disp = disp[iy, ix]
    D = (disp - disp.min()) / (disp.max() - disp.min())
    return srgb_to_linear(left.astype(np.float64) / 255.0).astype(np.float32), D


def photo_figure(path: Path, crop: int = 80) -> dict:
    """The Middlebury motorcycle refocused near (90th percentile of disparity) and far
    (10th), default preset, ``A`` = 2 % of the width. Top: input | exact stereo disparity |
    degraded disparity | degraded + guided refinement, per focus (half size). Below: per
    focus, ``crop`` px crops (x2) at the two strongest disparity edges, each with the
    same four columns.
    Returns the settings and the crop centres."""
    from PIL import Image

    from mpib_validate.runtime.compositor.composite import composite
    from mpib_validate.runtime.io.atomic import atomic_path
    from mpib_validate.runtime.io.preview import to_uint8
    from mpib_validate.runtime.layers.passes import PassesSettings, layers_from_passes
    from mpib_validate.runtime.presets import PRESETS
    from scipy import ndimage

    rgb, D = load_motorcycle()
    H, W = D.shape
    A = 0.02 * W
    Dg = degraded_input(D, 0)
    base = PRESETS["default"].passes
    mpis = [layers_from_passes(rgb, D, A, base)[0],
            layers_from_passes(rgb, Dg, A, base)[0],
            layers_from_passes(rgb, Dg, A, dataclasses.replace(base, refine="guided"))[0]]
    # crop centres: the two largest blur-radius ranges over 9x9 windows, 2 crops apart
    rng = A * (ndimage.maximum_filter(D, 9) - ndimage.minimum_filter(D, 9))
    h = crop // 2
    rng[:h], rng[-h:], rng[:, :h], rng[:, -h:] = 0, 0, 0, 0
    centres = []
    for _ in range(2):
        y, x = np.unravel_index(int(rng.argmax()), rng.shape)
        centres.append((int(y), int(x)))
        rng[max(0, y - 2 * crop):y + 2 * crop, max(0, x - 2 * crop):x + 2 * crop] = 0
    full_rows, crop_rows = [], []
    for name, d_f in (("near", float(np.quantile(D, 0.9))), ("far", float(np.quantile(D, 0.1)))):
        outs = [rgb] + [composite(m, A, d_f)[..., :3] for m in mpis]
        full_rows.append(np.concatenate([to_uint8(o) for o in outs], axis=1))
        tiles = [np.pad(to_uint8(o[y - h:y + h, x - h:x + h]), ((2, 2), (2, 2), (0, 0)),
                        constant_values=255) for y, x in centres for o in outs]
        crop_rows.append(np.concatenate(tiles, axis=1))
    top = Image.fromarray(np.concatenate(full_rows, axis=0))
    top = top.resize((top.width // 2, top.height // 2), Image.LANCZOS)
    crops = Image.fromarray(np.concatenate(crop_rows, axis=0))
    crops = crops.resize((crops.width * 2, crops.height * 2), Image.NEAREST)
    w = max(top.width, crops.width)
    fig = Image.new("RGB", (w, top.height + crops.height), (255, 255, 255))
    fig.paste(top, (0, 0))
    fig.paste(crops, (0, top.height))
    with atomic_path(path) as tmp:
        fig.save(tmp, format="PNG")
    return {"width": W, "height": H, "A": A, "crop_centres": centres, "crop_px": crop}


def run(out: Path, quick: bool = True, executor=None, seeds=SEEDS, size=None,
        ref_spp=None, hd=True, figure=True, remnants=True) -> dict:
    from mpib_validate.cards.generate import FAMILIES
    from mpib_validate.executor import make_executor

    out.mkdir(parents=True, exist_ok=True)
    size = size or (192 if quick else 512)
    ref_spp = ref_spp or (2048 if quick else 8192)
    items = [(seed, family, size, ref_spp) for family in FAMILIES for seed in seeds]
    rows = [r for part in (executor or make_executor()).map(_scene_task, items) for r in part]
    result = {"suite": "photos", "quick": quick, "size": size, "reference_spp": ref_spp,
              "machine": machine_info(), "rows": rows}
    if hd:
        print("bench photos: refinement cost at 1920x1080 ...", flush=True)
        result["refine_cost"] = refine_cost()
    if figure:
        print("bench photos: the Middlebury motorcycle ...", flush=True)
        result["figure"] = {"path": "photos.png", **photo_figure(out / "photos.png")}
    if remnants:
        from mpib_validate.bench import remnants as _remnants

        print("bench photos: sharp remnants on the shipped photographs ...", flush=True)
        result["remnants"] = _remnants.run(out if figure else None)
    result["summary"] = _summarise(result)
    return finish(out, "photos", result, _markdown)


KEYS = ("cpu_seconds", "psnr", "psnr_ob", "ssim", "ssim_ob")


def _summarise(result):
    heads, tables = [], {}
    for family in ("constant", "varying"):
        t = mean_table(result["rows"], family, KEYS)
        tables[family] = t
        g = {r["method"]: r for r in t}
        ex, dg, rf = (g.get(f"default {k}") for k in ("exact (bound)", "degraded",
                                                        "degraded + guided"))
        node = g.get("defocus-node degraded")
        if ex and dg and rf:
            s = (f"{family}: with degraded disparity the default preset reaches PSNR_ob "
                 f"{dg['psnr_ob']:.1f} dB, {rf['psnr_ob']:.1f} dB with the guided refinement, "
                 f"against {ex['psnr_ob']:.1f} dB from exact depth "
                 f"({rf['psnr_ob'] - ex['psnr_ob']:+.1f} dB)")
            if node:
                s += (f" and {node['psnr_ob']:.1f} dB for Blender's Defocus node on the same "
                      f"degraded depth ({rf['psnr_ob'] - node['psnr_ob']:+.1f} dB)")
            heads.append(s + ".")
        th = g.get("default degraded + guided-thin")
        if ex and th:
            heads.append(f"{family}: with the thin-structure recovery (guided-thin): "
                         f"{th['psnr_ob']:.1f} dB ({th['psnr_ob'] - ex['psnr_ob']:+.1f} dB)"
                         + (f", {th['psnr_ob'] - node['psnr_ob']:+.1f} dB over the Defocus "
                            f"node." if node else "."))
        orc = [g.get(ORACLES[k]) for k in ("highlights", "band", "both")]
        if ex and rf and all(orc):
            heads.append(f"{family}: where the degraded depth loses (the exact disparity "
                         f"given back to the guided refinement's): on the highlights "
                         f"{orc[0]['psnr_ob'] - rf['psnr_ob']:+.1f} dB, on the uncertain band "
                         f"{orc[1]['psnr_ob'] - rf['psnr_ob']:+.1f} dB, on both "
                         f"{orc[2]['psnr_ob'] - rf['psnr_ob']:+.1f} dB; the rest "
                         f"{ex['psnr_ob'] - orc[2]['psnr_ob']:+.1f} dB to the exact bound.")
        eg, et = g.get("default exact + guided"), g.get("default exact + guided-thin")
        if ex and eg and et:
            heads.append(f"{family}: the refinement on exact depth: PSNR_ob "
                         f"{eg['psnr_ob']:.1f} dB (guided), {et['psnr_ob']:.1f} dB "
                         f"(guided-thin) against {ex['psnr_ob']:.1f} dB without.")
    rem = result.get("remnants")
    if rem:
        rows = rem["rows"]
        heads.append(
            f"sharp remnants on {len({r['photo'] for r in rows})} scikit-image photographs with "
            f"network-like disparity (near and far focus): "
            f"{sum(r['remnants_input'] for r in rows)} against the unrefined output "
            f"({100 * sum(r['remnants_input'] for r in rows) / max(1, sum(r['must_blur_input'] for r in rows)):.3f} % "
            f"of the must-blur pixels); against the true-disparity render "
            f"{sum(r['remnants_true'] for r in rows)} with the default refinement, "
            f"{sum(r['remnants_true_off'] for r in rows)} with it off.")
    c = result.get("refine_cost")
    if c:
        heads.append(f"guided refinement at {c['width']}x{c['height']}: {c['refine_cpu_s']:.2f} "
                     f"CPU s against {c['rest_cpu_s']:.2f} CPU s for the rest of the default "
                     f"pipeline (ratio {c['ratio']:.2f}, one process).")
    return {"headlines": heads, "tables": tables}


def _markdown(result) -> str:
    from mpib_validate.bench.refocus import _fmt

    m = result["machine"]
    lines = ["# Refocusing from colour + predicted-looking disparity", "",
             f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} cores; "
             f"Python {m['python']}. {'Quick' if result['quick'] else 'Full'} mode: "
             f"{result['size']}x{result['size']} card scenes (the refocus suite's); reference = "
             f"ray tracer at {result['reference_spp']} samples; inputs = its all-in-focus image "
             f"and its disparity, exact or degraded (blur 2 px, 4x down + bilinear up, 2 % "
             f"multiplicative noise per low-resolution pixel, 1.5 px shift; seeded per scene). "
             f"Boundary mask from the true disparity.", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    for family, t in result["summary"]["tables"].items():
        lines += [f"## {family} disparity", "",
                  "| method | CPU s | PSNR | PSNR_ob | SSIM | SSIM_ob |",
                  "|---|---|---|---|---|---|"]
        for r in t:
            lines.append(f"| {r['method']} | {_fmt(r['cpu_seconds'], 3)} | {_fmt(r['psnr'])} | "
                         f"{_fmt(r['psnr_ob'])} | {_fmt(r['ssim'], 4)} | {_fmt(r['ssim_ob'], 4)} |")
        lines.append("")
    if result.get("remnants"):
        from mpib_validate.bench import remnants as _remnants

        lines += _remnants.markdown(result["remnants"])
    fig = result.get("figure")
    if fig:
        lines += ["## A real photograph (not scored)", "",
                  f"Middlebury motorcycle (scikit-image), {fig['width']}x{fig['height']}, "
                  f"A = {fig['A']:.1f} px, default preset. Top: focus near, then far; columns: "
                  "input, exact stereo disparity, the same disparity degraded, degraded + guided "
                  f"refinement. Below: {fig['crop_px']} px crops (x2) at the two strongest "
                  "disparity edges, each with the same four columns (rows: near focus, far).", "",
                  f"![photos]({fig['path']})", ""]
    return "\n".join(lines) + "\n"
