"""Blender's compositor Defocus node (bpy 4.2 to 5.x): the Z-buffer post-process to beat.

:func:`defocus` feeds an all-in-focus image and its depth (planar Z, scene units =
metres) through ``Image -> Defocus -> output`` in the scene's compositor tree (made by
:func:`.blender_compat.compositor_tree`; the output is a Group Output with an ``Image``
socket on 5.x, a Composite node on 4.x: :func:`.blender_compat.tree_output`), renders
it (no 3D render happens: the tree has no Render Layers node), and reads the EXR it
writes. The node is set up as an artist would: Z-buffer mode (``use_zbuffer = True``),
its own ``f_stop`` copied from the camera, a disk bokeh, ``blur_max`` at least the
largest radius it will compute, and a scene camera with the same lens, sensor (fit
horizontal) and focus distance. On 4.x its low-quality ``use_preview`` mode (on by
default there; 5.x has no such mode) is switched off.

What the node does (read in its source, ``node_composite_defocus.cc``, and measured
by :func:`measure_defects` on 5.0.1; ``tests/test_cycles.py`` checks them on every
Blender that ``make test-blender-versions`` covers):

- CoC radius (Potmesil-Chakravarty eq. 8) ``r = A |d - d_f| * z_f / (z_f - f)``
  pixels: the true thin-lens radius times an extra factor ``z_f / (z_f - f)``
  (``f`` the focal length in metres);
- pixels per metre of sensor: with ``sensor_fit = 'AUTO'`` on a square or portrait
  image it divides the height by the sensor *height*, where Cycles uses the sensor
  width along the larger side: radii 1.5x too large with the default 36 x 24 mm sensor;
- a gather over a square window of half-size ``blur_max`` (measured in 5.0.1: a near
  dot whose radius exceeds the circle of confusion at infinity is not cut, and the
  time grows with ``blur_max`` even when every radius is smaller: 4x ``blur_max``,
  about 4-5x the time; so does 4.5.15, while on 4.2.23 the time does not grow with
  ``blur_max``, ratio 0.8 to 1.1); its disk kernel is an image of ``2 blur_max + 1`` pixels sampled
  bilinearly, so the output also changes slightly with ``blur_max``;
- a pixel takes a neighbour only when the offset is within both radii, so a blurred
  foreground never spreads over an in-focus background (hard foreground edges), and
  the result is normalised per pixel, so energy is not conserved where radii change:
  a highlight on a defocused foreground's edge keeps about half its energy, one in
  its middle gains some.

The module imports ``bpy`` lazily. Each call resets Blender to empty factory settings.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from mpib_validate.runtime.blender import compat as _compat
from mpib_validate.runtime.io import exr as _exr

#: Blender's default sensor height (mm), used by the AUTO-fit defect.
DEFAULT_SENSOR_HEIGHT_MM = 24.0


def _bpy():
    from mpib_validate.blender.cycles import _bpy as get

    return get()


def node_radius(depth, camera_settings: dict, width: int, height: int, f_stop: float | None = None,
                sensor_fit: str = "HORIZONTAL",
                sensor_height_mm: float = DEFAULT_SENSOR_HEIGHT_MM) -> np.ndarray:
    """The radius (pixels) the Defocus node computes for planar depth ``depth`` (metres),
    re-derived from its source: ``|(V_u - V_p) f / (N V_u)| / 2 * pixels_per_metre`` with
    ``V = f z / (z - f)``; no ``blur_max`` clamp. ``camera_settings`` as
    ``Camera.cycles_settings()``."""
    f = camera_settings["lens_mm"] / 1000.0
    n = float(camera_settings["fstop"] if f_stop is None else f_stop)
    z_f = camera_settings["focus_distance"]
    z_f = 1e7 if math.isinf(z_f) else z_f  # as cycles.FAR_FOCUS
    sw = camera_settings["sensor_width_mm"] / 1000.0
    sh = sensor_height_mm / 1000.0
    if sensor_fit == "HORIZONTAL" or (sensor_fit == "AUTO" and width > height):
        ppm = width / sw
    else:
        ppm = height / sh
    z = np.asarray(depth, np.float64)
    v_u = f * z / (z - f)
    v_p = f * z_f / (z_f - f)
    return np.abs((v_u - v_p) * f / (n * v_u)) / 2.0 * ppm


def _write_input(path: Path, rgba: np.ndarray, depth: np.ndarray) -> None:
    ch = _exr.channels_from_rgba(rgba.astype(np.float32), "ViewLayer.Combined.")
    ch["ViewLayer.Depth.Z"] = np.ascontiguousarray(depth, np.float32)
    _exr.write_exr(path, ch)


def _setup(bpy, in_path: Path, width: int, height: int, camera_settings: dict, *,
           f_stop: float, blur_max: float, sensor_fit: str, sensor_height_mm: float,
           bokeh: str, use_zbuffer: bool, z_scale: float, threads: int, with_node: bool,
           angle: float = 0.0):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    r = sc.render
    r.resolution_x, r.resolution_y = int(width), int(height)
    r.resolution_percentage = 100
    r.use_compositing = True
    r.use_sequencer = False
    r.threads_mode = "FIXED" if threads else "AUTO"
    if threads:
        r.threads = int(threads)
    sc.view_settings.view_transform = "Standard"
    im = r.image_settings
    im.file_format = "OPEN_EXR"
    im.color_mode = "RGBA"
    im.color_depth = "32"
    im.exr_codec = "ZIP"

    cam = bpy.data.cameras.new("Camera")
    cam.lens = camera_settings["lens_mm"]
    cam.sensor_width = camera_settings["sensor_width_mm"]
    cam.sensor_height = sensor_height_mm
    cam.sensor_fit = sensor_fit
    z_f = camera_settings["focus_distance"]
    cam.dof.use_dof = True
    cam.dof.focus_distance = float(1e7 if math.isinf(z_f) else z_f)
    cam.dof.aperture_fstop = float(min(camera_settings["fstop"], 1e6))
    obj = bpy.data.objects.new("Camera", cam)
    sc.collection.objects.link(obj)
    sc.camera = obj

    img = bpy.data.images.load(str(in_path), check_existing=False)
    nt = _compat.compositor_tree(sc, create=True, name="Defocus")
    nt.nodes.clear()  # 4.x starts with Render Layers -> Composite: no 3D render wanted
    src = nt.nodes.new("CompositorNodeImage")
    src.image = img
    # the multilayer EXR's Combined pass: "Combined" on 5.x, "Image" on 4.x
    colour = src.outputs.get("Combined") or src.outputs["Image"]
    out = _compat.tree_output(nt).inputs[_compat.IMAGE_SOCKET]
    if not with_node:
        nt.links.new(colour, out)
        return sc
    node = nt.nodes.new("CompositorNodeDefocus")
    _compat.set_option(node, "use_zbuffer", bool(use_zbuffer))
    _compat.set_option(node, "z_scale", float(z_scale))
    _compat.set_option(node, "f_stop", float(f_stop))
    _compat.set_option(node, "blur_max", float(blur_max))
    _compat.set_option(node, "bokeh", bokeh)
    _compat.set_option(node, "angle", float(angle))
    if "use_preview" in node.bl_rna.properties:  # 4.x: on by default, a low-quality mode
        node.use_preview = False
    nt.links.new(colour, node.inputs["Image"])
    nt.links.new(src.outputs["Depth"], node.inputs["Z"])
    nt.links.new(node.outputs["Image"], out)
    return sc


def _run(bpy, sc, path: Path) -> tuple[np.ndarray, float]:
    sc.render.filepath = str(path)
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True, scene=sc.name)
    seconds = time.perf_counter() - t0
    return _exr.rgba_from(_exr.read_exr(path)), seconds


def defocus(rgb: np.ndarray, depth: np.ndarray, camera_settings: dict, *,
            blur_max: float | None = None, f_stop: float | None = None,
            sensor_fit: str = "HORIZONTAL", sensor_height_mm: float = DEFAULT_SENSOR_HEIGHT_MM,
            bokeh: str = "CIRCLE", use_zbuffer: bool = True, z_scale: float = 1.0,
            threads: int = 0, repeats: int = 1, timing: bool = True, angle: float = 0.0,
            info: dict | None = None,
            keep: str | os.PathLike | None = None) -> tuple[np.ndarray, float]:
    """Blur ``rgb`` with Blender's Defocus node.

    Args:
        rgb: ``(H, W, 3)`` or ``(H, W, 4)`` linear radiance (premultiplied if RGBA;
            alpha 1 if absent), the all-in-focus image.
        depth: ``(H, W)`` planar depth in metres (1e10 where nothing, as Cycles' Z).
        camera_settings: ``Camera.cycles_settings()``: ``lens_mm``, ``sensor_width_mm``,
            ``fstop``, ``focus_distance`` (metres, ``inf`` allowed).
        blur_max: the node's ``blur_max`` (pixels); default the largest radius the node
            computes over ``depth`` (:func:`node_radius`), rounded up, plus 1.
        f_stop: the node's own f-stop; default the camera's.
        sensor_fit: the camera's sensor fit the node sees (``AUTO`` shows its defect).
        bokeh, angle: the node's Bokeh Type (``CIRCLE``, ``TRIANGLE`` to ``OCTAGON``) and
            its rotation in radians.
        use_zbuffer, z_scale: Z-buffer mode (default) or the node's scale mode (radius
            ``= Z * z_scale`` pixels, clamped to ``blur_max``).
        repeats: time the node this many times (the fastest run counts).
        timing: False skips the bypass run (``seconds`` is then the whole render op).
        info: if given, filled with ``blur_max``, ``f_stop``, ``total_seconds`` (the
            render op with the node), ``baseline_seconds`` (the same tree without it).

    Returns:
        ``(rgb, seconds)``: ``(H, W, 3)`` float32 output (its alpha is in
        ``info["alpha"]``), and the node's own time in seconds: the render op with the
        node minus the same op with the node bypassed (loading the EXR, writing the
        output), fastest of ``repeats``.
    """
    rgb = np.asarray(rgb, np.float32)
    h, w = rgb.shape[:2]
    if rgb.shape[2] == 3:
        rgba = np.concatenate([rgb, np.ones((h, w, 1), np.float32)], axis=-1)
    else:
        rgba = rgb[..., :4]
    depth = np.asarray(depth, np.float32)
    if depth.shape != (h, w):
        raise ValueError(f"depth {depth.shape} does not match the image {(h, w)}")
    n = float(camera_settings["fstop"] if f_stop is None else f_stop)
    if blur_max is None:
        if use_zbuffer:
            rad = node_radius(depth, camera_settings, w, h, n, sensor_fit, sensor_height_mm)
        else:
            rad = depth * z_scale
        blur_max = float(math.ceil(np.nanmax(rad)) + 1)
    bpy = _bpy()
    with tempfile.TemporaryDirectory(prefix="mpib-defocus-") as tmp:
        d = Path(keep) if keep is not None else Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        in_path = d / "defocus_input.exr"
        _write_input(in_path, rgba, depth)
        kw = dict(f_stop=n, blur_max=blur_max, sensor_fit=sensor_fit,
                  sensor_height_mm=sensor_height_mm, bokeh=bokeh, use_zbuffer=use_zbuffer,
                  z_scale=z_scale, threads=threads, angle=angle)
        base_t, node_t = [], []
        for _ in range(max(1, int(repeats))):
            if timing:
                sc = _setup(bpy, in_path, w, h, camera_settings, with_node=False, **kw)
                base_t.append(_run(bpy, sc, d / "defocus_bypass.exr")[1])
            else:
                base_t.append(0.0)
            sc = _setup(bpy, in_path, w, h, camera_settings, with_node=True, **kw)
            out, t = _run(bpy, sc, d / "defocus_output.exr")
            node_t.append(t)
    seconds = max(0.0, min(node_t) - min(base_t))
    if info is not None:
        info.update(blur_max=blur_max, f_stop=n, total_seconds=min(node_t),
                    baseline_seconds=min(base_t), alpha=out[..., 3].copy())
    return out[..., :3].copy(), seconds


# --------------------------------------------------------------------------------------
# The node's defects, as figures


def _moment(img: np.ndarray) -> tuple[float, float]:
    """Second moment (pixels^2) of channel 0 about its centroid, and its sum."""
    p = np.asarray(img, np.float64)[..., 0]
    yy, xx = np.mgrid[:p.shape[0], :p.shape[1]]
    s = p.sum()
    cy, cx = (p * yy).sum() / s, (p * xx).sum() / s
    return float((p * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum() / s), float(s)


def effective_radius(rgb: np.ndarray, depth: np.ndarray, camera_settings: dict,
                     blur_max: float, bracket: tuple[float, float] | None = None,
                     tol: float = 1e-3, **kw) -> float:
    """The uniform radius (pixels) the node used on a single-dot image, measured: the
    radius that the node's scale mode (radius = Z * 1, exactly) needs to give the same
    second moment, found by bisection in ``bracket`` (default ``[0.5, blur_max]``) to
    ``tol`` (relative). The node is run in Z-buffer mode with ``kw`` (e.g.
    ``sensor_fit``) on ``rgb``/``depth``."""
    out, _ = defocus(rgb, depth, camera_settings, blur_max=blur_max, timing=False, **kw)
    target, _ = _moment(out)
    h, w = rgb.shape[:2]
    lo, hi = bracket if bracket is not None else (0.5, float(blur_max))
    skw = {k: v for k, v in kw.items() if k not in ("sensor_fit", "sensor_height_mm", "f_stop")}
    while hi - lo > tol * hi:
        mid = 0.5 * (lo + hi)
        o, _ = defocus(rgb, np.full((h, w), mid, np.float32), camera_settings,
                       blur_max=blur_max, use_zbuffer=False, z_scale=1.0, timing=False, **skw)
        if _moment(o)[0] < target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def measure_defects(size: int = 64, blur_parameter: float = 40.0, focus_disparity: float = 0.5,
                    threads: int = 0) -> dict:
    """Measure the Defocus node's known defects on small synthetic inputs.

    The camera: ``size`` x ``size`` pixels, 50 mm lens on a 36 mm sensor (so
    ``f = 0.05`` m), ``A = blur_parameter``, focus ``z_f = 1/focus_disparity`` metres.
    Returns a dict of figures (each with what the ideal value is):

    - ``coc_factor``: measured node radius / true ``A |d - d_f|`` for a dot at
      ``d = d_f / 2`` (ideal 1); ``coc_factor_predicted = z_f / (z_f - f)``.
    - ``auto_fit_factor``: radius with ``sensor_fit='AUTO'`` / radius with
      ``'HORIZONTAL'`` on a square image (ideal 1: Cycles renders both alike);
      ``auto_fit_predicted = sensor_width / sensor_height = 36 / 24``.
    - ``search_seconds``: node time for ``blur_max = m, 2m, 4m`` with ``m`` the
      largest radius + 1 on a 2x-size noise image whose radii stay below ``m``
      (ideal: flat); ``search_cost_ratio`` = time(4m) / time(m);
      ``search_output_change`` = largest output change between them (ideal 0; the
      node's disk kernel is an image of ``2 blur_max + 1`` pixels sampled bilinearly,
      so its edge changes a little with ``blur_max``).
    - ``fg_spread_fraction``: light a defocused foreground square spreads outside its
      silhouette over an in-focus background, node / ray tracer (ideal 1).
    - ``highlight_energy``: energy of a highlight on the edge texel of that defocused
      foreground, node output / input (ideal 1: nothing occludes it);
      ``highlight_energy_inside``: the same 2 px inside the edge;
      ``highlight_energy_centre``: at the square's centre, where its whole disk stays
      on the square (ideal 1; the per-pixel renormalisation near the square's edge
      gives energy back there).
    """
    from mpib_validate.runtime import samples as _samples
    from mpib_validate.cards import trace as _trace
    from mpib_validate.runtime.camera import Camera
    from mpib_validate.cards.scene import Card, Plane, Scene

    n = int(size)
    cam = Camera(n, n, blur_parameter, focus_disparity)
    cs = cam.cycles_settings()
    f = cs["lens_mm"] / 1000.0
    z_f = cs["focus_distance"]
    out: dict = {}
    dot = np.zeros((n, n, 3), np.float32)
    dot[n // 2, n // 2] = 100.0
    kw = dict(threads=threads)

    # 1. CoC factor z_f / (z_f - f)
    d = 0.5 * focus_disparity
    r_true = cam.blur_radius(d)
    bm = float(math.ceil(2 * r_true) + 2)
    r_node = effective_radius(dot, np.full((n, n), 1.0 / d, np.float32), cs, bm,
                              bracket=(0.5 * r_true, 1.5 * r_true), **kw)
    out.update(coc_factor=r_node / r_true, coc_factor_predicted=z_f / (z_f - f),
               coc_true_radius=r_true)

    # 2. AUTO sensor fit on a square image
    r_auto = effective_radius(dot, np.full((n, n), 1.0 / d, np.float32), cs, 2 * bm,
                              bracket=(0.5 * r_true, 3.0 * r_true), sensor_fit="AUTO", **kw)
    out.update(auto_fit_factor=r_auto / r_node,
               auto_fit_predicted=cs["sensor_width_mm"] / DEFAULT_SENSOR_HEIGHT_MM)

    # 3. search window = blur_max: cost grows although no radius exceeds m
    m2 = 2 * n
    rng = np.random.default_rng(0)
    noise = rng.random((m2, m2, 3)).astype(np.float32)
    ramp = np.tile(np.linspace(1.0 / focus_disparity, 4.0 / focus_disparity, m2,
                               dtype=np.float32), (m2, 1))
    cam2 = Camera(m2, m2, blur_parameter, focus_disparity)
    cs2 = cam2.cycles_settings()
    m = float(math.ceil(node_radius(ramp, cs2, m2, m2).max()) + 1)
    secs, outs = [], []
    for k in (1, 2, 4):
        o, t = defocus(noise, ramp, cs2, blur_max=k * m, repeats=2, **kw)
        secs.append(t)
        outs.append(o)
    out.update(search_blur_max=[k * m for k in (1, 2, 4)], search_seconds=secs,
               search_cost_ratio=secs[-1] / max(secs[0], 1e-9),
               search_output_change=float(max(np.abs(o - outs[0]).max() for o in outs)))

    # 4. a defocused foreground over an in-focus background
    d_fg = focus_disparity * 1.5
    lo, hi = n // 4, n - n // 4
    depth = np.full((n, n), 1.0 / focus_disparity, np.float32)
    depth[lo:hi, lo:hi] = 1.0 / d_fg
    white = np.zeros((n, n, 3), np.float32)
    white[lo:hi, lo:hi] = 1.0
    o, _ = defocus(white, depth, cs, timing=False, **kw)
    outside = np.ones((n, n), bool)
    outside[lo:hi, lo:hi] = False
    margin = int(math.ceil(cam.blur_radius(1e-9))) + 2
    bg = np.zeros((n + 2 * margin, n + 2 * margin, 4), np.float32)
    bg[..., 3] = 1.0
    fg = np.ones((hi - lo, hi - lo, 4), np.float32)
    scene = Scene(cam, [Card("bg", bg, Plane.fronto(focus_disparity), (-margin, -margin)),
                        Card("fg", fg, Plane.fronto(d_fg), (lo, lo))]).validate()
    ref, _ = _trace.trace(scene, _samples.stratified(4096), notices=False)
    out.update(fg_spread_fraction=float(o[..., 0][outside].sum() / ref[..., 0][outside].sum()),
               fg_radius=cam.blur_radius(d_fg))

    # 5. highlight energy on the defocused foreground's edge
    base, _ = defocus(np.zeros((n, n, 3), np.float32), depth, cs, timing=False, **kw)
    for key, col in (("highlight_energy", lo), ("highlight_energy_inside", lo + 2),
                     ("highlight_energy_centre", n // 2)):
        hl = np.zeros((n, n, 3), np.float32)
        hl[n // 2, col] = 100.0
        o, _ = defocus(hl, depth, cs, timing=False, **kw)
        out[key] = float((o - base)[..., 0].sum() / 100.0)
    return out


def score_against_tracer(scene, reference: np.ndarray | None = None, ref_samples: int = 4096,
                         threads: int = 0) -> dict:
    """Run the node on Cycles' all-in-focus render and Z pass of ``scene`` and score it
    against the ray tracer (``reference`` or ``trace.trace`` with ``ref_samples`` Sobol
    samples): :func:`mpib_validate.cards.evaluate.score` with the card-scene occlusion mask
    (``psnr``, ``psnr_ob``, ``ssim``, ...), plus ``seconds`` (the node alone) and the
    same scores for the unblurred all-in-focus image (``aif_psnr``, ``aif_psnr_ob``)."""
    from mpib_validate.blender import cycles as _cycles
    from mpib_validate.cards import evaluate as _evaluate
    from mpib_validate.runtime import samples as _samples
    from mpib_validate.cards import trace as _trace

    if reference is None:
        reference, _ = _trace.trace(scene, _samples.stratified(ref_samples), notices=False)
    aif, z, _ = _cycles.render(scene, 1, dof=False, threads=threads)
    info: dict = {}
    out, seconds = defocus(aif, z, scene.camera.cycles_settings(), threads=threads, info=info)
    mask = _evaluate.card_scene_mask(scene)
    res = _evaluate.score(reference, out, mask, with_flip=False)
    base = _evaluate.score(reference, aif, mask, with_flip=False)
    res.update(seconds=seconds, blur_max=info["blur_max"], aif_psnr=base["psnr"],
               aif_psnr_ob=base["psnr_ob"])
    return res
