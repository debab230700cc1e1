"""Benchmark of the MPI compositor against the ray tracer, on generated card scenes.

For each scene (both families) the reference is the Eq. 15 ray tracer with a large
Sobol sample set; its own noise is measured against a second, independent sample set.
Every method renders *exact layers* taken from the cards (so only the compositor's own
error is measured) and is scored with PSNR, PSNR_ob, SSIM, SSIM_ob and FLIP.

A second part times Eq. 1 at 1920x1080 with 32 planes and a largest radius of 60 px,
beside a direct per-plane convolution in the official manner (full-frame planes, the
official soft-disk kernels at integer radii, replication padding), in the same run.
Direct convolution costs exactly the same per output pixel everywhere, so in quick
mode it is timed on a full-width strip of rows and the frame's time extrapolated at the
same cost per row (the page says so); full mode times the whole frame. That row is
numpy's arithmetic, not the official renderer (``--suite official`` times the official
computation).
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from mpib_validate.bench.machine import (finish, machine_info, mean_table, peak_python_mb, peak_rss_mb, run_worker, worker_main)

STRIP_ROWS = 48


def _methods():
    from mpib_validate.runtime.layers import mpi as M
    from mpib_validate.cards import mpi as CM
    from mpib_validate.runtime.compositor.composite import PLAIN, CompositeSettings

    fast = CompositeSettings()
    return {
        # name: (planes, kind, settings, extra)
        "eq1-adaptive": ("adaptive", "eq1", fast, None),
        "eq1-uniform32": ("uniform32", "eq1", fast, None),
        "eq1-official-soft-int": ("uniform32", "eq1", CompositeSettings(kernel="soft"), None),
        "middle-k2": ("adaptive", "middle", fast, 2),
        "middle-k3": ("adaptive", "middle", fast, 3),
        "middle-k4": ("adaptive", "middle", fast, 4),
        "exact-256spp": ("adaptive", "exact", None, 256),
        "exact-1024spp": ("adaptive", "exact", None, 1024),
        # fast paths against the plain path (same layers, same kernels)
        "path-plain": ("adaptive", "eq1", PLAIN, None),
        "path-fft": ("adaptive", "eq1", CompositeSettings(conv="fft", crop=False), None),
        "path-crop": ("adaptive", "eq1", CompositeSettings(conv="direct", crop=True), None),
        "path-auto+crop": ("adaptive", "eq1", fast, None),
        "path-reduced16": ("adaptive", "eq1", CompositeSettings(reduce_above=16.0), None),
        "path-reduced8": ("adaptive", "eq1", CompositeSettings(reduce_above=8.0), None),
        "path-drjit-llvm": ("adaptive", "eq1", CompositeSettings(backend="llvm"), None),
    }, M


def _time(fn, repeats: int):
    fn()  # warm-up (kernel caches, JIT)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def _scene_rows(scene, label: str, family: str, ref_spp: int, repeats: int) -> list[dict]:
    from mpib_validate.runtime.compositor import composite as C
    from mpib_validate.runtime import samples
    from mpib_validate.cards import mpi as CM
    from mpib_validate.cards import trace
    from mpib_validate.cards.evaluate import card_scene_mask, score

    methods, M = _methods()
    cam = scene.camera
    ref, _ = trace.trace(scene, samples.stratified(ref_spp, seed=101), notices=False)
    ref2, _ = trace.trace(scene, samples.stratified(ref_spp, seed=202), notices=False)
    mask = card_scene_mask(scene)
    noise = score(ref, ref2, mask, with_flip=False)
    layers = {
        "adaptive": CM.layers_from_cards(scene),
        "uniform32": CM.layers_from_cards(scene, planes=M.uniform_planes(32, max(
            1.0, scene.disparity_range()[1] * 1.0001))),
    }
    rows = [{"scene": label, "family": family, "method": "reference-noise (two sample sets)",
             "seconds": math.nan, "planes": 0, **noise}]
    from mpib_validate.runtime.compositor.backend import resolve

    for name, (planes, kind, settings, extra) in methods.items():
        if settings is not None and settings.backend != "numpy" \
                and resolve(settings.backend).name != settings.backend:
            continue  # that backend does not run here; the report shows no row for it
        mpi = layers[planes]
        if kind == "eq1":
            fn = lambda: C.composite(mpi, cam.blur_parameter, cam.focus_disparity, settings)
        elif kind == "middle":
            fn = lambda: C.render_subapertures(mpi, cam.blur_parameter, cam.focus_disparity,
                                               extra, settings)
        else:
            fn = lambda: CM.render_exact(mpi, cam, samples.stratified(extra, seed=7))
        reps = 1 if name in ("path-plain", "path-crop") or kind == "exact" else repeats
        out, seconds = _time(fn, reps)
        rows.append({"scene": label, "family": family, "method": name, "seconds": seconds,
                     "peak_mb": peak_python_mb(fn) if kind != "exact" else math.nan,
                     "planes": len(mpi.layers), **score(ref, out, mask)})
    rows += _renderer_rows(scene, label, family, ref, mask)
    plain = next(r for r in rows if r["method"] == "path-plain")
    for r in rows:
        if r["method"].startswith("path-"):
            r["delta_psnr_vs_plain"] = r["psnr"] - plain["psnr"]
    return rows


def _renderer_rows(scene, label, family, ref, mask, spps=(16, 64, 256)) -> list[dict]:
    """What rendering depth of field directly costs: the ray tracer (its Dr.Jit and numpy
    backends), Mitsuba and Cycles at a sweep of sample counts, scored like the methods."""
    import importlib.util

    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.runtime.compositor.backend import resolve
    from mpib_validate.cards.evaluate import score

    rows = []
    engines = [("trace-numpy", None)]
    if resolve("llvm").name == "llvm":
        engines.insert(0, ("trace-llvm", None))
    if importlib.util.find_spec("mitsuba") is not None:
        engines.append(("mitsuba", None))
    if importlib.util.find_spec("bpy") is not None:
        engines.append(("cycles", None))
    for name, _ in engines:
        for spp in spps:
            if name == "trace-numpy" and spp > 64:
                continue  # its time grows linearly; two points show the line
            if name.startswith("trace"):
                img, meta = trace.trace(scene, samples.stratified(spp, seed=5),
                                        backend=name.split("-")[1], notices=False)
                seconds = meta["seconds"]
            elif name == "mitsuba":
                import mitsuba_scenes

                mitsuba_scenes.render(scene, spp, seed=5)  # warm-up (JIT)
                img, meta = mitsuba_scenes.render(scene, spp, seed=5)
                seconds = meta["render_seconds"]
            else:
                from mpib_validate.blender import cycles

                img, _, meta = cycles.render(scene, spp, 5, True, depth=False)
                seconds = meta["seconds"]
            rows.append({"scene": label, "family": family, "method": f"{name}-{spp}spp",
                         "seconds": seconds, "planes": 0, **score(ref, img, mask)})
    return rows


# --------------------------------------------------------------------------------------
# 1920x1080 timing, in a subprocess each (peak memory of its own)


def hd_scene():
    """A generated 'varying' scene at 1920x1080, A set so the largest radius is 60 px."""
    from mpib_validate.cards.generate import GeneratorSettings, generate

    scene = generate(0, "varying", settings=GeneratorSettings(width=1920, height=1080))
    lo, hi = scene.disparity_range()
    df = scene.camera.focus_disparity
    A = 60.0 / max(abs(hi - df), abs(lo - df))
    return scene.with_camera(blur_parameter=A)


def _hd_worker(cfg: dict) -> dict:
    """One 1080p measurement. ``prepare`` builds the scene's 32-plane MPI and saves it, so
    that the timed workers hold only the MPI and the compositor (their peak memory is the
    compositor's, not the scene generator's)."""
    from mpib_validate.cards import mpi as CM
    from mpib_validate.runtime.compositor import composite as C
    from mpib_validate.runtime.layers import mpi as M
    from mpib_validate.runtime.compositor.composite import CompositeSettings
    from mpib_validate.runtime.compositor.kernels import correlate_direct, soft_disk

    if cfg["what"] == "prepare":
        scene = hd_scene()
        mpi = CM.layers_from_cards(scene, planes=M.uniform_planes(
            32, max(1.0, scene.disparity_range()[1])))
        M.save_mpi(mpi, cfg["mpi"])
        cam = scene.camera
        return {"A": cam.blur_parameter, "d_f": cam.focus_disparity, "width": cam.width,
                "height": cam.height, "max_radius": scene.max_blur_radius()}
    mpi = M.load_mpi(cfg["mpi"])
    A, d_f = cfg["A"], cfg["d_f"]
    out = {"planes": len(mpi.layers), "max_radius": cfg["max_radius"],
           "layer_area_frames": sum(l.rgba.shape[0] * l.rgba.shape[1] for l in mpi.layers)
           / (mpi.width * mpi.height)}
    cam = SimpleNamespace(blur_parameter=A, focus_disparity=d_f, width=mpi.width,
                          height=mpi.height)
    if cfg["what"] == "eq1":
        st = CompositeSettings(**cfg.get("settings", {}))
        fn = lambda: C.composite(mpi, A, d_f, st)
        _, out["seconds"] = _time(fn, cfg.get("repeats", 3))
    else:  # the official manner: every plane full frame, soft disk, direct, replicate
        rows = cam.height if cfg["full"] else STRIP_ROWS
        total = 0.0
        for layer in mpi.layers:
            r = int(round(abs(cam.blur_parameter * (layer.disparity - cam.focus_disparity))))
            k = soft_disk(r)
            frame = np.zeros((rows + 2 * r, cam.width + 2 * r, 4), np.float32)
            t0 = time.perf_counter()
            correlate_direct(frame, k)
            total += time.perf_counter() - t0
        out["seconds"] = total * cam.height / rows
        out["measured_rows"] = rows
    out["peak_rss_mb"] = peak_rss_mb()
    return out


def _run_hd(cfg: dict) -> dict:
    return run_worker("mpib_validate.bench.compositor", cfg)


# --------------------------------------------------------------------------------------


def _scene_task(item) -> list[dict]:
    """One scene's rows (a top-level function, so any executor can run it)."""
    from mpib_validate.cards.generate import GeneratorSettings, generate

    seed, family, size, ref_spp, repeats = item
    print(f"bench compositor: {family}-{seed} ({size}x{size}) ...", flush=True)
    scene = generate(seed, family, settings=GeneratorSettings(width=size, height=size))
    return _scene_rows(scene, f"{family}-{seed}", family, ref_spp, repeats)


