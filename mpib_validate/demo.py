"""``mpib demo``: the project's result as a small gallery, in a few minutes on 2 cores.

Two default scenes, each refocused at two foci (``near``, ``far``) and scored against
its own reference:

- **cards** (:func:`card_cases`): the generated card scene (family ``varying``, seed
  0). The Eq. 15 ray tracer renders its all-in-focus colour and depth pass (the input,
  pinhole samples at pixel centres, pixel model ``texel``) and the defocused reference
  at each focus (``trace_spp`` stratified aperture samples). Foci: the median
  disparity of the nearest and of the farthest card that covers at least 2 % of the
  pinhole view.
- **Blender** (:func:`blender_cases`): the suite's ``spheres`` scene
  (:mod:`mpib_validate.blender.scenes`), rendered by Cycles on the CPU: the sharp
  Combined pass (``sharp_spp`` samples) and the Z pass are the input, Cycles' own
  depth of field at each focus (mean of two seeds, ``spp`` samples each) is the
  truth. The renders are cached under ``<out>/blender-cache``: a re-run renders
  nothing.

Methods, all on the same input (:func:`method_images`): mpib's presets
(:func:`mpib_validate.runtime.refocus.refocus`, the colour as ``mpib refocus`` writes
it into the EXR, premultiplied by its coverage), Blender's compositor Defocus node
(:func:`mpib_validate.baselines.defocus_node.defocus`, when ``bpy`` is installed) and
the sharp input itself. Times: mpib's the wall time of one call after an untimed
warm-up of the same call (kernel caches); the node's, its own render time (the render
with the node minus the same render with it bypassed).

Scores (:func:`mpib_validate.cards.evaluate.score`, colour clipped to [0, 1]): PSNR
over the image and PSNR_ob inside the occlusion-boundary mask, the card scene's true
boundaries (:func:`mpib_validate.cards.evaluate.card_scene_mask`) or the Z pass's
(:func:`mpib_validate.bench.blender.boundary_mask`), each dilated by the largest blur
radius around.

Written to ``out``: ``index.html`` and ``index.md`` (the gallery: inputs, results and
reference at each focus, boundary crops, error maps, the speed-against-error plot,
every figure in a table), ``demo.json`` (every figure, the run's wall and CPU time and
the load average), one folder per scene and focus with each image as EXR (linear) and
PNG (sRGB), and ``hero.jpg`` (:func:`write_hero`: sharp input, Defocus node, mpib
default and Cycles on the Blender scene focused far, with two boundary crops each).
"""

from __future__ import annotations

import html
import importlib.util
import json
import math
import os
import resource
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mpib_validate import __version__

CARD_FAMILY = "varying"
CARD_SEED = 0
BLENDER_KIND = "spheres"
BLENDER_SEED = 0
FOCI = ("near", "far")
PRESETS = ("draft", "default", "best")
SHARP = "sharp input"
NODE = "Defocus node"
DEFAULT = "mpib default"
#: A card counts for the card scene's foci when it is the front-most one on at least
#: this fraction of the pinhole view.
CARD_MIN_COVER = 0.02
#: Error maps: mean absolute error over RGB (colour clipped to [0, 1]) drawn from 0
#: (black) to this value (white); larger errors are drawn white.
ERROR_MAX = 0.1
#: Side of the window (px) over which a crop's error is averaged to place it.
CROP_WINDOW = 9
#: Scale of the crops in the gallery (nearest neighbour, so pixels stay visible).
CROP_SCALE = 3
#: JPEG quality of the hero picture (4:4:4 chroma, so colour edges stay sharp).
HERO_QUALITY = 88


#: Image sides the demo takes (the crops need 16 px; the demo is meant to be small).
MIN_SIDE, MAX_SIDE = 16, 4096


class DemoError(ValueError):
    """A demo option the scenes cannot take; the message names it."""


@dataclass(frozen=True)
class DemoSettings:
    """Sizes and sample counts of a run (the defaults: ``make demo``).

    ``trace_spp``: the card scene's HDR highlights blur into bokeh disks of about 30 px
    radius at the near focus, which the tracer's aperture samples cover sparsely: PSNR
    between two seeds (clipped) 27.4 dB at 1024 samples, 35.9 at 4096, 43.6 at 16384
    (about 7 CPU s per focus at 256x256). ``spp``: the Cycles truth's noise (the mean of
    its two seeds, clipped) is 47.8 / 49.1 dB PSNR at 64 samples per seed and 51.4 /
    52.7 dB at 128 (near / far focus), below every method's error.
    """

    card_size: int = 256
    trace_spp: int = 16384
    width: int = 320
    height: int = 240
    spp: int = 128
    sharp_spp: int = 32
    presets: tuple = PRESETS
    backend: str = "auto"

    def validate(self) -> "DemoSettings":
        """Refuse sizes the scenes cannot take, naming the option."""
        if not (MIN_SIDE <= self.width <= MAX_SIDE and MIN_SIDE <= self.height <= MAX_SIDE):
            raise DemoError(f"--size {self.width}x{self.height}: each side must be "
                             f"{MIN_SIDE} to {MAX_SIDE}")
        if not (MIN_SIDE <= self.card_size <= MAX_SIDE):
            raise DemoError(f"--card-size {self.card_size}: must be {MIN_SIDE} to {MAX_SIDE}")
        return self


