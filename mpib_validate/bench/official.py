"""Benchmark against the official MPIB renderer's code path, on the same 32 planes.

Our Eq. 1 compositor (:func:`compositor.composite.composite` with the default preset's
:class:`CompositeSettings`: exact fractional-radius kernels, FFT or direct by cost, each
layer cropped to its content) against the official ``MPIBokehRenderer`` computation
(:mod:`mpib_validate.baselines.official_torch`: soft disks at integer radii, direct
per-plane ``conv2d`` in torch on the CPU with 2 threads), on ONE MPI per case that both
render: the project's planes are ``uniform_planes(32, d_max)``, which the affine map
``d_n = d / d_max``, ``K = A d_max`` puts exactly on the official ``(i + 0.5) / 32``.

- Card scenes (both families): each renderer against the ray tracer (PSNR, PSNR_ob,
  SSIM, SSIM_ob on values clipped to [0, 1]), with the time of each.
- Timing: the compositor suite's 1920x1080 card MPI (20 non-empty of 32 planes, radii up
  to 59 px) and a 32-plane MPI where every plane has content (a photograph with a smooth
  disparity, built by the colour + depth path on 32 uniform planes). Quick mode times the
  central 480x270 window of the first (same radii) and the second built at 480x270 (same
  radius rule); ``--full`` times both at 1920x1080.

Times are interleaved in one process (ours, official, ours, official after one
warm-up of ours and the official kernel table), wall (``perf_counter``) and CPU
(``process_time``, all threads of the process); the timing MPIs add one official render
on a single torch thread (its CPU time free of OpenMP's waits). On a shared machine only the ratios of
one run mean anything. When torch is not installed the suite writes "skipped (torch not
installed)" and returns.
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

import numpy as np

from mpib_validate.bench.machine import finish, machine_info, mean_table, peak_rss_mb

N_PLANES = 32
SKIPPED = "skipped (torch not installed)"
#: largest blur radius of the timing MPIs (px), as the compositor suite's 1080p scene
TIMING_RADIUS = 60.0
#: quick mode's timing window (px)
QUICK_SIZE = (270, 480)


def _interleaved(ours, official, pairs: int = 2):
    """Run ``ours, official`` ``pairs`` times alternately; returns the last outputs and
    the wall and CPU seconds of each call (lists)."""
    t = {"ours": {"wall": [], "cpu": []}, "official": {"wall": [], "cpu": []}}
    out = {}
    for _ in range(pairs):
        for name, fn in (("ours", ours), ("official", official)):
            w0, c0 = time.perf_counter(), time.process_time()
            out[name] = fn()
            t[name]["cpu"].append(time.process_time() - c0)
            t[name]["wall"].append(time.perf_counter() - w0)
    return out, t


def _timing_fields(t) -> dict:
    f = {}
    for name in ("ours", "official"):
        f[f"{name}_wall_s"] = statistics.median(t[name]["wall"])
        f[f"{name}_cpu_s"] = statistics.median(t[name]["cpu"])
    f["ratio_wall"] = f["official_wall_s"] / f["ours_wall_s"]
    f["ratio_cpu"] = f["official_cpu_s"] / f["ours_cpu_s"]
    if "official_1thread_cpu" in t:
        f["official_1thread_cpu_s"] = t["official_1thread_cpu"]
        f["ratio_cpu_1thread"] = t["official_1thread_cpu"] / f["ours_cpu_s"]
    f["calls"] = t
    return f


def _nan_to_black(img: np.ndarray) -> tuple[np.ndarray, int]:
    """The official output with NaN (0/0: no plane covers the pixel) set to 0 for
    scoring; returns it and the number of NaN pixels."""
    bad = ~np.isfinite(img).all(axis=-1)
    return np.where(bad[..., None], 0.0, img).astype(np.float32), int(bad.sum())


def _pair(mpi, A, d_f, d_max, renderer, pairs=2, single_thread=False):
    """Both renderers on one MPI: outputs, interleaved times and the mapping."""
    from mpib_validate.baselines import official_torch as O
    from mpib_validate.runtime.compositor.composite import composite
    from mpib_validate.runtime.presets import PRESETS

    settings = PRESETS["default"].composite
    om = O.to_official(mpi, A, d_f, (0.0, d_max), N_PLANES)
    renderer.prepare(om)
    ours = lambda: composite(mpi, A, d_f, settings)  # noqa: E731
    ours()  # warm-up: our kernel caches (the official table is built by prepare)
    out, t = _interleaved(ours, lambda: renderer.render(om), pairs)
    if single_thread:
        # the official computation on one thread: its CPU time without OpenMP's waits
        one = O.OfficialRenderer(threads=1)
        one.prepare(om)
        c0 = time.process_time()
        one.render(om)
        t["official_1thread_cpu"] = time.process_time() - c0
    hc, wc = mpi.canvas_shape
    info = {"planes": N_PLANES, "non_empty_planes": mpi.plane_count, "K": om.K,
            "canvas_area_frames": hc * wc / (mpi.height * mpi.width),
            "focus_normalised": om.focus, "max_radius_px": max(om.radii()),
            "plane_error_px": om.plane_error_px, "height": mpi.height, "width": mpi.width}
    return out, t, info


# --------------------------------------------------------------------------------------
# card scenes


def _scene_rows(seed, family, size, ref_spp, renderer) -> list[dict]:
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.cards.evaluate import card_scene_mask, score
    from mpib_validate.cards.generate import GeneratorSettings, generate
    from mpib_validate.runtime.layers import mpi as M
    from mpib_validate.cards import mpi as CM

    print(f"bench official: {family}-{seed} ({size}x{size}) ...", flush=True)
    scene = generate(seed, family, settings=GeneratorSettings(width=size, height=size))
    cam = scene.camera
    # the compositor suite's reference and 32 planes, so the figures compare with its
    ref, _ = trace.trace(scene, samples.stratified(ref_spp, seed=101), notices=False)
    mask = card_scene_mask(scene)
    d_max = max(1.0, scene.disparity_range()[1] * 1.0001)
    mpi = CM.layers_from_cards(scene, planes=M.uniform_planes(N_PLANES, d_max))
    out, t, info = _pair(mpi, cam.blur_parameter, cam.focus_disparity, d_max, renderer)
    official, nan = _nan_to_black(out["official"])
    rows = []
    for name, img in (("ours-eq1-default", out["ours"]), ("official-torch", official)):
        rows.append({"scene": f"{family}-{seed}", "family": family, "method": name,
                     "seconds": statistics.median(t[name.split("-")[0]]["wall"]),
                     "cpu_seconds": statistics.median(t[name.split("-")[0]]["cpu"]),
                     "nan_pixels": nan if name.startswith("official") else 0,
                     **info, **score(ref, img, mask, with_flip=False)})
    return rows


# --------------------------------------------------------------------------------------
# timing MPIs


def crop_mpi(mpi, y0: int, y1: int, x0: int, x1: int):
    """The MPI over the frame window ``[y0, y1) x [x0, x1)`` (frame pixels), margin 0."""
    from mpib_validate.runtime.layers.mpi import MPI, Layer

    m = mpi.margin
    out = MPI(y1 - y0, x1 - x0, 0)
    for l in mpi.layers:
        ly0, ly1, lx0, lx1 = l.box
        a0, a1 = max(ly0, y0 + m), min(ly1, y1 + m)
        b0, b1 = max(lx0, x0 + m), min(lx1, x1 + m)
        if a0 >= a1 or b0 >= b1:
            continue
        out.layers.append(Layer(l.disparity, np.ascontiguousarray(
            l.rgba[a0 - ly0:a1 - ly0, b0 - lx0:b1 - lx0]), a0 - m - y0, b0 - m - x0, l.group))
    return out


def hd_card_mpi(quick: bool):
    """The compositor suite's 1920x1080 card MPI on 32 uniform planes, no margin (both
    renderers replicate the frame edge); quick: its central 480x270 window."""
    from mpib_validate.bench.compositor import hd_scene
    from mpib_validate.cards import mpi as CM
    from mpib_validate.runtime.layers import mpi as M

    scene = hd_scene()
    d_max = max(1.0, scene.disparity_range()[1])
    mpi = CM.layers_from_cards(scene, planes=M.uniform_planes(N_PLANES, d_max), margin=0)
    if quick:
        h, w = QUICK_SIZE
        y0, x0 = (mpi.height - h) // 2, (mpi.width - w) // 2
        mpi = crop_mpi(mpi, y0, y0 + h, x0, x0 + w)
    cam = scene.camera
    return mpi, cam.blur_parameter, cam.focus_disparity, d_max


def smooth_disparity(height: int, width: int) -> np.ndarray:
    """A smooth disparity in [0.05, 1] whose level sets wind across the whole frame
    (two oblique waves), so that every one of 32 planes has content spread over it."""
    v, u = np.mgrid[0:height, 0:width]
    u = (u + 0.5) / width
    v = (v + 0.5) / height
    t = 0.5 + 0.25 * np.sin(2 * np.pi * (1.3 * u + 0.2 * v)) \
        + 0.25 * np.cos(2 * np.pi * (0.7 * v - 0.4 * u))
    return 0.05 + 0.95 * (t - t.min()) / (t.max() - t.min())


def all_planes_mpi(height: int, width: int):
    """A photograph (scikit-image's astronaut, linear) with :func:`smooth_disparity`,
    made into an MPI by the colour + depth path on 32 uniform planes (over split, fill
    on: what ``mpib refocus`` builds with ``planes="uniform"``); focus at the 35th
    percentile of the disparity, ``A`` so that the largest plane radius is about 60 px."""
    from mpib_validate.cards.textures import shipped_image
    from mpib_validate.runtime.layers.passes import PassesSettings, layers_from_passes

    colour = shipped_image("astronaut", height, width)
    D = smooth_disparity(height, width)
    d_f = float(np.percentile(D, 35))
    A = TIMING_RADIUS / max(float(D.max()) - d_f, d_f)
    mpi, _ = layers_from_passes(colour, D, A, PassesSettings(planes="uniform",
                                                             n_uniform=N_PLANES))
    # the passes path puts its top plane at (n - 0.5) / n of d_max
    d_max = max(l.disparity for l in mpi.layers) * N_PLANES / (N_PLANES - 0.5)
    return mpi, A, d_f, d_max


def _timing_row(name, built, renderer, pairs: int = 2) -> dict:
    from mpib_validate.metrics import psnr

    mpi, A, d_f, d_max = built
    print(f"bench official: timing {name} ({mpi.width}x{mpi.height}) ...", flush=True)
    out, t, info = _pair(mpi, A, d_f, d_max, renderer, pairs, single_thread=True)
    official, nan = _nan_to_black(out["official"])
    # on values clipped to [0, 1], as every figure of the report
    agree = psnr(np.clip(out["ours"][..., :3], 0, 1), np.clip(official, 0, 1))
    return {"mpi": name, **info, **_timing_fields(t), "nan_pixels": nan,
            "agreement_psnr_db": agree}


# --------------------------------------------------------------------------------------


def run(out: Path, quick: bool = True, torch_available: bool | None = None) -> dict:
    """Run the suite. ``torch_available=False`` behaves as if torch were not installed
    (the suite is skipped); ``None`` looks for it."""
    from mpib_validate.baselines import official_torch as O

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if torch_available is None:
        torch_available = O.torch_available()
    if not torch_available:
        print(f"bench official: {SKIPPED}", flush=True)
        result = {"suite": "official", "quick": quick, "skipped": SKIPPED,
                  "summary": {"headlines": [f"official renderer: {SKIPPED}"]}}
        return finish(out, "official", result, _markdown)
    from mpib_validate.cards.generate import FAMILIES

    renderer = O.OfficialRenderer()
    size = 192 if quick else 512
    seeds = range(2) if quick else range(6)
    ref_spp = 2048 if quick else 8192
    rows = [r for family in FAMILIES for seed in seeds
            for r in _scene_rows(seed, family, size, ref_spp, renderer)]
    h, w = QUICK_SIZE if quick else (1080, 1920)
    timing = [_timing_row("cards-1080p" + (" (central 480x270 window)" if quick else ""),
                          hd_card_mpi(quick), renderer),
              _timing_row("all-planes" + (" (built at 480x270)" if quick else " (1920x1080)"),
                          all_planes_mpi(h, w), renderer)]
    import torch

    result = {"suite": "official", "quick": quick, "size": size, "reference_spp": ref_spp,
              "machine": {**machine_info(), "torch": torch.__version__,
                          "torch_threads": O.OFFICIAL_THREADS},
              "rows": rows, "timing": timing,
              "peak_rss_mb": peak_rss_mb()}
    result["summary"] = _summarise(result)
    return finish(out, "official", result, _markdown)


def _table(rows, family=None):
    keys = ("seconds", "cpu_seconds", "psnr", "psnr_ob", "ssim", "ssim_ob", "nan_pixels",
            "canvas_area_frames")
    if family is not None:
        return mean_table(rows, family, keys)
    return mean_table([{**r, "family": "all"} for r in rows], "all", keys)


def _summarise(result) -> dict:
    heads = []
    allt = {r["method"]: r for r in _table(result["rows"])}
    o, f = allt["ours-eq1-default"], allt["official-torch"]
    n = len({r["scene"] for r in result["rows"]})
    heads.append(
        f"On the same 32 planes (mean of {n} card scenes, {result['size']}x{result['size']}, "
        f"against the ray tracer): our Eq. 1 {o['psnr']:.1f} / {o['psnr_ob']:.1f} dB PSNR / "
        f"PSNR_ob, the official renderer {f['psnr']:.1f} / {f['psnr_ob']:.1f} dB; official "
        f"time / ours {f['seconds'] / o['seconds']:.1f}x wall, "
        f"{f['cpu_seconds'] / o['cpu_seconds']:.1f}x CPU (the official renderer convolves the "
        f"whole canvas, the frame plus its margin of real content, "
        f"{f['canvas_area_frames']:.1f}x the frame's area on average; the timing MPIs below have "
        f"no margin).")
    for t in result["timing"]:
        heads.append(
            f"{t['mpi']}, {t['width']}x{t['height']}, {t['non_empty_planes']} non-empty of 32 "
            f"planes, radii up to {t['max_radius_px']} px: official {t['official_wall_s']:.2f} s "
            f"against ours {t['ours_wall_s']:.2f} s, {t['ratio_wall']:.1f}x by wall time and "
            f"{t['ratio_cpu']:.1f}x by CPU time ({t['ratio_cpu_1thread']:.1f}x against the "
            f"official on one thread; interleaved; the outputs agree to "
            f"{t['agreement_psnr_db']:.1f} dB).")
    return {"headlines": heads,
            "tables": {fam: _table(result["rows"], fam) for fam in ("constant", "varying")}}


def _fmt(v, nd=2):
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def _markdown(result) -> str:
    lines = ["# Against the official MPIB renderer (same 32 planes)", ""]
    if result.get("skipped"):
        return "\n".join(lines + [f"The suite was {result['skipped']}: install the optional "
                                  "extra with `make official` (CPU torch 2.13.0).", ""])
    m = result["machine"]
    lines += [f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} "
              f"cores; Python {m['python']}, numpy {m.get('numpy')}, torch {m['torch']} "
              f"({m['torch_threads']} threads). {'Quick' if result['quick'] else 'Full'} mode. "
              f"Peak RSS {result['peak_rss_mb']:.0f} MB.", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    lines += ["Ours: Eq. 1 with the default preset's settings (exact kernels at fractional "
              "radii, FFT or direct by cost, crop to content). Official: the "
              "`MPIBokehRenderer` computation in torch (soft disks at integer radii "
              "`round(K |d_i - d_f|)`, replication padding, direct per-plane conv2d on all 32 "
              "planes, far-to-near accumulation, division without epsilon). Both on one MPI "
              "per case: the project's `uniform_planes(32, d_max)`, mapped by "
              "`d_n = d / d_max`, `K = A d_max` onto the official `(i + 0.5) / 32` (the "
              "largest radius error of the mapping is in the JSON, `plane_error_px`). Times: "
              "median of two calls each, interleaved ours, official, ours, official in one "
              "process after a warm-up; on a shared machine only the ratios are meaningful. "
              "Official 1-thread CPU: one more official render on one torch thread after "
              "them, its CPU time without the 2-thread OpenMP waits that inflate CPU time on "
              "a loaded machine. Agreement: PSNR between the two outputs, clipped to [0, 1].",
              ""]
    for family, table in result["summary"]["tables"].items():
        lines += [f"## {family} disparity ({result['size']}x{result['size']}, reference: ray "
                  f"tracer at {result['reference_spp']} samples)", "",
                  "| renderer | wall (s) | CPU (s) | PSNR | PSNR_ob | SSIM | SSIM_ob | NaN px |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in table:
            lines.append(f"| {r['method']} | {_fmt(r['seconds'], 3)} | {_fmt(r['cpu_seconds'], 3)} "
                         f"| {_fmt(r['psnr'])} | {_fmt(r['psnr_ob'])} | {_fmt(r['ssim'], 4)} | "
                         f"{_fmt(r['ssim_ob'], 4)} | {_fmt(r['nan_pixels'], 0)} |")
        lines.append("")
    lines += ["## Timing side by side", "",
              "| MPI | size | planes with content | max radius (px) | ours wall (s) | official "
              "wall (s) | ratio wall | ours CPU (s) | official CPU (s) | ratio CPU | official 1-thread "
              "CPU (s) | ratio | agreement (dB) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for t in result["timing"]:
        lines.append(f"| {t['mpi']} | {t['width']}x{t['height']} | {t['non_empty_planes']} / 32 | "
                     f"{t['max_radius_px']} | {_fmt(t['ours_wall_s'])} | "
                     f"{_fmt(t['official_wall_s'])} | {_fmt(t['ratio_wall'], 1)} | "
                     f"{_fmt(t['ours_cpu_s'])} | {_fmt(t['official_cpu_s'])} | "
                     f"{_fmt(t['ratio_cpu'], 1)} | {_fmt(t['official_1thread_cpu_s'])} | "
                     f"{_fmt(t['ratio_cpu_1thread'], 1)} | {_fmt(t['agreement_psnr_db'], 1)} |")
    if result["quick"]:
        lines += ["", "Quick mode times a 480x270 window with the full-size radii (the official "
                  "cost per output pixel is the same as at 1920x1080; ours pays relatively more "
                  "for the blur's padding on a small window, so the quick ratios understate "
                  "the 1080p ones). `mpib bench --suite official --full` times 1920x1080."]
    return "\n".join(lines) + "\n"