def run(out: Path, quick: bool = True, executor=None) -> dict:
    from mpib_validate.executor import make_executor
    from mpib_validate.cards.generate import FAMILIES

    out.mkdir(parents=True, exist_ok=True)
    size = 192 if quick else 512
    seeds = range(2) if quick else range(6)
    ref_spp = 2048 if quick else 8192
    items = [(seed, family, size, ref_spp, 1 if quick else 3)
             for family in FAMILIES for seed in seeds]
    rows = [r for part in (executor or make_executor()).map(_scene_task, items) for r in part]
    print("bench compositor: 1920x1080, 32 planes, radius 60 ...", flush=True)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        base = {"mpi": str(Path(tmp) / "hd.npz")}
        prep = _run_hd({**base, "what": "prepare"})
        base.update({k: prep[k] for k in ("A", "d_f", "max_radius")} if "A" in prep else {})
        hd = {"eq1_fast": _run_hd({**base, "what": "eq1", "settings": {}}),
              "eq1_reduced16": _run_hd({**base, "what": "eq1", "settings": {"reduce_above": 16.0}})}
        if not quick:
            hd["eq1_drjit_llvm"] = _run_hd({**base, "what": "eq1", "repeats": 1,
                                            "settings": {"backend": "llvm"}})
        hd["official_direct"] = _run_hd({**base, "what": "official", "full": not quick})
    result = {"suite": "compositor", "quick": quick, "size": size, "reference_spp": ref_spp,
              "machine": machine_info(), "rows": rows, "hd": hd}
    result["summary"] = _summarise(result)
    return finish(out, "compositor", result, _markdown)


