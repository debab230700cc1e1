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

Each row also has the re-scoped PSNR_ob of issue #28 (:func:`scope_scores`: the boundary
mask less the HDR highlights and the structures under 3 px wide whose depth no predicted
map holds, :func:`mpib_validate.metrics.degraded_scope_exclusion`) and the sharp
remnants against the tracer (:func:`mpib_validate.metrics.sharp_remnants` where the
exact disparity blurs by more than 6 px); the page states the two re-scoped targets
(within 3 dB of exact depth, 4 dB over the Defocus node fed the same map) per family,
met or missed, with the failing scenes, and the remnant counts with the worst scene.

Also: the refinement's CPU time at 2000x1333 against the rest of the default pipeline
(one process, ``time.process_time``: all threads' CPU time, so a ratio that holds on a
loaded machine), and the Middlebury motorcycle (scikit-image) refocused near and far
with exact and with degraded disparity, with boundary crops beside the input.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import numpy as np

from mpib_validate import metrics
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
#: some channel, grown by this many pixels (its anti-aliased rim); the re-scoped targets'
#: exclusion (:func:`mpib_validate.metrics.degraded_scope_exclusion`) starts from the same.
HIGHLIGHT_GROW_PX = metrics.HIGHLIGHT_GROW_PX


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


#: The re-scoped degraded-depth targets (issue #28), on PSNR_ob outside
#: :func:`mpib_validate.metrics.degraded_scope_exclusion`: the default preset with the
#: guided refinement, fed the degraded map, within ``SCOPE_WITHIN_DB`` of its own
#: exact-depth score, and at least ``SCOPE_OVER_NODE_DB`` above the Defocus node fed the
#: same map.
SCOPE_WITHIN_DB = 3.0
SCOPE_OVER_NODE_DB = 4.0


def scope_scores(truth, out, mask, exclusion, disparity, A: float, d_f: float,
                 maps=None, unrefined=None) -> dict:
    """The re-scoped figures of one output against the truth (both linear RGB):

    - ``psnr_ob_scoped``: PSNR (dB, colour clipped to [0, 1]) over ``mask & ~exclusion``
      (the boundary mask less :func:`metrics.degraded_scope_exclusion`), and
      ``scoped_fraction``, the share of the boundary mask's pixels that it keeps;
    - ``remnants``, ``must_blur``: :func:`metrics.sharp_remnants` of the output against
      the truth where the exact ``disparity`` blurs by more than 6 px (both
      sRGB-encoded, the display values its thresholds are in), and
      ``must_blur_smooth``: the must-blur pixels where the truth itself is smooth
      (3x3 top-hat below :data:`metrics.REMNANT_SMOOTH`), the only ones that can count:
      a truth's Monte Carlo noise hides the rest;
    - ``edges``: :func:`metrics.sharp_edges`, steps inside the same region that the
      truth does not have within a pixel;
    - with ``maps`` (the degraded input map and its refinement, :func:`refined_input`):
      ``remnants_maps`` and ``must_blur_maps``, the remnants against the truth where both
      maps blur by more than 6 px (the photographs' region: lines drawn into a blur that
      the user's map asks for), and with ``unrefined`` (the output of the same input
      with the refinement off, linear RGB) ``remnants_maps_off``, against that output
      in the same region (the photographs' measure, which needs no truth)."""
    from mpib_validate.runtime.io.preview import srgb_encode

    t = np.clip(np.asarray(truth, np.float64)[..., :3], 0, 1)
    o = np.clip(np.asarray(out, np.float64)[..., :3], 0, 1)
    keep = mask & ~exclusion
    te, oe = srgb_encode(t), srgb_encode(o)
    rem, must = metrics.sharp_remnants(oe, te, disparity, A, d_f)
    smooth = must & (metrics.thin_structure(te) < metrics.REMNANT_SMOOTH)
    edges, _ = metrics.sharp_edges(oe, te, disparity, A, d_f)
    out = {"edges": int(edges.sum()), "psnr_ob_scoped": metrics.psnr(t, o, keep),
           "scoped_fraction": float(keep.sum() / max(1, int(mask.sum()))),
           "remnants": int(rem.sum()), "must_blur": int(must.sum()),
           "must_blur_smooth": int(smooth.sum())}
    if maps is not None:
        rem_m, must_m = metrics.sharp_remnants(oe, te, maps, A, d_f)
        out.update(remnants_maps=int(rem_m.sum()), must_blur_maps=int(must_m.sum()))
        if unrefined is not None:
            ue = srgb_encode(np.clip(np.asarray(unrefined, np.float64)[..., :3], 0, 1))
            out["remnants_maps_off"] = int(metrics.sharp_remnants(oe, ue, maps, A, d_f)[0].sum())
    return out