@dataclass
class Case:
    """One scene at one focus: its input passes, camera, reference and mask."""

    scene: str  # "cards" or "blender"
    focus: str
    title: str
    passes: object  # refocus.Passes
    A: float
    d_f: float
    reference: np.ndarray  # (H, W, 3) linear
    mask: np.ndarray  # (H, W) bool, the occlusion-boundary mask
    node_camera: dict  # the Defocus node's camera settings
    reference_label: str
    reference_seconds: float
    disparity: np.ndarray  # (H, W) 1/scene-unit, for display
    extra: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.scene}-{self.focus}"


def _slug(method: str) -> str:
    return method.replace(" ", "-")


# --------------------------------------------------------------------------------------
# The scenes


def card_foci(scene) -> dict:
    """``{"near": d, "far": d}``: the median pinhole disparity of the nearest and of the
    farthest card that is front-most on at least :data:`CARD_MIN_COVER` of the view."""
    from mpib_validate.cards.trace import pinhole_maps

    maps = pinhole_maps(scene)
    medians = [float(np.median(maps["disparity"][maps["layer"] == k]))
               for k in range(len(scene.cards)) if (maps["layer"] == k).mean() >= CARD_MIN_COVER]
    return {"near": max(medians), "far": min(medians)}


def card_cases(s: DemoSettings, log=print) -> list[Case]:
    """The card scene at both foci (see the module docstring)."""
    from mpib_validate.cards import trace
    from mpib_validate.cards.evaluate import card_scene_mask
    from mpib_validate.cards.generate import GeneratorSettings, generate
    from mpib_validate.runtime import samples
    from mpib_validate.runtime.layers.passes import depth_to_disparity
    from mpib_validate.runtime.refocus import Passes

    scene = generate(CARD_SEED, CARD_FAMILY,
                     settings=GeneratorSettings(width=s.card_size, height=s.card_size))
    foci = card_foci(scene)
    cases = []
    aif = None
    for focus in FOCI:
        sc = replace(scene, camera=replace(scene.camera, focus_disparity=foci[focus]))
        t0 = time.perf_counter()
        if aif is None:
            res = trace.render(sc, samples.stratified(s.trace_spp), backend=s.backend,
                               notices=False)
            bokeh, aif, depth = res.bokeh, res.all_in_focus, res.depth
        else:
            bokeh, _ = trace.trace(sc, samples.stratified(s.trace_spp), backend=s.backend,
                                   notices=False)
        seconds = time.perf_counter() - t0
        passes = Passes(np.ascontiguousarray(aif[..., :3], np.float32), depth,
                        "ray tracer (pinhole)", "ray tracer (depth at pixel centres)",
                        pixel_model="texel")
        cam = sc.camera
        log(f"demo: cards ({CARD_FAMILY}, seed {CARD_SEED}, {s.card_size}x{s.card_size}), "
            f"focus {focus}: traced {s.trace_spp} spp in {seconds:.1f} s")
        cases.append(Case("cards", focus, f"Card scene ({CARD_FAMILY}, seed {CARD_SEED}), "
                          f"focus {focus}", passes, float(cam.blur_parameter),
                          float(cam.focus_disparity), bokeh[..., :3], card_scene_mask(sc),
                          cam.cycles_settings(),
                          f"ray tracer, {s.trace_spp} aperture samples", seconds,
                          depth_to_disparity(depth)))
    return cases


def _blender_specs(s: DemoSettings) -> list:
    from mpib_validate.blender.scenes import SceneSpec

    return [SceneSpec(BLENDER_KIND, BLENDER_SEED, s.width, s.height, f) for f in FOCI]


def blender_cached(out: Path, s: DemoSettings) -> bool:
    """Whether every Cycles render of the run is in ``out/blender-cache`` already."""
    from mpib_validate.blender.scenes import _complete, folder_name

    return all(_complete(out / "blender-cache" / folder_name(spec, s.spp),
                         spec.key(s.spp, s.sharp_spp)) for spec in _blender_specs(s))