def _mean_table(rows, family):
    return mean_table(rows, family, ("seconds", "peak_mb", "planes", "psnr", "psnr_ob", "ssim",
                                     "ssim_ob", "flip", "psnr_hdr", "delta_psnr_vs_plain"))


def _summarise(result) -> dict:
    heads = []
    tables = {}
    for family in ("constant", "varying"):
        t = _mean_table(result["rows"], family)
        tables[family] = t
        get = {r["method"]: r for r in t}
        if "eq1-adaptive" in get and "exact-1024spp" in get and "middle-k2" in get:
            heads.append(
                f"{family}: Eq. 1 with exact layers reaches {get['eq1-adaptive']['psnr']:.1f} dB "
                f"(PSNR_ob {get['eq1-adaptive']['psnr_ob']:.1f}) on {get['eq1-adaptive']['planes']:.1f} "
                f"adaptive planes against {get['eq1-uniform32']['psnr']:.1f} dB "
                f"(PSNR_ob {get['eq1-uniform32']['psnr_ob']:.1f}) on 32 uniform planes; the middle "
                f"setting k=2 {get['middle-k2']['psnr']:.1f} dB, the exact renderer "
                f"{get['exact-1024spp']['psnr']:.1f} dB.")
        match = _cycles_match(get, "eq1-adaptive")
        if match:
            heads.append(f"{family}: {match}")
        worst = [r["delta_psnr_vs_plain"] for r in t
                 if r["method"] in ("path-fft", "path-crop", "path-auto+crop")]
        if worst:
            heads.append(f"{family}: FFT and crop change PSNR by at most "
                         f"{max(abs(w) for w in worst):.4f} dB against the plain path.")
    hd = result["hd"]
    fast, off = hd["eq1_fast"], hd["official_direct"]
    if "seconds" in fast and "seconds" in off:
        heads.append(
            f"At 1920x1080 with 32 planes ({fast['planes']} non-empty) and a largest radius of "
            f"{fast['max_radius']:.0f} px, Eq. 1 with the fast paths takes {fast['seconds']:.2f} s "
            f"(peak {fast['peak_rss_mb']:.0f} MB). The official renderer's own computation "
            f"(CPU torch conv2d) is timed beside it by `mpib bench --suite official`.")
        # numpy's direct correlation is far slower than the official renderer's torch
        # conv2d: this row measures numpy's arithmetic, so it is labelled as such and
        # gives no ratio to Eq. 1
        rows = off.get("measured_rows", 1080)
        how = ("the whole frame" if rows == 1080 else
               f"{rows} rows timed, the frame's 1080 rows extrapolated at the same cost per row")
        heads.append(
            f"Numpy arithmetic, not the official renderer: direct per-plane full-frame "
            f"convolution in the official manner, written in numpy, takes {off['seconds']:.0f} s "
            f"on the same MPI ({how}).")
    return {"headlines": heads, "tables": tables}