def refined_input(colour, degraded, A: float) -> np.ndarray:
    """The map that the default (``refine="guided"``) builds its layers from when fed
    ``degraded``: :func:`mpib_validate.runtime.layers.refine.refine_disparity` with its
    defaults, as :func:`mpib_validate.runtime.layers.passes.layers_from_passes` calls it."""
    from mpib_validate.runtime.layers.refine import refine_disparity

    return refine_disparity(np.asarray(colour)[..., :3], degraded, A)


def scope_summary(rows, label: str, exact: str, guided: str, node: str) -> dict:
    """The re-scoped targets over ``rows`` (one per scene and method, with
    :func:`scope_scores`' keys): the mean PSNR_ob, masked and unmasked, of the ``exact``,
    ``guided`` and ``node`` methods over the scenes that have all three, the two margins,
    whether each target is met on the mean, the scenes where it fails, and a headline."""
    by = {}
    for r in rows:
        by.setdefault(r["scene"], {})[r["method"]] = r
    scenes = [s for s, g in by.items() if exact in g and guided in g and node in g]
    if not scenes:
        return {}
    out = {"label": label, "scenes": len(scenes), "methods": [exact, guided, node]}
    for key, col in (("psnr_ob_scoped", "scoped"), ("psnr_ob", "unmasked")):
        e, g, n = (np.array([by[s][m][key] for s in scenes]) for m in (exact, guided, node))
        ok = np.isfinite(e) & np.isfinite(g) & np.isfinite(n)
        within, over = g - e, g - n
        out[col] = {"exact": float(np.mean(e[ok])), "guided": float(np.mean(g[ok])),
                    "node": float(np.mean(n[ok])), "n": int(ok.sum()),
                    "within": float(np.mean(within[ok])), "over_node": float(np.mean(over[ok])),
                    "within_met": bool(np.mean(within[ok]) >= -SCOPE_WITHIN_DB),
                    "over_node_met": bool(np.mean(over[ok]) >= SCOPE_OVER_NODE_DB),
                    "within_fails": {s: float(v) for s, v, k in zip(scenes, within, ok)
                                     if k and v < -SCOPE_WITHIN_DB},
                    "over_node_fails": {s: float(v) for s, v, k in zip(scenes, over, ok)
                                        if k and v < SCOPE_OVER_NODE_DB}}
    out["kept"] = float(np.mean([by[s][guided].get("scoped_fraction", math.nan)
                                 for s in scenes]))

    def verdict(c, what):
        met = c[f"{what}_met"]
        fails = c[f"{what}_fails"]
        s = "met" if met else "missed"
        if fails:
            s += "; fails on " + ", ".join(f"{k} {v:+.1f}" for k, v in
                                           sorted(fails.items(), key=lambda kv: kv[1]))
        return s

    sc, un = out["scoped"], out["unmasked"]
    out["headline"] = (
        f"{label}, re-scoped targets (PSNR_ob outside HDR highlights and structures under "
        f"{metrics.SCOPE_THIN_PX} px wide, grown by their blur; {out['kept']:.0%} of the "
        f"boundary mask kept on average, {sc['n']} scenes): the default with the guided "
        f"refinement on the degraded map {sc['guided']:.1f} dB against {sc['exact']:.1f} "
        f"dB from exact depth ({sc['within']:+.1f} dB; within {SCOPE_WITHIN_DB:g} dB: "
        f"{verdict(sc, 'within')}) and {sc['node']:.1f} dB for the "
        f"Defocus node on the same map ({sc['over_node']:+.1f} dB; >= "
        f"{SCOPE_OVER_NODE_DB:g} dB: {verdict(sc, 'over_node')}). "
        f"Unmasked: {un['guided']:.1f} against {un['exact']:.1f} ({un['within']:+.1f} dB, "
        f"{'met' if un['within_met'] else 'missed'}) and {un['node']:.1f} "
        f"({un['over_node']:+.1f} dB, {'met' if un['over_node_met'] else 'missed'}).")
    return out