def blender_cases(out: Path, s: DemoSettings, log=print) -> list[Case]:
    """The Blender scene at both foci, rendered by Cycles (cached under
    ``out/blender-cache``)."""
    from mpib_validate.bench.blender import boundary_mask
    from mpib_validate.blender.scenes import lens, load_scene, render_suite
    from mpib_validate.runtime.io.camera_header import resolve
    from mpib_validate.runtime.layers.passes import depth_to_disparity
    from mpib_validate.runtime.refocus import load_passes

    specs = _blender_specs(s)
    t0 = time.perf_counter()
    folders = render_suite(out / "blender-cache", specs, s.spp, sharp_spp=s.sharp_spp,
                           log=lambda line: log(f"demo: {line}"))
    log(f"demo: Cycles renders of {BLENDER_KIND} ({s.width}x{s.height}): "
        f"{time.perf_counter() - t0:.1f} s (0 when cached)")
    cases = []
    for focus, folder in zip(FOCI, folders):
        sc = load_scene(folder)
        path = folder / "passes.exr"
        passes = load_passes(path)
        H, W = passes.depth.shape
        cam = resolve(passes.camera, {}, W, H, path).camera  # as mpib refocus reads it
        A, d_f = float(cam.blur_parameter), float(cam.focus_disparity)
        secs = sc.meta["seconds"]
        cases.append(Case("blender", focus, f"Blender scene ({BLENDER_KIND}, seed "
                          f"{BLENDER_SEED}), focus {focus}", passes, A, d_f, sc.truth,
                          boundary_mask(sc.depth, A, d_f), lens(sc.spec),
                          f"Cycles' depth of field, mean of 2 seeds x "
                          f"{sc.meta['truth_spp']} spp", float(sum(secs["truth"])),
                          depth_to_disparity(passes.depth),
                          {"sharp_spp": sc.meta["sharp_spp"], "noise_psnr":
                           sc.meta["noise"]["psnr_clipped"],
                           "truth": f"2 seeds x {sc.meta['truth_spp']} spp"}))
    return cases


# --------------------------------------------------------------------------------------
# The methods


def method_images(case: Case, presets=PRESETS) -> dict:
    """``{method: (rgb (H, W, 3) linear, seconds)}`` on the case's input."""
    from mpib_validate.runtime.refocus import refocus
    from mpib_validate.runtime.request import RefocusRequest

    p = case.passes
    out = {SHARP: (np.asarray(p.colour, np.float32), 0.0)}
    if importlib.util.find_spec("bpy") is not None:
        from mpib_validate.baselines.defocus_node import defocus

        out[NODE] = defocus(p.colour, p.depth, case.node_camera)
    for name in presets:
        refocus(RefocusRequest(p, case.A, case.d_f, name))  # warm-up (kernel caches), untimed
        t0 = time.perf_counter()
        res = refocus(RefocusRequest(p, case.A, case.d_f, name))
        seconds = time.perf_counter() - t0
        # as refocus.write_result writes it: colour times coverage
        out[f"mpib {name}"] = (res.image[..., :3] * res.image[..., 3:4], seconds)
    return out


def score_rows(case: Case, images: dict) -> list[dict]:
    from mpib_validate.cards.evaluate import score

    rows = []
    for method, (img, seconds) in images.items():
        s = score(case.reference, img, case.mask, with_flip=False)
        rows.append({"scene": case.scene, "focus": case.focus, "method": method,
                     "seconds": float(seconds), "psnr": s["psnr"], "psnr_ob": s["psnr_ob"],
                     "ssim": s["ssim"], "ssim_ob": s["ssim_ob"],
                     "file": f"{case.name}/{_slug(method)}.exr"})
    return rows


# --------------------------------------------------------------------------------------
# Pictures


def error_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``(H, W)`` mean absolute error over RGB of the two, each clipped to [0, 1]."""
    a = np.clip(np.asarray(image, np.float64)[..., :3], 0, 1)
    b = np.clip(np.asarray(reference, np.float64)[..., :3], 0, 1)
    return np.abs(a - b).mean(-1)


def crop_side(shape) -> int:
    """Side of the boundary crops: a quarter of the image width less 2 px (two crops at
    twice their size fit side by side under the image, with a gap), at most half its
    height."""
    H, W = shape[:2]
    return max(4, min(W // 4 - 2, H // 2))


def crop_places(case: Case, images: dict) -> list[dict]:
    """Where to crop: the window (:data:`CROP_WINDOW` mean of the error inside the
    boundary mask) where the Defocus node errs most, then where mpib's default errs
    most at least one crop side away from the first; each ``{"what", "y", "x",
    "side"}`` (``y, x`` the crop's top-left corner)."""
    from scipy import ndimage

    c = crop_side(case.reference.shape)
    H, W = case.mask.shape
    h = c // 2
    places = []
    for method, what in ((NODE, "where the Defocus node errs most"),
                         (DEFAULT, "where mpib default errs most")):
        if method not in images:
            continue
        err = np.where(case.mask, error_map(images[method][0], case.reference), 0.0)
        err = ndimage.uniform_filter(err, CROP_WINDOW)
        err[:h], err[H - (c - h):], err[:, :h], err[:, W - (c - h):] = 0, 0, 0, 0
        for p in places:
            cy, cx = p["y"] + h, p["x"] + h
            err[max(0, cy - c):cy + c, max(0, cx - c):cx + c] = 0
        y, x = np.unravel_index(int(err.argmax()), err.shape)
        y, x = min(max(int(y), h), H - (c - h)), min(max(int(x), h), W - (c - h))
        places.append({"what": what, "y": y - h, "x": x - h, "side": c})
    return places


def _font(size: int):
    """DejaVu Sans (shipped with matplotlib) at ``size`` px, else PIL's default font."""
    from PIL import ImageFont

    try:
        from matplotlib import font_manager

        return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)
    except Exception:  # noqa: BLE001 - any font problem: the default bitmap font
        return ImageFont.load_default()