def _cycles_match(get: dict, method: str) -> str:
    """How long Cycles would take to reach ``method``'s PSNR: interpolated in log time
    between the sweep's points, or extrapolated past the last one with Monte Carlo's
    1/sqrt(spp) law (6.02 dB per 4x samples, i.e. per 4x time)."""
    sweep = sorted((r["seconds"], r["psnr"], int(m.split("-")[1][:-3])) for m, r in get.items()
                   if m.startswith("cycles-") and m.endswith("spp"))
    if not sweep or method not in get:
        return ""
    target, t_m = get[method]["psnr"], get[method]["seconds"]
    t_c = spp = None
    for (t0, p0, s0), (t1, p1, s1) in zip(sweep, sweep[1:]):
        if p0 <= target <= p1:
            f = (target - p0) / (p1 - p0)
            t_c = math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0)))
            spp = s0 * (s1 / s0) ** f
    if t_c is None and target > sweep[-1][1]:
        t_last, p_last, s_last = sweep[-1]
        k = 4 ** ((target - p_last) / 6.02)
        t_c, spp = t_last * k, s_last * k
    if t_c is None:
        return (f"Cycles' lowest sample count ({sweep[0][2]} spp, {sweep[0][0]:.2f} s) already "
                f"beats {method}'s {target:.1f} dB.")
    return (f"Cycles needs about {spp:.0f} spp ({t_c:.2f} s) to reach the {target:.1f} dB that "
            f"{method} reaches in {t_m:.3f} s: the compositor is {t_c / t_m:.0f}x faster there.")


def _fmt(v, nd=2):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return f"{v:.{nd}f}"


def _markdown(result) -> str:
    m = result["machine"]
    lines = ["# Compositor benchmark (Eq. 1, middle setting, exact renderer)", "",
             f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} cores; "
             f"Python {m['python']}, numpy {m.get('numpy')}, drjit {m.get('drjit', '-')}. "
             f"{'Quick' if result['quick'] else 'Full'} mode: {result['size']}x{result['size']} scenes, "
             f"reference = ray tracer at {result['reference_spp']} Sobol samples.", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    lines += ["Metrics on values clipped to [0, 1] (the paper's convention), against the ray "
              "tracer; time is the median after a warm-up. The first row is the reference's own "
              "noise (two independent sample sets).", ""]
    for family, table in result["summary"]["tables"].items():
        lines += [f"## {family} disparity", "",
                  "| method | planes | time (s) | peak numpy MB | PSNR | PSNR_ob | SSIM | SSIM_ob | FLIP | ΔPSNR vs plain |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in table:
            lines.append(f"| {r['method']} | {_fmt(r['planes'], 1)} | {_fmt(r['seconds'], 3)} | "
                         f"{_fmt(r['peak_mb'], 1)} | "
                         f"{_fmt(r['psnr'])} | {_fmt(r['psnr_ob'])} | {_fmt(r['ssim'], 4)} | "
                         f"{_fmt(r['ssim_ob'], 4)} | {_fmt(r['flip'], 4)} | "
                         f"{_fmt(r['delta_psnr_vs_plain'], 4)} |")
        lines.append("")
    lines += ["## 1920x1080, 32 planes, largest radius 60 px", "",
              "| run | time (s) | peak RSS (MB) | note |", "|---|---|---|---|"]
    for k, v in result["hd"].items():
        if "error" in v:
            lines.append(f"| {k} | - | - | failed: {v['error']} |")
        else:
            note = (f"{v['planes']} non-empty planes, layer area {v['layer_area_frames']:.1f} frames"
                    + (f"; {v['measured_rows']} rows timed, 1080 extrapolated at the same cost "
                       "per row" if v.get("measured_rows", 1080) != 1080 else "")
                    + ("; numpy arithmetic, not the official renderer" if k == "official_direct" else ""))
            name = "numpy direct, official manner" if k == "official_direct" else k
            lines.append(f"| {name} | {v['seconds']:.2f} | {v['peak_rss_mb']:.0f} | {note} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    worker_main(_hd_worker)