def remnant_summary(rows, label: str, methods, guided: str | None = None,
                    control: str | None = None) -> dict:
    """Sharp remnants against the truth (:func:`scope_scores`' ``remnants``) summed over
    the scenes per method of ``methods``: the count, the must-blur pixels, their share,
    the worst scene (most remnants), those in the photographs' region where the rows
    have them, and a headline; it gives the target's verdict there for the ``guided``
    method (the refined default), beside the exact-depth ``control``."""
    out = {"label": label, "methods": {}}
    for m in methods:
        rs = [r for r in rows if r["method"] == m and "remnants" in r]
        if not rs:
            continue
        worst = max(rs, key=lambda r: (r["remnants"], r["remnants"] / max(1, r["must_blur"])))
        n, must = sum(r["remnants"] for r in rs), sum(r["must_blur"] for r in rs)
        out["methods"][m] = {"remnants": n, "must_blur": must,
                             "must_blur_smooth": sum(r["must_blur_smooth"] for r in rs),
                             "edges": sum(r.get("edges", 0) for r in rs),
                             "percent": 100.0 * n / max(1, must), "scenes": len(rs),
                             "worst": worst["scene"], "worst_remnants": worst["remnants"],
                             "worst_percent": 100.0 * worst["remnants"] / max(1, worst["must_blur"])}
        for key in ("remnants_maps", "must_blur_maps", "remnants_maps_off"):
            if all(key in r for r in rs):
                out["methods"][m][key] = sum(r[key] for r in rs)
        if all("remnants_maps_off" in r for r in rs):
            w = max(rs, key=lambda r: (r["remnants_maps_off"],
                                       r["remnants_maps_off"] / max(1, r["must_blur_maps"])))
            out["methods"][m]["worst_maps_off"] = (w["scene"], w["remnants_maps_off"],
                                                   w["must_blur_maps"])
    if out["methods"]:
        out["headline"] = (f"{label}, sharp remnants against the truth where the exact "
                           f"disparity blurs by more than {metrics.REMNANT_BLUR_PX:g} px: " +
                           "; ".join(f"{m} {v['remnants']} ({v['percent']:.3f} % of "
                                     f"{v['must_blur']}; worst {v['worst']} "
                                     f"{v['worst_remnants']}, {v['worst_percent']:.3f} %; "
                                     f"sharp edges {v['edges']})"
                                     for m, v in out["methods"].items()) + "."
                           + _maps_clause(out["methods"], guided, control))
    return out


def _maps_clause(methods: dict, guided, control) -> str:
    """The headline's clause for the photographs' region (where the degraded map and its
    refinement both blur), with the target's verdict on the ``guided`` method."""
    v = methods.get(guided, {})
    if "remnants_maps" not in v:
        return ""
    of = max(1, v["must_blur_maps"])
    s = (f" Where the degraded map and its refinement both blur (the photographs' region, "
         f"{v['must_blur_maps']} px), {guided}: {v['remnants_maps']} "
         f"({100 * v['remnants_maps'] / of:.3f} %) against the truth")
    if "remnants_maps_off" in v:
        met = v["remnants_maps_off"] <= REMNANT_TARGET * v["must_blur_maps"]
        scene, n, must = v["worst_maps_off"]
        s += (f", {v['remnants_maps_off']} ({100 * v['remnants_maps_off'] / of:.3f} %) "
              f"against the unrefined output (target {100 * REMNANT_TARGET:g} % over the "
              f"suite: {'met' if met else 'missed'}; most in {scene}, {n} of {must} px)")
    ctl = methods.get(control, {})
    if "remnants_maps" in ctl:
        s += f"; the exact-depth control {ctl['remnants_maps']} against the truth there"
    return s + "."