def _u8(img):
    from mpib_validate.runtime.io.preview import to_uint8

    return to_uint8(np.clip(np.asarray(img, np.float64)[..., :3], 0, None))


def _colour_bar(width: int, height: int, vmax: float, font):
    """A horizontal inferno bar from 0 to ``vmax`` with its two end labels (PIL image)."""
    from matplotlib import colormaps
    from PIL import Image, ImageDraw

    bar = colormaps["inferno"](np.linspace(0, 1, width))[None, :, :3].repeat(height, 0)
    img = Image.new("RGB", (width, height + 16), "white")
    img.paste(Image.fromarray(np.round(bar * 255).astype(np.uint8)), (0, 0))
    d = ImageDraw.Draw(img)
    d.text((0, height + 1), "0", fill="black", font=font)
    label = f">= {vmax:g}"
    d.text((width - int(d.textlength(label, font=font)), height + 1), label, fill="black",
           font=font)
    return img


def _tiles(path: Path, header: str, rows: list, scale: int, footer=None) -> None:
    """Write a grid of labelled tiles: ``rows`` = ``[(row title or None, [(label, uint8
    (h, w, 3)), ...]), ...]``, each tile scaled ``scale`` times (nearest neighbour)."""
    from PIL import Image, ImageDraw

    from mpib_validate.runtime.io.atomic import atomic_path

    font = _font(13)
    pad, line = 4, 17
    tw = max(t.shape[1] for _, ts in rows for _, t in ts) * scale
    th = max(t.shape[0] for _, ts in rows for _, t in ts) * scale
    ncol = max(len(ts) for _, ts in rows)
    row_h = [(line if title else 0) + line + th + pad for title, _ in rows]
    height = line + sum(row_h) + pad + (footer.height + pad if footer is not None else 0)
    canvas = Image.new("RGB", (ncol * (tw + pad) + pad, height), "white")
    d = ImageDraw.Draw(canvas)
    d.text((pad, 1), header, fill="black", font=font)
    y = line
    for (title, ts), h in zip(rows, row_h):
        if title:
            d.text((pad, y), title, fill=(70, 70, 70), font=font)
            y += line
        for k, (label, t) in enumerate(ts):
            x = pad + k * (tw + pad)
            d.text((x, y), label, fill="black", font=font)
            canvas.paste(Image.fromarray(t).resize((t.shape[1] * scale, t.shape[0] * scale),
                                                   Image.NEAREST), (x, y + line))
        y += h - (line if title else 0)
    if footer is not None:
        canvas.paste(footer, (pad, y))
    with atomic_path(path) as tmp:
        canvas.save(tmp, format="PNG")


def write_crops(path: Path, case: Case, images: dict, places: list[dict],
                columns: list[str]) -> None:
    """One row per crop place: each method of ``columns`` and the reference, scaled
    :data:`CROP_SCALE` times (nearest neighbour)."""
    names = [m for m in columns if m in images] + ["reference"]
    rows = []
    for p in places:
        sl = (slice(p["y"], p["y"] + p["side"]), slice(p["x"], p["x"] + p["side"]))
        rows.append((f"{p['what']} (x {p['x']}, y {p['y']}, {p['side']} px square)",
                     [(m, _u8((case.reference if m == "reference" else images[m][0])[sl]))
                      for m in names]))
    _tiles(path, f"{case.title}: boundary crops, x{CROP_SCALE}", rows, CROP_SCALE)


def write_error_maps(path: Path, case: Case, images: dict, methods: list[str]) -> None:
    """The error maps (:func:`error_map`) of ``methods`` against the reference side by
    side at 1:1, inferno from 0 to :data:`ERROR_MAX`, with a colour bar."""
    from matplotlib import colormaps

    tiles = []
    for m in methods:
        if m in images:
            e = np.clip(error_map(images[m][0], case.reference) / ERROR_MAX, 0, 1)
            tiles.append((m, np.round(colormaps["inferno"](e)[..., :3] * 255).astype(np.uint8)))
    bar = _colour_bar(min(256, case.reference.shape[1]), 10, ERROR_MAX, _font(12))
    _tiles(path, f"{case.title}: |method - reference|, mean over RGB (clipped colour)",
           [(None, tiles)], 1, footer=bar)


def write_disparity(path: Path, disparity: np.ndarray) -> None:
    """The input's disparity (1/scene-unit) from its minimum (dark) to its maximum
    (bright), viridis."""
    from matplotlib import colormaps
    from PIL import Image

    from mpib_validate.runtime.io.atomic import atomic_path

    D = np.asarray(disparity, np.float64)
    lo, hi = float(D.min()), float(D.max())
    rgb = colormaps["viridis"]((D - lo) / (hi - lo if hi > lo else 1.0))[..., :3]
    with atomic_path(path) as tmp:
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(tmp, format="PNG")


