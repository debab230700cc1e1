"""Sharp remnants on photographs that ship with scikit-image, with network-like disparity.

Part of ``mpib bench --suite photos``. Four photographs: the Middlebury motorcycle (its
stereo disparity is the truth) and three portraits of objects whose true disparity is
hand-built here (:func:`true_disparity`): objects drawn as polygons and ellipses in image
coordinates, snapped to the colour edges by SLIC superpixels (a superpixel is the
object's if more than half of it lies in the shape), each a base disparity plus a smooth
relief (a bulge, a slope), in the paper's [0, 1] convention.

The input disparity is shaped like a monocular network's (:func:`network_disparity`):
the near side fattened by a 2 px grey dilation (networks overshoot thin outlines), then
:func:`mpib_validate.cards.degrade.degrade_disparity` (Gaussian blur 0.8 % of the
short side, 4x down as a 2000 px photograph at a network's 384 to 518 px, 2 % smooth
multiplicative noise, bilinear up, a 1.5 px shift), stored as 8 bits as a user saves it.

Each photograph is refocused near (the true disparity's 90th percentile) and far (10th)
with ``K = 6 %`` of its width, gamma 2.2, default preset: with the default refinement,
with it off, and from the true disparity (refinement off: the reference).
:func:`mpib_validate.metrics.sharp_remnants` counts the sharp remnants two ways: against
the unrefined output where the input map says blur (what a user can count without a
truth) and against the reference where the true disparity says blur. The table also
gives the default fed the map shrunk by :data:`OVERSHOOT_PX` first (``mpib refocus
--map-overshoot``), against the reference.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

#: the photographs, in the order of the table
PHOTOS = ("astronaut", "chelsea", "coffee", "motorcycle")
#: The ``mpib refocus --map-overshoot`` the table also shows (photograph pixels): the
#: network-like maps here overshoot by a 2 px dilation
#: (:func:`network_disparity`)
OVERSHOOT_PX = 2
#: K as a fraction of the width (K = 60 at 1000 px: the paper's blur on a photograph
#: half the size of its 2000 px example)
K_FRACTION = 0.06
GAMMA = 2.2


def _poly(shape, pts):
    from PIL import Image, ImageDraw

    im = Image.new("L", (shape[1], shape[0]), 0)
    ImageDraw.Draw(im).polygon([tuple(p) for p in pts], fill=1)
    return np.asarray(im, bool)


def _ellipse(shape, cx, cy, rx, ry):
    y, x = np.mgrid[:shape[0], :shape[1]]
    return ((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2 <= 1


def _bulge(shape, cx, cy, rx, ry):
    y, x = np.mgrid[:shape[0], :shape[1]]
    return np.sqrt(np.clip(1 - ((x - cx) / rx) ** 2 - ((y - cy) / ry) ** 2, 0, 1))


def _snap(img, shape_mask, n=600):
    from scipy import ndimage
    from skimage.segmentation import slic

    seg = slic(img, n_segments=n, compactness=12, start_label=0)
    frac = ndimage.mean(shape_mask.astype(float), seg, np.arange(seg.max() + 1))
    return frac[seg] > 0.5


def true_disparity(name: str):
    """``(sRGB uint8 image, true disparity in [0, 1])`` of one of :data:`PHOTOS`."""
    from skimage import data

    if name == "motorcycle":
        from scipy import ndimage

        # as bench.photos.load_motorcycle: unknown values (inf) take their nearest
        # known one, then the map is normalised to [0, 1]
        left, _, disp = data.stereo_motorcycle()
        _, (iy, ix) = ndimage.distance_transform_edt(~np.isfinite(disp), return_indices=True)
        disp = disp[iy, ix]
        return left, (disp - disp.min()) / (disp.max() - disp.min())
    img = getattr(data, name)()
    H, W = img.shape[:2]
    s = (H, W)
    y = np.mgrid[:H, :W][0] / max(H, W)
    if name == "astronaut":
        D = 0.15 + 0.05 * y  # wall and flag
        shuttle = _snap(img, _poly(s, [(395, 0), (440, 0), (452, 120), (470, 230), (470, 280),
                                       (355, 280), (362, 200), (382, 100)]))
        D = np.where(shuttle, 0.42, D)
        person = _snap(img, _ellipse(s, 228, 85, 78, 72) | _poly(s, [
            (20, 512), (30, 280), (110, 230), (130, 160), (300, 160), (340, 250), (365, 330),
            (360, 512)]))
        D = np.where(person, 0.70 + 0.08 * _bulge(s, 225, 110, 80, 90)
                     + 0.04 * _bulge(s, 190, 380, 200, 200), D)
        helmet = _snap(img, _ellipse(s, 392, 452, 118, 112))
        D = np.where(helmet, 0.88 + 0.06 * _bulge(s, 392, 452, 118, 112), D)
    elif name == "chelsea":
        D = 0.12 + 0.05 * y
        cat = _snap(img, _poly(s, [(0, 0), (40, 0), (60, 20), (100, 0), (340, 0), (392, 8),
                                   (372, 60), (362, 120), (372, 200), (352, 300), (0, 300)]))
        D = np.where(cat, 0.62 + 0.25 * _bulge(s, 250, 200, 230, 200), D)
    elif name == "coffee":
        D = 0.15 + 0.55 * np.mgrid[:H, :W][0] / H  # the table, slanted
        D = np.where(_snap(img, _ellipse(s, 280, 232, 205, 152)), D + 0.08, D)  # saucer
        cup = _snap(img, _poly(s, [(178, 60), (200, 30), (300, 18), (380, 35), (408, 70),
                                   (400, 200), (380, 260), (300, 300), (250, 300), (195, 310),
                                   (198, 240), (178, 160)]))
        D = np.where(cup, 0.82, D)
        spoon = _snap(img, _poly(s, [(400, 70), (420, 70), (412, 120), (395, 215), (405, 260),
                                     (400, 315), (360, 325), (325, 300), (330, 255), (370, 235),
                                     (385, 200)]))
        D = np.where(spoon & ~cup, 0.86, D)
    else:
        raise KeyError(f"unknown photograph {name!r}; one of {', '.join(PHOTOS)}")
    return img, np.clip(D, 0.0, 1.0)


def network_disparity(D: np.ndarray, seed: int = 0) -> np.ndarray:
    """A network-like map of the true disparity ``D`` (see the module docstring), 8-bit
    levels in [0, 1], same shape."""
    from scipy import ndimage

    from mpib_validate.cards.degrade import degrade_disparity

    fat = ndimage.grey_dilation(np.asarray(D, np.float64), size=5)
    out = degrade_disparity(fat, seed, blur_px=0.008 * min(D.shape), down=4, shift_px=1.5,
                            noise=0.02)
    return np.round(np.clip(out, 0.0, 1.0) * 255) / 255


def _render(lin, D, K, d_f, refine):
    from mpib_validate.runtime.compositor.composite import render_subapertures
    from mpib_validate.runtime.layers.passes import layers_from_passes
    from mpib_validate.runtime.presets import PRESETS

    p = PRESETS["default"]
    mpi, _ = layers_from_passes(lin, D, K, dataclasses.replace(p.passes, refine=refine))
    return _display(render_subapertures(mpi, K, d_f, p.subapertures, p.composite)[..., :3])


def _display(linear):
    """Display values (8-bit levels in [0, 1]) of a linear render, gamma :data:`GAMMA`."""
    return np.round(np.clip(linear, 0.0, 1.0) ** (1 / GAMMA) * 255) / 255


def photo_rows(name: str, outputs: dict | None = None, matting: bool = False) -> list[dict]:
    """One row per focus of photograph ``name``: the must-blur pixel counts, the remnants
    of the default (guided) and of the unrefined result, and their PSNR against the
    reference (display values, dB). ``outputs``, if given, receives the images. With
    ``matting``, the same for the matting variant
    (:func:`mpib_validate.bench.matting.matte_render`; needs pymatting)."""
    from mpib_validate.metrics import psnr, sharp_edges, sharp_remnants
    from mpib_validate.runtime.io.photo import shrink_overshoot
    from mpib_validate.runtime.layers.refine import refine_disparity

    img, Dt = true_disparity(name)
    N = network_disparity(Dt)
    lin = (img.astype(np.float64) / 255.0) ** GAMMA
    K = K_FRACTION * Dt.shape[1]
    refined = refine_disparity(lin, N, K)  # the map the default builds its layers from
    shrunk = shrink_overshoot(N, OVERSHOOT_PX)  # what --map-overshoot gives the default
    rows = []
    for focus, q in (("near", 0.9), ("far", 0.1)):
        d_f = float(np.quantile(Dt, q))
        guided, off, ref = (_render(lin, D, K, d_f, r) for D, r in
                            ((N, "guided"), (N, "off"), (Dt, "off")))
        rem_in, must_in = sharp_remnants(guided, off, N, K, d_f)
        rem_both, must_both = sharp_remnants(guided, off, (N, refined), K, d_f)
        rem_t, must_t = sharp_remnants(guided, ref, Dt, K, d_f)
        rem_off, _ = sharp_remnants(off, ref, Dt, K, d_f)
        edge_both, _ = sharp_edges(guided, off, (N, refined), K, d_f)
        edge_t, _ = sharp_edges(guided, ref, Dt, K, d_f)
        edge_off, _ = sharp_edges(off, ref, Dt, K, d_f)
        over = _render(lin, shrunk, K, d_f, "guided")
        extra = {}
        if matting:
            from mpib_validate.bench.matting import matte_render

            matted = _display(matte_render(lin, refined, K, d_f, GAMMA))
            extra = {"remnants_both_matting": int(sharp_remnants(matted, off, (N, refined), K,
                                                                 d_f)[0].sum()),
                     "remnants_true_matting": int(sharp_remnants(matted, ref, Dt, K,
                                                                 d_f)[0].sum()),
                     "psnr_matting": psnr(ref, matted)}
        rows.append({"photo": name, "focus": focus, "K": K, "disp_focus": d_f,
                     "width": Dt.shape[1], "height": Dt.shape[0],
                     "must_blur_input": int(must_in.sum()), "remnants_input": int(rem_in.sum()),
                     "must_blur_both": int(must_both.sum()), "remnants_both": int(rem_both.sum()),
                     "must_blur_true": int(must_t.sum()), "remnants_true": int(rem_t.sum()),
                     "remnants_true_off": int(rem_off.sum()),
                     "edges_both": int(edge_both.sum()), "edges_true": int(edge_t.sum()),
                     "edges_true_off": int(edge_off.sum()),
                     "psnr_guided": psnr(ref, guided), "psnr_off": psnr(ref, off),
                     "remnants_true_overshoot": int(sharp_remnants(over, ref, Dt, K,
                                                                   d_f)[0].sum()),
                     "psnr_overshoot": psnr(ref, over), **extra})
        if outputs is not None:
            outputs[(name, focus)] = {"input": img / 255.0, "default": guided, "off": off,
                                      "reference": ref, "remnants": rem_t, "disparity": N}
            if matting:
                outputs[(name, focus)]["matting"] = matted
    return rows


def crops_figure(outputs: dict, path: Path, crop: int = 48) -> list[dict]:
    """Boundary crops (x3): per photograph and focus, the ``crop`` px window holding the
    most true-disparity remnants of the default (else the strongest disparity edge);
    columns: input, default (guided), refinement off, the matting variant (where the
    outputs hold it), true-disparity reference."""
    from PIL import Image
    from scipy import ndimage

    from mpib_validate.runtime.io.atomic import atomic_path

    rows, where = [], []
    h = crop // 2
    for (name, focus), o in outputs.items():
        N = o["disparity"]
        score = ndimage.uniform_filter(o["remnants"].astype(float), crop)
        if score.max() <= 0:
            score = ndimage.maximum_filter(N, 9) - ndimage.minimum_filter(N, 9)
        score[:h], score[-h:], score[:, :h], score[:, -h:] = -1, -1, -1, -1
        y, x = np.unravel_index(int(score.argmax()), score.shape)
        where.append({"photo": name, "focus": focus, "centre": [int(y), int(x)]})
        tiles = [np.pad((np.clip(o[k][y - h:y + h, x - h:x + h], 0, 1) * 255).astype(np.uint8),
                        ((2, 2), (2, 2), (0, 0)), constant_values=255)
                 for k in ("input", "default", "off", "matting", "reference") if k in o]
        rows.append(np.concatenate(tiles, axis=1))
    fig = Image.fromarray(np.concatenate(rows, axis=0))
    fig = fig.resize((fig.width * 3, fig.height * 3), Image.NEAREST)
    with atomic_path(path) as tmp:
        fig.save(tmp, format="PNG")
    return where


#: The light-patch check (:func:`light_patches`): the network map's side (px), the
#: paper's K and focus (on the helmet the astronaut holds), and a display-level step
#: that a viewer sees in a smooth blur.
PATCH_MAP_PX, PATCH_K, PATCH_FOCUS, PATCH_LEVELS = 128, 30.0, 232 / 255, 10


def light_patches() -> dict:
    """What :func:`mpib_validate.metrics.sharp_remnants` does not count: light patches
    inside a surface blurred by less than its 6 px. The astronaut's network-like map
    brought down to :data:`PATCH_MAP_PX` px (area mean, 8 bits), upsampled as ``mpib
    refocus`` does (:func:`mpib_validate.runtime.io.photo.upsample_disparity`), refocused
    with K = 30 and focus 232/255 (her hair blurs by 4 to 6 px) with the default
    refinement and without. Over the head's inside (the map's near region above 150/255,
    8 px in from its edge, in the head's box), the share of pixels more than
    :data:`PATCH_LEVELS` display levels lighter with the refinement than without, and the
    largest difference (levels). Without the refinement's jump at the hair's outline no
    hidden background lies behind the hair, so the unrefined output is the smooth
    reference there."""
    from PIL import Image
    from scipy import ndimage

    from mpib_validate.runtime.io.photo import upsample_disparity

    img, truth = true_disparity("astronaut")
    network = network_disparity(truth)
    side = PATCH_MAP_PX
    low = np.asarray(Image.fromarray(network.astype(np.float32)).resize((side, side), Image.BOX))
    D = upsample_disparity(np.round(low * 255) / 255, network.shape)
    lin = (img.astype(np.float64) / 255.0) ** GAMMA
    lighter = 255 * (_render(lin, D, PATCH_K, PATCH_FOCUS, "guided")
                     - _render(lin, D, PATCH_K, PATCH_FOCUS, "off")).mean(axis=-1)
    head = np.zeros(D.shape, bool)
    head[:150, 140:320] = True
    head &= ndimage.binary_erosion(D > 150 / 255, iterations=8)
    return {"photo": "astronaut", "map_px": side, "K": PATCH_K, "disp_focus": PATCH_FOCUS,
            "levels": PATCH_LEVELS, "head_px": int(head.sum()),
            "share": float((lighter[head] > PATCH_LEVELS).mean()),
            "max_levels": float(lighter[head].max())}


def run(out: Path | None = None, photos=PHOTOS, matting: bool = True) -> dict:
    """The remnant table (rows per photograph and focus; with ``matting``, the matting
    variant's columns too, where pymatting is installed), the light-patch check
    (:func:`light_patches`) and, with ``out``, the crops figure ``out / "remnants.png"``."""
    import importlib.util

    if matting and importlib.util.find_spec("pymatting") is None:
        print("bench photos: pymatting is not installed (the `matting` extra): the matting "
              "variant is left out", flush=True)
        matting = False
    outputs = {} if out is not None else None
    rows = [r for name in photos for r in photo_rows(name, outputs, matting)]
    result = {"rows": rows}
    if "astronaut" in photos:
        result["light_patches"] = light_patches()
    if out is not None:
        result["figure"] = {"path": "remnants.png",
                            "crops": crops_figure(outputs, out / "remnants.png")}
    return result


def markdown(result: dict) -> list[str]:
    lines = ["## Sharp remnants on shipped photographs (network-like disparity)", "",
             f"scikit-image photographs; true disparity hand-built (the motorcycle: its stereo "
             f"disparity); input = the network-like map (2 px fattening, blur 0.8 % of the "
             f"short side, 4x down, noise, 1.5 px shift, 8 bits); K = {K_FRACTION:.0%} of the "
             f"width, gamma {GAMMA}, default preset. Remnants "
             "(`metrics.sharp_remnants`) against the unrefined output: where the input "
             "and the refined map both blur by > 6 px (lines drawn into the blur, the "
             "issue's measure), and where the input map alone does (also counting an edge "
             "the refinement moved into the blur); against the true-disparity render "
             "where the true disparity blurs (also misplaced edges); PSNR against that "
             "render (display values).", "",
             f"The `--map-overshoot {OVERSHOOT_PX}` columns: the default fed the input map "
             f"shrunk by {OVERSHOOT_PX} px first (`runtime.io.photo.shrink_overshoot`), "
             "against the truth.", "",
             "| photo | focus | K | remnants vs off, both maps blur | input map blurs | "
             "must-blur (true) | remnants vs truth: default | refine off | PSNR default | "
             f"PSNR off | --map-overshoot {OVERSHOOT_PX}: remnants vs truth | PSNR |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def share(n, of):
        return f"{n} ({100 * n / max(1, of):.3f} %)"

    if any("psnr_matting" in r for r in result["rows"]):
        lines[-2] += " matting: remnants vs off, both | matting vs truth | PSNR matting |"
        lines[-1] += "---|---|---|"
    for r in result["rows"]:
        matted = (f" {r['remnants_both_matting']} | {r['remnants_true_matting']} | "
                  f"{r['psnr_matting']:.2f} |" if "psnr_matting" in r else "")
        lines.append(f"| {r['photo']} ({r['width']}x{r['height']}) | {r['focus']} | "
                     f"{r['K']:.1f} | {share(r['remnants_both'], r['must_blur_both'])} | "
                     f"{share(r['remnants_input'], r['must_blur_input'])} | "
                     f"{r['must_blur_true']} | {r['remnants_true']} | {r['remnants_true_off']} | "
                     f"{r['psnr_guided']:.2f} | {r['psnr_off']:.2f} | "
                     f"{r['remnants_true_overshoot']} | {r['psnr_overshoot']:.2f} |" + matted)
    lines += ["", "Sharp edges inside the blur (`metrics.sharp_edges`: a step, gradient above "
              "0.4 of its 5x5 window's range, that the reference does not have within a "
              "pixel; the strips and gaps that the top-hat does not count), same regions:", "",
              "| photo | focus | default vs off, both maps blur | default vs truth | "
              "refine off vs truth |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        if "edges_true" in r:
            lines.append(f"| {r['photo']} | {r['focus']} | {r['edges_both']} | "
                         f"{r['edges_true']} | {r['edges_true_off']} |")
    lp = result.get("light_patches")
    if lp:
        lines += ["", f"Light patches inside a surface blurred by less than 6 px (which the "
                  f"remnants do not count; `remnants.light_patches`): the astronaut's map at "
                  f"{lp['map_px']} px, upsampled, K = {lp['K']:g}, focus "
                  f"{255 * lp['disp_focus']:.0f}/255 (the hair blurs by 4 to 6 px): "
                  f"{100 * lp['share']:.2f} % of the head's inside ({lp['head_px']} px) more "
                  f"than {lp['levels']} display levels lighter with the default refinement "
                  f"than without it, {lp['max_levels']:.0f} levels at most."]
    fig = result.get("figure")
    if fig:
        lines += ["", "Boundary crops (x3), one row per photograph and focus (near, far), at "
                  "the window with the most remnants against the truth (else the strongest "
                  "disparity edge); columns: input, default, refinement off, "
                  + ("the matting variant (`bench.matting`), "
                     if any("psnr_matting" in r for r in result["rows"]) else "")
                  + "true-disparity render.", "", f"![remnants]({fig['path']})"]
    return lines + [""]