def scope_markdown(scope: dict, rem: dict, rows, methods) -> list[str]:
    """The re-scoped table (per scene and mean: masked and unmasked PSNR_ob of the
    targets' three methods, the kept share of the mask) and the remnant table (per
    method: count, share, worst scene)."""
    lines = []
    if scope:
        sc, un = scope["scoped"], scope["unmasked"]
        by = {}
        for r in rows:
            by.setdefault(r["scene"], {})[r["method"]] = r
        ex, gd, nd = scope["methods"]
        lines += [f"### {scope['label']}: re-scoped degraded-depth targets", "",
                  f"PSNR_ob (dB) outside HDR highlights and structures under "
                  f"{metrics.SCOPE_THIN_PX} px wide in the exact disparity, each grown by the "
                  "largest blur radius around it (`metrics.degraded_scope_exclusion`), beside "
                  "the unmasked PSNR_ob. Targets: guided - exact >= "
                  f"-{SCOPE_WITHIN_DB:g} dB, guided - node >= {SCOPE_OVER_NODE_DB:g} dB.", "",
                  "| scene | mask kept | exact | degraded + guided | Defocus node, degraded "
                  "| guided - exact | guided - node | exact (unmasked) | guided (unmasked) "
                  "| node (unmasked) | guided - exact (unmasked) | guided - node (unmasked) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for s, g in by.items():
            if not all(m in g for m in (ex, gd, nd)):
                continue
            e, q, n = g[ex], g[gd], g[nd]
            lines.append(
                f"| {s} | {q['scoped_fraction']:.0%} | {_f(e['psnr_ob_scoped'])} | "
                f"{_f(q['psnr_ob_scoped'])} | {_f(n['psnr_ob_scoped'])} | "
                f"{_d(q['psnr_ob_scoped'] - e['psnr_ob_scoped'])} | "
                f"{_d(q['psnr_ob_scoped'] - n['psnr_ob_scoped'])} | {_f(e['psnr_ob'])} | "
                f"{_f(q['psnr_ob'])} | {_f(n['psnr_ob'])} | {_d(q['psnr_ob'] - e['psnr_ob'])} | "
                f"{_d(q['psnr_ob'] - n['psnr_ob'])} |")
        lines.append(
            f"| **mean** | {scope['kept']:.0%} | {_f(sc['exact'])} | {_f(sc['guided'])} | "
            f"{_f(sc['node'])} | **{_d(sc['within'])}** "
            f"({'met' if sc['within_met'] else 'missed'}) | **{_d(sc['over_node'])}** "
            f"({'met' if sc['over_node_met'] else 'missed'}) | {_f(un['exact'])} | "
            f"{_f(un['guided'])} | {_f(un['node'])} | {_d(un['within'])} | "
            f"{_d(un['over_node'])} |")
        lines.append("")
    if rem and rem.get("methods"):
        lines += [f"### {rem['label']}: sharp remnants against the truth", "",
                  "`metrics.sharp_remnants` of each output against the reference's depth of "
                  f"field where the exact disparity blurs the whole 5x5 window by more than "
                  f"{metrics.REMNANT_BLUR_PX:g} px (sRGB display values); 'smooth' is how many of "
                  "those pixels the truth itself holds smooth enough to count (its noise "
                  "hides the others). The exact-depth rows are the control. Sharp edges: "
                  "`metrics.sharp_edges`, steps in the same region that the truth does not "
                  "have within a pixel. The last three columns count in the photographs' "
                  "region instead: where the degraded map and its refinement (the default's "
                  "layers' map) both blur by more than "
                  f"{metrics.REMNANT_BLUR_PX:g} px, against the truth and against the "
                  "unrefined output (the photographs' measure).", "",
                  "| method | remnants | must-blur | smooth in the truth | share | worst scene "
                  "| sharp edges | where both maps blur: must-blur | remnants vs truth "
                  "| remnants vs unrefined |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for m, v in rem["methods"].items():
            lines.append(f"| {m} | {v['remnants']} | {v['must_blur']} | {v['must_blur_smooth']} | "
                         f"{v['percent']:.3f} % | {v['worst']} ({v['worst_remnants']}, "
                         f"{v['worst_percent']:.3f} %) | {v.get('edges', '-')} | "
                         f"{v.get('must_blur_maps', '-')} | {v.get('remnants_maps', '-')} | "
                         f"{v.get('remnants_maps_off', '-')} |")
        lines.append("")
    return lines


def _f(v):
    return "-" if v is None or not math.isfinite(v) else f"{v:.2f}"


def _d(v):
    return "-" if v is None or not math.isfinite(v) else f"{v:+.2f}"


def scene_rows(scene, label, family, seed, ref_spp, only=None) -> list[dict]:
    """One row per method: PSNR, PSNR_ob, SSIM, SSIM_ob against the ray tracer at
    ``ref_spp`` samples, the re-scoped PSNR_ob and the sharp remnants against it
    (:func:`scope_scores`), and the method's time (CPU seconds of this process; the
    Defocus node's is Blender's whole render op, not comparable)."""
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.cards.evaluate import card_scene_mask, score

    from mpib_validate.runtime.layers.passes import depth_to_disparity

    res = trace.render(scene, samples.stratified(ref_spp, seed=11), notices=False)
    mask = card_scene_mask(scene)
    cam = scene.camera
    exact = depth_to_disparity(res.depth)
    excl = metrics.degraded_scope_exclusion(res.all_in_focus, exact, cam.blur_parameter,
                                            cam.focus_disparity)
    outputs = {}
    for name, fn in _methods(scene, res, seed).items():
        if only is not None and name not in only:
            continue
        t0 = time.process_time()
        out = fn()
        seconds = time.process_time() - t0
        if isinstance(out, tuple):
            out = out[0]
            seconds = math.nan
        outputs[name] = (out, seconds)
    # the photographs' region: where the degraded map and its refinement both blur
    degraded = degraded_input(exact, seed)
    maps = (degraded, refined_input(res.all_in_focus, degraded, cam.blur_parameter))
    unrefined = outputs.get(UNREFINED, (None,))[0]
    return [{"scene": label, "family": family, "method": name, "cpu_seconds": seconds,
             **score(res.bokeh, out, mask, with_flip=False),
             **scope_scores(res.bokeh, out, mask, excl, exact, cam.blur_parameter,
                            cam.focus_disparity, maps,
                            unrefined if name in VS_UNREFINED else None)}
            for name, (out, seconds) in outputs.items()]


def _scene_task(item) -> list[dict]:
    from mpib_validate.cards.generate import GeneratorSettings, generate

    seed, family, size, ref_spp = item
    print(f"bench photos: {family}-{seed} ({size}x{size}) ...", flush=True)
    scene = generate(seed, family, settings=GeneratorSettings(width=size, height=size))
    return scene_rows(scene, f"{family}-{seed}", family, seed, ref_spp)


#: The size of the issue's photograph (a 2000x1333 portrait), at which the refinement's
#: cost target is set (1.5 s on 2 cores).
COST_SIZE = (2000, 1333)
#: The refinement's cost target at :data:`COST_SIZE` (seconds on 2 cores, issue #28).
REFINE_TARGET_S = 1.5
#: The issue's remnant target: at most this share of the must-blur pixels per photograph
#: and focus (issue #28: 0.02 %, 200 pixels per megapixel that must blur).
REMNANT_TARGET = 2e-4
#: Light patches in blurred hair (``remnants.light_patches``): at most this share of the
#: head's inside visibly (10 display levels) lighter than the unrefined output, which
#: has no hidden background behind the hair. What the check leaves is within about a
#: blur radius of the outline, where the refined edge is not the unrefined one (0.24 %).
PATCH_TARGET = 0.01


def cost_scene(width: int, height: int):
    """The refocus suite's 'varying' scene 0 at ``width x height``, ``A`` set so the
    largest blur radius is 60 px (as :func:`mpib_validate.bench.compositor.hd_scene`)."""
    from mpib_validate.cards.generate import GeneratorSettings, generate

    scene = generate(0, "varying", settings=GeneratorSettings(width=width, height=height))
    lo, hi = scene.disparity_range()
    df = scene.camera.focus_disparity
    return scene.with_camera(blur_parameter=60.0 / max(abs(hi - df), abs(lo - df)))


def refine_cost(size=COST_SIZE) -> dict:
    """CPU seconds (``time.process_time``, one run, this process: all threads' CPU time,
    which no other process's load adds to) of the guided refinement and of the rest of
    the default pipeline (layers + Eq. 1) on :func:`cost_scene` at ``size`` with its
    degraded disparity; ``refocus_cpu_s`` is their sum, the whole refocus of a
    photograph. Wall seconds are recorded too, valid only on an idle machine."""
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.runtime.compositor.composite import render_subapertures
    from mpib_validate.runtime.layers.passes import depth_to_disparity, layers_from_passes
    from mpib_validate.runtime.layers.refine import refine_disparity
    from mpib_validate.runtime.cores import available_cores
    from mpib_validate.runtime.presets import PRESETS

    scene = cost_scene(*size)
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
    t_photo, w_photo = photo_refine_seconds(size)
    return {"width": cam.width, "height": cam.height, "refine_cpu_s": t_ref, "rest_cpu_s": t_rest,
            "refocus_cpu_s": t_ref + t_rest, "ratio": t_ref / t_rest,
            "refine_wall_s": w_ref, "rest_wall_s": w_rest, "refine_photo_cpu_s": t_photo,
            "refine_photo_wall_s": w_photo, "cores": available_cores(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}


def photo_refine_seconds(size=COST_SIZE) -> tuple[float, float]:
    """CPU and wall seconds of the guided refinement on a busy photograph at ``size``: the
    Middlebury motorcycle (edges over most of the frame) resized bicubically, its
    disparity (nearest) through :func:`mpib_validate.bench.remnants.network_disparity`,
    ``K`` = 6 % of the width. The card scene of :func:`refine_cost` has fewer edges; a
    photograph's cost grows with the pixels near its disparity edges."""
    from PIL import Image

    from mpib_validate.bench import remnants
    from mpib_validate.runtime.layers.refine import refine_disparity

    img, Dt = remnants.true_disparity("motorcycle")
    w, h = size
    rgb = np.asarray(Image.fromarray(img).resize((w, h), Image.BICUBIC), np.float64)
    D = np.asarray(Image.fromarray(Dt.astype(np.float32)).resize((w, h), Image.NEAREST),
                   np.float64)
    N = remnants.network_disparity(D)
    lin = (rgb / 255.0) ** remnants.GAMMA
    t0, w0 = time.process_time(), time.perf_counter()
    refine_disparity(lin, N, remnants.K_FRACTION * w)
    return time.process_time() - t0, time.perf_counter() - w0


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
    from mpib_validate.runtime.layers.passes import layers_from_passes
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
        print(f"bench photos: refinement cost at {COST_SIZE[0]}x{COST_SIZE[1]} ...", flush=True)
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


KEYS = ("cpu_seconds", "psnr", "psnr_ob", "ssim", "ssim_ob", "psnr_ob_scoped", "scoped_fraction")
#: The re-scoped targets' methods on the cards: exact depth, the default for a predicted
#: map (guided), the Defocus node fed the same map.
SCOPE_METHODS = ("default exact (bound)", "default degraded + guided", "defocus-node degraded")
#: The default on the degraded map with the refinement off: the photographs' remnant
#: measure compares the refined outputs with it.
UNREFINED = "default degraded"
#: The rows compared with :data:`UNREFINED` in the photographs' region: those fed the
#: same degraded map through the same (default) preset, or Blender's node.
VS_UNREFINED = ("default degraded + guided", "default degraded + guided-thin",
                "defocus-node degraded")
#: The rows whose sharp remnants the card table gives (exact depth: the control).
REMNANT_METHODS = ("default exact (bound)", "default degraded", "default degraded + guided",
                   "default degraded + guided-thin", "defocus-node degraded",
                   "defocus-node exact")


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
    scope, rems = {}, {}
    for family in ("constant", "varying"):
        frows = [r for r in result["rows"] if r["family"] == family]
        sc = scope_summary(frows, f"{family} cards", *SCOPE_METHODS[:3])
        rm = remnant_summary(frows, f"{family} cards", REMNANT_METHODS,
                             SCOPE_METHODS[1], SCOPE_METHODS[0])
        if sc:
            scope[family] = sc
            heads.append(sc["headline"])
        if rm.get("methods"):
            rems[family] = rm
            heads.append(rm["headline"])
    rem = result.get("remnants")
    if rem:
        rows = rem["rows"]

        def summed(key, must):
            n, of = sum(r[key] for r in rows), sum(r[must] for r in rows)
            worst = max(rows, key=lambda r: r[key] / max(1, r[must]))
            w = 100 * worst[key] / max(1, worst[must])
            return (f"{n} ({100 * n / max(1, of):.3f} % of the must-blur pixels; worst "
                    f"{worst['photo']} {worst['focus']} {w:.3f} %, target "
                    f"{100 * REMNANT_TARGET:g} % per row "
                    f"{'met' if all(r[key] <= REMNANT_TARGET * r[must] for r in rows) else 'missed'})")

        heads.append(
            f"sharp remnants on {len({r['photo'] for r in rows})} scikit-image photographs with "
            f"network-like disparity (near and far focus), default refinement: against the "
            f"unrefined output where the input and the refined map both blur "
            f"{summed('remnants_both', 'must_blur_both')}, where the input map blurs "
            f"{summed('remnants_input', 'must_blur_input')}; against the true-disparity "
            f"render {summed('remnants_true', 'must_blur_true')}, refinement off "
            f"{sum(r['remnants_true_off'] for r in rows)}; sharp edges inside the blur "
            f"(steps the reference does not have) {sum(r.get('edges_both', 0) for r in rows)} "
            f"against the unrefined output, {sum(r.get('edges_true', 0) for r in rows)} "
            f"against the truth (refinement off "
            f"{sum(r.get('edges_true_off', 0) for r in rows)}).")
        if all("psnr_overshoot" in r for r in rows):
            from mpib_validate.bench.remnants import OVERSHOOT_PX

            heads.append(
                f"with --map-overshoot {OVERSHOOT_PX} (the map's near side shrunk "
                f"first; these maps overshoot by 2 px): sharp remnants against the "
                f"true-disparity render {sum(r['remnants_true_overshoot'] for r in rows)} "
                f"(default {sum(r['remnants_true'] for r in rows)}), mean PSNR "
                f"{np.mean([r['psnr_overshoot'] for r in rows]):.2f} dB (default "
                f"{np.mean([r['psnr_guided'] for r in rows]):.2f} dB).")
        lp = rem.get("light_patches")
        if lp:
            heads.append(
                f"light patches in blurred hair (the astronaut's map at {lp['map_px']} px, "
                f"K = {lp['K']:g}, focus {255 * lp['disp_focus']:.0f}/255): "
                f"{100 * lp['share']:.2f} % of the head's inside more than {lp['levels']} "
                f"display levels lighter than with the refinement off (target "
                f"{100 * PATCH_TARGET:g} %: {'met' if lp['share'] <= PATCH_TARGET else 'missed'}"
                f"), {lp['max_levels']:.0f} levels at most.")
    c = result.get("refine_cost")
    if c:
        heads.append(f"guided refinement at {c['width']}x{c['height']}: {c['refine_cpu_s']:.2f} "
                     f"CPU s (target {REFINE_TARGET_S:g} s: "
                     f"{'met' if c['refine_cpu_s'] <= REFINE_TARGET_S else 'missed'}) of "
                     f"{c.get('refocus_cpu_s', c['refine_cpu_s'] + c['rest_cpu_s']):.2f} CPU s "
                     f"for the whole default refocus ({c['rest_cpu_s']:.2f} for the rest; "
                     f"ratio {c['ratio']:.2f}, one process)"
                     + (f"; on a busy photograph (the motorcycle at that size) "
                        f"{c['refine_photo_cpu_s']:.2f} CPU s, "
                        f"{c['refine_photo_wall_s']:.2f} s wall on {c['cores']} cores ("
                        f"{'met' if c['refine_photo_wall_s'] <= REFINE_TARGET_S else 'missed'}"
                        f" at load {(c.get('load_average') or [float('nan')])[0]:.1f}: "
                        f"wall time holds only on an idle machine)"
                        if "refine_photo_wall_s" in c else "") + ".")
    return {"headlines": heads, "tables": tables, "scope": scope, "card_remnants": rems}


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
                  "| method | CPU s | PSNR | PSNR_ob | PSNR_ob re-scoped | SSIM | SSIM_ob |",
                  "|---|---|---|---|---|---|---|"]
        for r in t:
            lines.append(f"| {r['method']} | {_fmt(r['cpu_seconds'], 3)} | {_fmt(r['psnr'])} | "
                         f"{_fmt(r['psnr_ob'])} | {_fmt(r['psnr_ob_scoped'])} | "
                         f"{_fmt(r['ssim'], 4)} | {_fmt(r['ssim_ob'], 4)} |")
        lines.append("")
    scope = result["summary"].get("scope", {})
    crem = result["summary"].get("card_remnants", {})
    if scope or crem:
        lines += ["## Re-scoped degraded-depth targets and sharp remnants (cards)", ""]
        for family in ("constant", "varying"):
            frows = [r for r in result["rows"] if r["family"] == family]
            lines += scope_markdown(scope.get(family, {}), crem.get(family, {}), frows,
                                    REMNANT_METHODS)
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