def speed_error_plot(path: Path, rows: list[dict], metric: str = "psnr_ob") -> None:
    """``metric`` against time (log), one panel per scene, one colour per method,
    filled markers for the near focus and open ones for the far focus; the sharp input
    (no time) as a grey line per focus (dotted near, dashed far)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from mpib_validate.runtime.io.atomic import atomic_path

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods = [m for m in dict.fromkeys(r["method"] for r in rows) if m != SHARP]
    colours = {m: f"C{i}" for i, m in enumerate(methods)}
    style = {"near": ":", "far": "--"}
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 3.9), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for r in rows:
            if r["scene"] != scene:
                continue
            if r["method"] == SHARP:
                ax.axhline(r[metric], ls=style[r["focus"]], lw=1.0, color="0.55")
                continue
            c = colours[r["method"]]
            ax.scatter([r["seconds"]], [r[metric]], s=50, marker="o", linewidths=1.6,
                       facecolors=c if r["focus"] == "near" else "none", edgecolors=c)
        ax.set_xscale("log")
        ax.set_xlabel("time of one refocus (s, log scale)")
        ax.set_ylabel(f"{'PSNR_ob' if metric == 'psnr_ob' else 'PSNR'} against the reference (dB)")
        ax.set_title(f"{scene} scene", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    handles = [Line2D([], [], ls="", marker="o", color=colours[m], label=m) for m in methods]
    handles += [Line2D([], [], ls="", marker="o", color="0.3", label="near focus"),
                Line2D([], [], ls="", marker="o", mfc="none", color="0.3", label="far focus"),
                Line2D([], [], ls=":", color="0.55", label="sharp input, near"),
                Line2D([], [], ls="--", color="0.55", label="sharp input, far")]
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.13, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def hero_image(case: Case, images: dict, rows: list[dict], places: list[dict]):
    """The README's picture: sharp input | Defocus node | mpib default | reference,
    each full frame with the crop places outlined, and below it its two crops side by
    side (scaled by the largest whole factor with which both fit under the frame,
    nearest neighbour). Each panel is labelled with its PSNR and PSNR_ob against the
    reference. Returns a PIL image and the panels' figures."""
    from PIL import Image, ImageDraw

    H, W = case.reference.shape[:2]
    by = {r["method"]: r for r in rows if r["scene"] == case.scene and r["focus"] == case.focus}
    truth = "Cycles' depth of field" if case.scene == "blender" else "Ray tracer (reference)"
    panels = [(SHARP, "Sharp input"), (NODE, "Blender's Defocus node"),
              (DEFAULT, "mpib (default preset)"), ("reference", truth)]
    panels = [(m, t) for m, t in panels if m == "reference" or m in images]
    outline = [(255, 210, 0), (0, 200, 255)]
    big_px, small_px, pad = max(10, W // 20), max(8, W // 27), 4
    big, small = _font(big_px), _font(small_px)
    head = int(1.3 * big_px + 1.4 * small_px) + 4
    crops = places[:2]
    # two crops side by side under each frame, each scaled by the same whole factor
    zoom = max(1, (W - pad) // (2 * crops[0]["side"])) if crops else 1
    below = crops[0]["side"] * zoom + pad if crops else 0
    canvas = Image.new("RGB", (len(panels) * (W + pad) + pad, head + H + below + pad), "white")
    d = ImageDraw.Draw(canvas)
    figures = []
    for k, (m, title) in enumerate(panels):
        x0 = pad + k * (W + pad)
        if m == "reference":
            img, sub = case.reference, f"the reference: {case.extra.get('truth', '')}".rstrip(": ")
            figures.append({"panel": title, "method": "reference", "label": case.reference_label})
        else:
            img, r = images[m][0], by[m]
            sub = f"PSNR {r['psnr']:.1f} dB, at edges {r['psnr_ob']:.1f} dB"
            # no times: they vary with the machine's load, the picture and its
            # figures do not (demo.json has the times)
            figures.append({"panel": title, "method": m, "psnr": r["psnr"],
                            "psnr_ob": r["psnr_ob"]})
        figures[-1]["box"] = [x0, head, W, H]  # where the full frame lies in the picture
        d.text((x0, 2), title, fill="black", font=big)
        d.text((x0, 2 + int(1.3 * big_px)), sub, fill=(70, 70, 70), font=small)
        canvas.paste(Image.fromarray(_u8(img)), (x0, head))
        for i, p in enumerate(crops):
            d.rectangle([x0 + p["x"] - 1, head + p["y"] - 1, x0 + p["x"] + p["side"],
                         head + p["y"] + p["side"]], outline=outline[i], width=1)
            tile = _u8(img[p["y"]:p["y"] + p["side"], p["x"]:p["x"] + p["side"]])
            n = tile.shape[0] * zoom
            cx, cy = x0 + (0 if i == 0 else W - n), head + H + pad
            canvas.paste(Image.fromarray(tile).resize((n, n), Image.NEAREST), (cx, cy))
            d.rectangle([cx, cy, cx + n - 1, cy + n - 1], outline=outline[i], width=2)
    return canvas, figures


def write_hero(path: Path, case: Case, images: dict, rows: list[dict], places: list[dict],
               command: str) -> dict:
    """:func:`hero_image` as JPEG (or PNG, by the suffix), and ``<stem>.json`` beside it
    with the panels' figures (the caption's data) and the ``command`` that makes it."""
    from mpib_validate.runtime.io.atomic import atomic_path, write_text

    path = Path(path)
    img, figures = hero_image(case, images, rows, places)
    with atomic_path(path) as tmp:
        if path.suffix.lower() in (".jpg", ".jpeg"):
            img.save(tmp, format="JPEG", quality=HERO_QUALITY, subsampling=0, optimize=True)
        else:
            img.save(tmp, format="PNG", optimize=True)
    info = {"picture": path.name, "scene": case.title, "size": [int(case.reference.shape[1]),
                                                                  int(case.reference.shape[0])],
            "reference": case.reference_label, "panels": figures,
            "crops": [{k: p[k] for k in ("what", "x", "y", "side")} for p in places[:2]],
            "crop_outlines": ["yellow", "cyan"][:len(places[:2])],
            "scores": "colour clipped to [0, 1]; 'at edges' = PSNR_ob, inside the occlusion-"
                      "boundary mask (disparity jumps of 1 px of blur radius, dilated by the "
                      "blur radius)",
            "command": command}
    write_text(path.with_suffix(".json"), json.dumps(info, indent=2, default=float) + "\n")
    return info


# --------------------------------------------------------------------------------------
# The gallery


def _fmt(v, nd=2) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{nd}f}"


def _table_rows(rows: list[dict]) -> list[list[str]]:
    return [[r["method"], _fmt(r["seconds"], 3) if r["method"] != SHARP else "-",
             _fmt(r["psnr"]), _fmt(r["psnr_ob"]), _fmt(r["ssim"], 4), _fmt(r["ssim_ob"], 4)]
            for r in rows]


HEADER = ["method", "time (s)", "PSNR (dB)", "PSNR_ob (dB)", "SSIM", "SSIM_ob"]


def _run_line(summary: dict) -> str:
    t, m = summary["timing"], summary["machine"]
    cycles = "cached" if t["cycles_cached"] else f"{t['cycles_seconds']:.0f} s"
    bpy = f"bpy {m['bpy']}" if m.get("bpy") else "no bpy"
    return (f"mpib {summary['version']}, Python {m['python']}, {bpy}; {m['processor']}, "
            f"{m['cores']} cores. This run: {t['wall_seconds']:.0f} s wall, "
            f"{t['cpu_seconds']:.0f} s CPU; load average {t['load_start'][0]:.2f} at the start, "
            f"{t['load_end'][0]:.2f} at the end (1 min). Cycles renders: {cycles}.")


def _intro(summary: dict) -> str:
    s = summary["settings"]
    return (f"Two default scenes refocused at two foci. Cards: the generated card scene "
            f"({CARD_FAMILY}, seed {CARD_SEED}, {s['card_size']}x{s['card_size']}); input = the "
            f"ray tracer's all-in-focus colour and depth pass; reference = the ray tracer "
            f"({s['trace_spp']} aperture samples). Blender: the suite's {BLENDER_KIND} scene "
            f"({s['width']}x{s['height']}); input = Cycles' sharp Combined ({s['sharp_spp']} spp) "
            f"and Z passes; truth = Cycles' own depth of field (2 seeds x {s['spp']} spp). "
            f"mpib and Blender's Defocus node run on the same input. Scores on colour clipped "
            f"to [0, 1]; PSNR_ob inside the occlusion-boundary mask; mpib times: one call after "
            f"a warm-up; the node's: its own render time.")


def write_gallery(out: Path, summary: dict, cases: list[Case]) -> list[Path]:
    """``index.html`` and ``index.md`` from the run's summary (every figure comes from
    ``summary``, the images from ``out``)."""
    from mpib_validate.runtime.io.atomic import write_text

    rows = summary["rows"]
    e = html.escape
    H = ["<!doctype html>", "<html><head><meta charset='utf-8'><title>mpib demo</title>",
         "<style>body{font-family:sans-serif;max-width:1400px;margin:1em auto;padding:0 1em}"
         "table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;"
         "text-align:right}td:first-child,th:first-child{text-align:left}"
         "figure{display:inline-block;margin:4px;vertical-align:top}figcaption{font-size:12px}"
         "img{image-rendering:pixelated}</style></head><body>",
         "<h1>mpib demo</h1>", f"<p>{e(_intro(summary))}</p>", f"<p>{e(_run_line(summary))}</p>"]
    M = ["# mpib demo", "", _intro(summary), "", _run_line(summary), ""]
    # the headline: PSNR_ob of every method per scene and focus
    methods = list(dict.fromkeys(r["method"] for r in rows))
    by = {(r["scene"], r["focus"], r["method"]): r for r in rows}
    head = ["scene, focus"] + methods
    table = [[f"{c.scene}, {c.focus}"] + [_fmt(by[(c.scene, c.focus, m)]["psnr_ob"])
                                          if (c.scene, c.focus, m) in by else "-"
                                          for m in methods] for c in cases]
    what = ("PSNR_ob (dB) against each scene's reference, inside the occlusion-boundary "
            "mask (higher is better); the tables below give PSNR, SSIM and times.")
    H += ["<h2>Summary</h2>", f"<p>{e(what)}</p>", "<table><tr>"
          + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>"]
    H += ["<tr>" + "".join(f"<td>{e(v)}</td>" for v in row) + "</tr>" for row in table]
    H += ["</table>"]
    M += ["## Summary", "", what, "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    M += ["| " + " | ".join(row) + " |" for row in table] + [""]
    if summary.get("hero"):
        hero = summary["hero"]
        cap = "; ".join(f"{p['panel']}: PSNR {p['psnr']:.2f} dB, PSNR_ob {p['psnr_ob']:.2f} dB"
                        for p in hero["panels"] if "psnr" in p)
        crops = "; ".join(f"{c['what']} ({o})" for c, o in zip(hero["crops"],
                                                                hero["crop_outlines"]))
        text = (f"{hero['scene']}: the sharp input, Blender's Defocus node, mpib's default "
                f"preset and {hero['reference']}; {cap}. Crops (outlined in the frames): "
                f"{crops}.")
        H += ["<h2>At the boundaries</h2>", f"<p>{e(text)}</p>",
              f"<img src='{e(hero['picture'])}' alt='hero'>"]
        M += ["## At the boundaries", "", text, "", f"![hero]({hero['picture']})", ""]
    H += ["<h2>Speed against error</h2>",
          "<p>PSNR_ob against each scene's reference, against the time of one refocus on "
          "this run's machine and load; filled: near focus, open: far focus; grey lines: the "
          "sharp input.</p>", "<img src='speed-error.png' alt='speed'>"]
    M += ["## Speed against error", "", "PSNR_ob against each scene's reference, against the "
          "time of one refocus on this run's machine and load; filled: near focus, open: far "
          "focus; grey lines: the sharp input.", "", "![speed against error](speed-error.png)", ""]
    for case in cases:
        n = case.name
        sel = [r for r in rows if r["scene"] == case.scene and r["focus"] == case.focus]
        c = summary["cases"][n]
        lead = (f"A = {case.A:.2f} px per unit disparity, d_f = {case.d_f:.4f}; largest blur "
                f"radius {c['largest_radius_px']:.1f} px; reference: {case.reference_label} "
                f"(rendered in {case.reference_seconds:.1f} s"
                + (f"; its noise: PSNR {c['noise_psnr']:.1f} dB" if "noise_psnr" in c else "")
                + ").")
        H += [f"<h2>{e(case.title)}</h2>", f"<p>{e(lead)}</p>", "<table><tr>"
              + "".join(f"<th>{e(h)}</th>" for h in HEADER) + "</tr>"]
        H += ["<tr>" + "".join(f"<td>{e(v)}</td>" for v in row) + "</tr>"
              for row in _table_rows(sel)]
        H += ["</table>", "<div>"]
        M += [f"## {case.title}", "", lead, "", "| " + " | ".join(HEADER) + " |",
              "|" + "---|" * len(HEADER)]
        M += ["| " + " | ".join(row) + " |" for row in _table_rows(sel)]
        M += [""]
        figs = [("input.png", "input: colour"), ("disparity.png", "input: disparity")]
        figs += [(f"{_slug(r['method'])}.png", r["method"]) for r in sel if r["method"] != SHARP]
        figs += [("reference.png", "reference")]
        for f, cap in figs:
            H.append(f"<figure><img src='{n}/{f}' alt='{e(cap)}'><figcaption>{e(cap)}"
                     f"</figcaption></figure>")
        H += ["</div>", f"<p>Boundary crops (x{CROP_SCALE}), columns: "
              f"{e(', '.join(c['crop_columns']))}.</p>",
              f"<img src='{n}/crops.png' alt='crops'>",
              f"<p>Error maps: mean absolute error over RGB, black 0 to light yellow {ERROR_MAX} and above.</p>",
              f"<img src='{n}/errors.png' alt='errors'>"]
        M += [" ".join(f"![{cap}]({n}/{f})" for f, cap in figs), "",
              f"Boundary crops (x{CROP_SCALE}), columns: {', '.join(c['crop_columns'])}.", "",
              f"![crops]({n}/crops.png)", "",
              f"Error maps: mean absolute error over RGB, black 0 to light yellow {ERROR_MAX} and above.", "",
              f"![errors]({n}/errors.png)", ""]
    H += ["<p>Every figure: <a href='demo.json'>demo.json</a>. The full benchmark: "
          "<code>make bench</code>.</p>", "</body></html>"]
    M += ["Every figure: [demo.json](demo.json). The full benchmark: `make bench`.", ""]
    write_text(out / "index.html", "\n".join(H) + "\n")
    write_text(out / "index.md", "\n".join(M) + "\n")
    return [out / "index.html", out / "index.md"]


# --------------------------------------------------------------------------------------
# The run


def _cpu_seconds() -> float:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def _machine() -> dict:
    from mpib_validate.bench.machine import machine_info

    m = machine_info()
    return {"python": m["python"], "processor": m.get("processor"), "platform": m.get("platform"),
            "cores": m.get("affinity_cores", m.get("cpu_count")), "bpy": m.get("bpy")}


def _write_case_images(out: Path, case: Case, images: dict) -> None:
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr
    from mpib_validate.runtime.io.preview import write_png

    d = out / case.name
    d.mkdir(parents=True, exist_ok=True)
    for name, img in [("reference", case.reference)] + [(_slug(m), v[0]) for m, v in images.items()]:
        rgb = np.asarray(img, np.float32)[..., :3]
        write_exr(d / f"{name}.exr", channels_from_rgba(rgb))
        write_png(d / f"{name}.png", np.clip(rgb, 0, None))
    write_png(d / "input.png", np.clip(np.asarray(case.passes.colour)[..., :3], 0, None))
    write_disparity(d / "disparity.png", case.disparity)


def check_hero_path(hero) -> None:
    """Refuse a ``--hero`` path before any work: a .jpg, .jpeg or .png file name whose
    folder exists."""
    from mpib_validate.runtime.io.atomic import OutputError, check_outputs

    if hero is None:
        return
    p = Path(hero)
    if p.suffix.lower() not in (".jpg", ".jpeg", ".png"):
        raise OutputError(f"--hero '{hero}': give a .jpg, .jpeg or .png file name")
    if not p.parent.is_dir():
        raise OutputError(f"--hero '{hero}': the folder '{p.parent}' does not exist")
    check_outputs([p, p.with_name(p.name + ".json")], option="--hero")


def run_demo(out: Path, settings: DemoSettings | None = None, hero=None, log=print) -> dict:
    """Render both scenes, refocus them at both foci, score, write the gallery and
    ``hero.jpg`` (and a copy at ``hero`` with its ``.json``, if given); returns the
    summary that ``demo.json`` holds."""
    from mpib_validate.runtime.io.atomic import write_text

    from mpib_validate.runtime.io.atomic import check_outputs

    s = (settings or DemoSettings()).validate()
    check_hero_path(hero)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DemoError(f"--out '{out}' is a file; give a folder for the gallery")
    check_outputs([out / "index.html"], option="--out")
    out.mkdir(parents=True, exist_ok=True)
    t0, c0, load0 = time.perf_counter(), _cpu_seconds(), os.getloadavg()
    cases = card_cases(s, log)
    t_cycles = time.perf_counter()
    have_bpy, cached = importlib.util.find_spec("bpy") is not None, False
    if have_bpy:
        cached = blender_cached(out, s)
        cases += blender_cases(out, s, log)
    else:
        log("demo: bpy is not installed: no Blender scene, no Defocus node")
    cycles_seconds = time.perf_counter() - t_cycles
    rows, info, hero_case = [], {}, None
    for case in cases:
        images = method_images(case, s.presets)
        r = score_rows(case, images)
        rows += r
        for row in r:
            if row["method"] != SHARP:
                log(f"demo: {case.name}: {row['method']}: {row['seconds']:.2f} s, PSNR "
                    f"{row['psnr']:.2f} dB, PSNR_ob {row['psnr_ob']:.2f} dB")
        _write_case_images(out, case, images)
        places = crop_places(case, images)
        columns = [m for m in (SHARP, NODE, DEFAULT) if m in images]
        write_crops(out / case.name / "crops.png", case, images, places, columns)
        write_error_maps(out / case.name / "errors.png", case, images,
                         [m for m in images if m != SHARP])
        D = case.disparity
        info[case.name] = {"A": case.A, "d_f": case.d_f, "reference": case.reference_label,
                           "reference_seconds": case.reference_seconds,
                           "largest_radius_px": float(case.A * np.abs(D - case.d_f).max()),
                           "mask_fraction": float(case.mask.mean()), "crops": places,
                           "crop_columns": columns + ["reference"], **case.extra}
        if case.scene == ("blender" if have_bpy else "cards") and case.focus == "far":
            hero_case = (case, images, places)
    hero_info = write_hero(out / "hero.jpg", *hero_case[:2], rows, hero_case[2],
                           f"mpib demo --out {out}")
    if hero is not None:
        write_hero(Path(hero), *hero_case[:2], rows, hero_case[2], f"mpib demo --hero {hero}")
    speed_error_plot(out / "speed-error.png", rows)
    wall, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
    summary = {"version": __version__, "machine": _machine(), "settings": {
        **{k: getattr(s, k) for k in ("card_size", "trace_spp", "width", "height", "spp",
                                      "sharp_spp", "backend")}, "presets": list(s.presets)},
        "timing": {"wall_seconds": wall, "cpu_seconds": cpu, "load_start": list(load0),
                   "load_end": list(os.getloadavg()), "cycles_seconds": cycles_seconds,
                   "cycles_cached": bool(have_bpy and cached)},
        "cases": info, "rows": rows, "hero": hero_info}
    write_text(out / "demo.json", json.dumps(summary, indent=2, default=float) + "\n")
    pages = write_gallery(out, summary, cases)
    if hero is not None:
        log(f"demo: wrote {hero} and {Path(hero).with_suffix('.json')}")
    log(f"demo: {wall:.0f} s wall, {cpu:.0f} s CPU on {summary['machine']['cores']} cores "
        f"(load average {load0[0]:.2f} at the start, {summary['timing']['load_end'][0]:.2f} "
        f"at the end)")
    log(f"demo: gallery {pages[0].resolve()} (and {pages[1].name})")
    return summary
