"""Cycles (Blender 4.2 to 5.x, ``bpy``) thin-lens references for card scenes.

Each card becomes a planar quad whose pinhole projection is exactly its texture
extent; the texture is looked up through the pinhole projection of the shading point
(computed in the shader), so tilted cards are mapped projectively, exactly as the ray
tracer of :mod:`mpib_validate.cards.trace` does (Eq. 15: a hit is looked up where it
projects through the lens centre). Materials are emission (strength 1, the texel's
linear colour) mixed with a Transparent BSDF by the texel's alpha, so Cycles'
front-to-back transparency compositing is the tracer's "over".

Conventions (see ``docs/camera.md``):

- Blender world axes are the project's camera axes: the camera sits at the origin,
  rotated 180 degrees about X, so it looks down world +Z with world -Y up; a world
  point ``(X, Y, Z)`` (scene units, 1 unit = 1 m) projects to
  ``x = f_px X / Z, y = f_px Y / Z`` (pixels from the image centre, y down).
- Thin lens: ``sensor_fit = 'HORIZONTAL'``, ``f_px = lens_mm / sensor_mm * W``,
  aperture radius ``R = lens / (2 N)`` in scene units, the camera's aperture shape
  (``Camera.aperture``: blades, rotation, ratio, Cycles' own conventions; a disk by
  default), focus distance ``z_f = 1/d_f`` (``d_f = 0``: 1e7 units).
- Pixel model: the Box pixel filter (Cycles forces its width to 1 pixel, whatever
  ``filter_width`` says) spreads the samples uniformly over the pixel square: the
  canonical model's box average; Closest texture interpolation (nearest texel).
  Cycles puts sample 0 at the pixel centre; :func:`build_scene` skips it (a sample
  subset) so that the average is unbiased at any sample count. The sampling pattern is
  Tabulated Sobol on every Blender (4.2, 4.5 and 5.3 default to another one).
- Pinhole views (``dof=False``) sample the pixel centres instead (Gaussian filter of
  width 0.01: every sample within 0.02 px of the centre, measured with 4096 samples on
  stripes): there every pixel sees exactly one texel of each card (the lookup
  is the pinhole projection, and texel edges are pixel edges), so the centre value
  *is* the box average, and no sample comes near a texel edge. A box sample at a pixel
  edge is ambiguous in float32: bpy 5.3's blue-noise pattern put sample 5 of pixel
  (26, 19) (seed 0, the 48x40 'varying' test scene) at the pixel's right edge, where
  the projective lookup (``X/Z``, scale and offset, ``u W`` in the texture) gives the
  texel coordinate 23.0 exactly, so Closest read the next texel (relative error
  0.157). Pixel centres keep 0.48 px from every edge, against lookup rounding below
  3e-5 px (measured on bpy 5.0.1 and 5.3.0 by moving the centres towards a texel edge
  with the camera shift: every read is right from 3e-5 px on, 2 of 607 are wrong at
  1e-5 px, most at 1e-6 px).
- No Russian roulette on transparent bounces (``min_transparent_bounces`` =
  ``transparent_max_bounces``): less noise, and an exact Z pass behind transparent cards.
- Outputs are linear radiance: ``rgba[..., :3]`` premultiplied, ``rgba[..., 3]`` the
  coverage (film transparent), depth planar along the view axis (scene units) of the
  front-most card with alpha >= 0.5 at the pixel centre, 1e10 where there is none.

Version differences go through :mod:`.blender_compat`. Measured on 2 CPU cores
(bpy 5.0.1): see :func:`noise_vs_spp`; all-in-focus renders
equal the tracer's to float rounding, and defocused ones agree with it to the level of
Monte Carlo noise (:func:`agreement`, ``tests/test_cycles.py``).

``bpy`` is imported inside the functions only, so the package imports without it.
Each call resets Blender to empty factory settings: do not mix with other ``bpy`` work
in the same process.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from mpib_validate.runtime.blender.compat import set_multilayer_exr, set_sample_subset
from mpib_validate.cards.scene import Scene

#: Depth Cycles writes where no surface is solid (scene units).
BACKGROUND_DEPTH = 1e10
#: Focus distance used for ``d_f = 0`` (focus at infinity), scene units. The focal
#: point is then so far that Cycles' float32 ray direction equals the pinhole one:
#: rays from every lens point are parallel, which *is* focus at infinity.
FAR_FOCUS = 1e7
#: Fault injections for the tests (each must make the cross-renderer test fail).
FAULTS = ("offset", "shift", "flip", "radius")
#: Radiance added by the ``offset`` fault (linear units).
FAULT_OFFSET = 0.02
#: Aperture radius factor of the ``radius`` fault.
FAULT_RADIUS = 1.5


def _bpy():
    try:
        import bpy  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("Cycles rendering needs Blender as a Python module: "
                          "pip install 'mpib-validate[blender]' (bpy 5.0.1 on Python 3.11, "
                          "5.3.0 on Python 3.13)") from exc
    return bpy


def available() -> bool:
    """True when ``bpy`` imports (Cycles can run)."""
    try:
        import bpy  # noqa: F401
    except ImportError:
        return False
    return True


def camera_settings(scene: Scene, sensor_width_mm: float = 36.0) -> dict:
    """Blender camera settings for ``scene.camera`` (see ``Camera.cycles_settings``):
    ``lens_mm``, ``sensor_width_mm``, ``sensor_fit``, ``fstop`` (dimensionless, inf for
    a pinhole), ``focus_distance`` (scene units; ``inf`` for ``d_f = 0``)."""
    return scene.camera.cycles_settings(sensor_width_mm)


def card_corners(scene: Scene, card) -> np.ndarray:
    """World (= project camera) coordinates of the 4 corners of ``card``'s texture
    extent, back-projected onto its plane: ``(4, 3)`` float64 in scene units, in the
    order (x0, y0), (x1, y0), (x1, y1), (x0, y1) of image coordinates (pixels)."""
    cam = scene.camera
    f = float(cam.focal_length_px)
    x0, x1, y0, y1 = card.extent(cam)
    xs = np.array([x0, x1, x1, x0], np.float64)
    ys = np.array([y0, y0, y1, y1], np.float64)
    z = 1.0 / card.plane.disparity(xs, ys)
    return np.stack([xs * z / f, ys * z / f, z], axis=1)


def _reset(bpy):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def camera_object(bpy, bl_scene, settings: dict, dof: bool, clip_end: float,
                  shift_x: float = 0.0, width: int | None = None):
    """Add the project's camera to ``bl_scene``: at the origin, turned 180 degrees about
    X, so world axes = camera axes (x right, y down, looking down +Z).

    ``settings`` as ``Camera.cycles_settings()`` (``lens_mm``, ``sensor_width_mm``,
    ``sensor_fit``, ``fstop``, ``focus_distance``: ``inf`` becomes :data:`FAR_FOCUS`,
    and the aperture's ``aperture_blades``, ``aperture_rotation`` (radians),
    ``aperture_ratio``: a disk where left out); ``shift_x`` in pixels to the right
    (needs ``width``)."""
    data = bpy.data.cameras.new("Camera")
    data.type = "PERSP"
    data.lens_unit = "MILLIMETERS"
    data.sensor_fit = settings["sensor_fit"]
    data.sensor_width = settings["sensor_width_mm"]
    data.lens = settings["lens_mm"]
    data.shift_y = 0.0
    # in units of the sensor width (fit horizontal)
    data.shift_x = float(shift_x) / width if shift_x else 0.0
    data.clip_start = 1e-4
    data.clip_end = float(clip_end)
    data.dof.use_dof = bool(dof)
    data.dof.aperture_blades = int(settings.get("aperture_blades", 0))
    data.dof.aperture_rotation = float(settings.get("aperture_rotation", 0.0))
    data.dof.aperture_ratio = float(settings.get("aperture_ratio", 1.0))
    data.dof.aperture_fstop = float(settings["fstop"])
    data.dof.focus_object = None
    z_f = settings["focus_distance"]
    data.dof.focus_distance = float(FAR_FOCUS if math.isinf(z_f) else z_f)
    obj = bpy.data.objects.new("Camera", data)
    bl_scene.collection.objects.link(obj)
    # Blender cameras look down local -Z with +Y up; a 180 degree turn about X makes them
    # look down world +Z with world -Y up, i.e. world axes = the project's (x right, y down).
    obj.location = (0.0, 0.0, 0.0)
    obj.rotation_euler = (math.pi, 0.0, 0.0)
    bl_scene.camera = obj
    return obj


def _camera(bpy, bl_scene, scene: Scene, dof: bool, fault: str | None, sensor_width_mm: float,
            shift_px: float = 0.0):
    cam = scene.camera
    st = dict(cam.cycles_settings(sensor_width_mm))
    if fault == "radius":
        st["fstop"] = st["fstop"] / FAULT_RADIUS
    depths = [card_corners(scene, c)[:, 2].max() for c in scene.cards]
    return camera_object(bpy, bl_scene, st, dof, max(1e3, 10.0 * max(depths)), shift_px,
                         cam.width)


def _image(bpy, card):
    """A packed float32 image of the card's RGBA (straight, linear), rows bottom-up."""
    h, w = card.rgba.shape[:2]
    img = bpy.data.images.new(card.name, width=w, height=h, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    # straight colour and alpha stay independent channels (no (un)premultiplication)
    img.alpha_mode = "CHANNEL_PACKED"
    rgba = np.asarray(card.rgba, np.float32)[::-1]  # Blender stores the bottom row first
    img.pixels.foreach_set(np.ascontiguousarray(rgba).ravel())
    img.pack()
    return img


def _material(bpy, scene: Scene, card, fault: str | None):
    """Emission (colour, strength 1) mixed with Transparent by alpha; the texture is
    looked up at the pinhole projection of the shading point (projective UVs)."""
    cam = scene.camera
    f = float(cam.focal_length_px)
    x0, _, y0, _ = card.extent(cam)
    wt, ht = card.size
    mat = bpy.data.materials.new(card.name)
    if mat.node_tree is None:  # 4.x: off by default; 5.x makes it (use_nodes is deprecated)
        mat.use_nodes = True
    mat.cycles.emission_sampling = "NONE"  # not a light: no light-tree work
    nt = mat.node_tree
    nt.nodes.clear()
    N, L = nt.nodes, nt.links

    tc = N.new("ShaderNodeTexCoord")  # Object = world = camera axes (identity transform)
    sep = N.new("ShaderNodeSeparateXYZ")
    L.new(tc.outputs["Object"], sep.inputs[0])

    def math_node(op, a, b=None, c=None):
        m = N.new("ShaderNodeMath")
        m.operation = op
        for i, v in enumerate((a, b, c)):
            if v is None:
                continue
            if isinstance(v, (int, float)):
                m.inputs[i].default_value = float(v)
            else:
                L.new(v, m.inputs[i])
        return m.outputs[0]

    px = math_node("DIVIDE", sep.outputs["X"], sep.outputs["Z"])  # x / f_px
    py = math_node("DIVIDE", sep.outputs["Y"], sep.outputs["Z"])  # y / f_px
    # u = (f X/Z - x0) / W_t ; v = 1 - (f Y/Z - y0) / H_t (texture rows bottom-up)
    u = math_node("MULTIPLY_ADD", px, f / wt, -x0 / wt)
    if fault != "flip":  # the "flip" fault forgets that the rows are stored bottom-up
        v = math_node("MULTIPLY_ADD", py, -f / ht, 1.0 + y0 / ht)
    else:
        v = math_node("MULTIPLY_ADD", py, f / ht, -y0 / ht)
    comb = N.new("ShaderNodeCombineXYZ")
    L.new(u, comb.inputs[0])
    L.new(v, comb.inputs[1])

    tex = N.new("ShaderNodeTexImage")
    tex.image = _image(bpy, card)
    tex.interpolation = "Closest"
    tex.extension = "CLIP"  # outside the texture: transparent black, as the tracer's miss
    L.new(comb.outputs[0], tex.inputs["Vector"])

    emit = N.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    colour = tex.outputs["Color"]
    if fault == "offset":
        add = N.new("ShaderNodeVectorMath")
        add.operation = "ADD"
        L.new(colour, add.inputs[0])
        add.inputs[1].default_value = (FAULT_OFFSET,) * 3
        colour = add.outputs[0]
    L.new(colour, emit.inputs["Color"])
    transp = N.new("ShaderNodeBsdfTransparent")
    transp.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    mix = N.new("ShaderNodeMixShader")
    L.new(tex.outputs["Alpha"], mix.inputs["Fac"])
    L.new(transp.outputs[0], mix.inputs[1])
    L.new(emit.outputs[0], mix.inputs[2])
    out = N.new("ShaderNodeOutputMaterial")
    out.target = "CYCLES"
    L.new(mix.outputs[0], out.inputs["Surface"])
    return mat


def _card_object(bpy, bl_scene, scene: Scene, card, fault):
    corners = card_corners(scene, card)
    mesh = bpy.data.meshes.new(card.name)
    # corners (x0,y0) (x1,y0) (x1,y1) (x0,y1): counter-clockwise seen from the camera in a
    # y-down frame is clockwise in y-up; the winding only sets the normal, and emission
    # and transparency are two-sided in Cycles, so it does not matter here.
    mesh.from_pydata([tuple(map(float, p)) for p in corners], [], [(0, 1, 2, 3)])
    mesh.update()
    mesh.materials.append(_material(bpy, scene, card, fault))
    obj = bpy.data.objects.new(card.name, mesh)
    bl_scene.collection.objects.link(obj)
    return obj


def build_scene(scene: Scene, spp: int, seed: int = 0, dof: bool = True, *,
                threads: int = 0, pixel_filter: str | None = None, filter_width: float = 0.01,
                depth_pass: bool = False, unbiased: bool = True, shift_px: float = 0.0,
                fault: str | None = None, sensor_width_mm: float = 36.0):
    """Replace Blender's data with a Cycles scene of ``scene``; returns the bpy scene.

    Args:
        spp: samples per pixel (adaptive sampling and denoising off).
        seed: Cycles' sampling seed (independent noise per seed).
        dof: thin lens on (True) or pinhole (False: the all-in-focus view).
        threads: CPU threads, 0 = all.
        pixel_filter, filter_width: Cycles pixel filter and its width (pixels). Cycles
            forces the width of ``BOX`` to 1 pixel whatever is asked (checked: a
            0.25-pixel image shift gives the same 0.75/0.25 mix at widths 0.01, 1 and
            2), so ``BOX`` is always the canonical box average over the pixel square.
            ``GAUSSIAN`` with width 0.01 samples the pixel centre only. None (the
            default): ``BOX`` with depth of field, ``GAUSSIAN`` (centres, equal to the
            box average there, see the module notes) for the pinhole view.
        depth_pass: also write the Z pass (planar depth, sample 0 only).
        unbiased: skip Cycles' sample 0. Cycles always puts the pixel-filter position of
            sample 0 at the pixel centre (``rand_filter = (sample == 0) ? (0.5, 0.5)``
            in its camera kernel, so that data passes sample the centre), which biases
            the pixel average by ``(f(centre) - box average) / spp``. With ``unbiased``
            the render uses the sample subset ``[spp, 2 spp)`` of the same Sobol
            sequence: an aligned block (stratified for power-of-two ``spp``) without
            sample 0, at the same cost. Must be False for the Z pass.
        shift_px: camera shift to the right in pixels (the image content moves left);
            0 except in tests of the pixel model.
        fault: one of :data:`FAULTS`, for tests only: ``offset`` adds
            :data:`FAULT_OFFSET` to every card's radiance, ``shift`` moves the image
            half a pixel, ``flip`` turns every texture upside down, ``radius``
            multiplies the aperture radius by :data:`FAULT_RADIUS`.
    """
    if fault is not None and fault not in FAULTS:
        raise ValueError(f"fault must be one of {FAULTS} or None, got {fault!r}")
    if int(spp) < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    scene.validate()
    bpy = _bpy()
    bl = _reset(bpy)
    cam = scene.camera
    if pixel_filter is None:
        pixel_filter = "BOX" if dof else "GAUSSIAN"
    configure_render(bl, cam.width, cam.height, spp, seed, threads=threads,
                     pixel_filter=pixel_filter, filter_width=filter_width,
                     unbiased=unbiased, transparent_bounces=4 * len(scene.cards) + 16,
                     film_transparent=True)
    black_world(bpy, bl)
    configure_passes(bl, depth_pass)

    shift = float(shift_px) + (0.5 if fault == "shift" else 0.0)
    _camera(bpy, bl, scene, dof, fault, sensor_width_mm, shift)
    for card in scene.cards:
        _card_object(bpy, bl, scene, card, fault)

    return bl


def configure_render(bl, width: int, height: int, spp: int, seed: int, *, threads: int = 0,
                     pixel_filter: str = "BOX", filter_width: float = 0.01,
                     unbiased: bool = True, transparent_bounces: int = 16,
                     film_transparent: bool = True, max_bounces: int = 0) -> None:
    """Cycles settings shared by every scene this project renders (CPU, no adaptive
    sampling or denoising, no clamping, the Standard view transform: linear pixels),
    and 32-bit multilayer EXR output.

    ``max_bounces = 0``: emission seen directly and, on diffuse surfaces, direct light
    only. ``unbiased`` renders the sample subset ``[spp, 2 spp)`` (sample 0, at the pixel
    centre, is skipped; see :func:`build_scene`). ``transparent_bounces`` is both the
    maximum and the minimum (no Russian roulette on transparent bounces: less noise, and
    an exact Z behind transparent surfaces)."""
    r = bl.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y = int(width), int(height)
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_border = False
    r.film_transparent = bool(film_transparent)
    r.use_persistent_data = False
    r.threads_mode = "FIXED" if threads else "AUTO"
    if threads:
        r.threads = int(threads)
    r.use_compositing = False
    r.use_sequencer = False
    c = bl.cycles
    c.device = "CPU"
    # The same sequence on every Blender: Tabulated Sobol (5.0.1's default; 4.2, 4.5 and
    # 5.3 default to AUTOMATIC, which is blue noise on 5.3), whose aligned blocks are what
    # ``unbiased`` relies on.
    c.sampling_pattern = "TABULATED_SOBOL"
    set_sample_subset(c, int(spp) if unbiased else 0, int(spp))
    c.seed = int(seed)
    c.use_animated_seed = False
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.max_bounces = int(max_bounces)
    c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = c.volume_bounces = 0
    c.transparent_max_bounces = int(transparent_bounces)
    # No Russian roulette on transparent bounces (Cycles' default starts it after
    # min_transparent_bounces = 0): it adds noise, and when it ends the sample-0 path
    # behind a transparent card, Z is left at a card with alpha < pass_alpha_threshold.
    c.min_transparent_bounces = c.transparent_max_bounces
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.caustics_reflective = c.caustics_refractive = False
    c.pixel_filter_type = pixel_filter
    c.filter_width = float(filter_width)
    c.film_exposure = 1.0
    c.use_auto_tile = False
    bl.view_settings.view_transform = "Standard"
    bl.view_settings.look = "None"
    bl.view_settings.exposure = 0.0
    bl.view_settings.gamma = 1.0
    bl.unit_settings.scale_length = 1.0
    set_multilayer_exr(r.image_settings, color_depth="32", codec="ZIP")


def black_world(bpy, bl):
    """A black world (strength 0): nothing behind the scene, no light from it."""
    world = bpy.data.worlds.new("World")
    if world.node_tree is None:
        world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        bg.inputs["Strength"].default_value = 0.0
    bl.world = world
    return world


def configure_passes(bl, depth_pass: bool) -> None:
    """Combined, and the Z pass if ``depth_pass`` (first surface with alpha >= 0.5)."""
    vl = bl.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = bool(depth_pass)
    vl.pass_alpha_threshold = 0.5


def render_exr(bl, path: str | os.PathLike) -> float:
    """Render the bpy scene ``bl`` (from :func:`build_scene`) to the multilayer EXR
    ``path``; returns the wall time of the render operator in seconds (Cycles' scene
    sync, BVH build and image upload included; Blender's start-up and the scene
    building in Python not)."""
    bpy = _bpy()
    bl.render.filepath = str(path)
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True, scene=bl.name)
    return time.perf_counter() - t0


def read_render(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a Cycles multilayer EXR: ``(rgba (H, W, 4) float32 from ViewLayer.Combined,
    depth (H, W) float32 from the Depth pass or None)``."""
    from mpib_validate.runtime.io.exr import ExrError, find_pass, read_exr, rgba_from

    img = read_exr(path)
    rgba = rgba_from(img, "ViewLayer.Combined.").astype(np.float32)
    try:
        z = np.asarray(img.channels[find_pass(img, "Depth")], np.float32)
    except ExrError:
        z = None
    return rgba, z


def render(scene: Scene, spp: int, seed: int = 0, dof: bool = True, *, depth: bool = True,
           threads: int = 0, fault: str | None = None, unbiased: bool = True,
           keep: str | os.PathLike | None = None):
    """Render ``scene`` with Cycles on the CPU.

    Returns ``(rgba, depth, meta)``:

    - ``rgba``: ``(H, W, 4)`` float32, linear premultiplied radiance averaged over the
      pixel square (box) and the aperture disk, alpha = coverage;
    - ``depth``: ``(H, W)`` float32 planar depth (scene units) of the front-most card
      with alpha >= 0.5 at the pixel centre, 1e10 where there is none; from a separate
      1-spp pinhole render (Cycles writes Z from sample 0 only, which sits at the pixel
      centre, and with depth of field on that sample's ray leaves from a random lens
      point), or ``None`` when ``depth`` is False;
    - ``meta``: engine, settings, ``seconds`` (the main render operator, see
      :func:`render_exr`), ``build_seconds`` (building the bpy scene),
      ``depth_seconds``.

    ``keep``: a directory to keep the EXR files in (else a temporary one).
    """
    meta = {"engine": "cycles", "spp": int(spp), "seed": int(seed), "dof": bool(dof),
            "unbiased": bool(unbiased), "fault": fault, "device": "CPU",
            "blender": _bpy().app.version_string}
    with tempfile.TemporaryDirectory(prefix="mpib-cycles-") as tmp:
        out_dir = Path(keep) if keep is not None else Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        bl = build_scene(scene, spp, seed, dof, threads=threads, unbiased=unbiased,
                         fault=fault)
        meta["build_seconds"] = time.perf_counter() - t0
        meta["seconds"] = render_exr(bl, out_dir / "cycles.exr")
        rgba, _ = read_render(out_dir / "cycles.exr")
        z = None
        if depth:
            bl = build_scene(scene, 1, seed, False, threads=threads, depth_pass=True,
                             unbiased=False, fault=fault)
            meta["depth_seconds"] = render_exr(bl, out_dir / "cycles_depth.exr")
            _, z = read_render(out_dir / "cycles_depth.exr")
    return rgba, z, meta


def render_result(scene: Scene, spp: int, seed: int = 0, threads: int = 0):
    """Everything ``mpib render`` writes, from Cycles: a :class:`trace.TraceResult` with
    ``bokeh`` (thin lens, ``spp`` samples), ``all_in_focus`` (pinhole: exact at any
    sample count, 1 spp), ``depth`` (Cycles' Z pass) and ``disparity = 1/Z`` (0 where
    Z = 1e10); ``layer``, ``card_alpha`` and ``card_disparity`` are the scene's exact
    pinhole maps (:func:`trace.pinhole_maps`). ``meta`` carries ``engine``,
    ``backend`` (``cycles-cpu``), ``samples``, ``sample_count``, ``seconds``."""
    from mpib_validate.cards.trace import TraceResult, pinhole_maps

    bokeh, _, meta = render(scene, spp, seed, True, depth=False, threads=threads)
    aif, z, meta_aif = render(scene, 1, seed, False, depth=True, threads=threads)
    maps = pinhole_maps(scene)
    disparity = np.where(z < BACKGROUND_DEPTH, 1.0 / np.maximum(z, 1e-30), 0.0).astype(np.float32)
    meta.update(backend="cycles-cpu", samples=f"cycles-sobol{int(spp)}-seed{int(seed)}",
                sample_count=int(spp), all_in_focus_seconds=meta_aif["seconds"],
                depth_seconds=meta_aif.get("depth_seconds"))
    return TraceResult(bokeh, aif, disparity, z, maps["layer"], maps["card_alpha"],
                       maps["card_disparity"], meta)


def render_many(scene: Scene, spp: int, seeds, dof: bool = True, **kw) -> np.ndarray:
    """``(K, H, W, 4)`` float32: one :func:`render` (no depth) per seed."""
    return np.stack([render(scene, spp, int(s), dof, depth=False, **kw)[0] for s in seeds])


# --------------------------------------------------------------------------------------
# Statistics: agreement to the level of Monte Carlo noise


#: Cap on each value's z^2 in :func:`agreement` (|z| = 5).
Z2_CAP = 25.0


def _capped_t2_moments(nu: int, cap: float) -> tuple[float, float]:
    """Mean and variance of ``min(t^2, cap)`` for Student's t with ``nu`` dof."""
    from scipy import integrate, stats

    c = math.sqrt(cap)
    m1 = 2 * integrate.quad(lambda t: t * t * stats.t.pdf(t, nu), 0, c)[0]
    m2 = 2 * integrate.quad(lambda t: t ** 4 * stats.t.pdf(t, nu), 0, c)[0]
    tail = 2 * stats.t.sf(c, nu)
    mean = m1 + cap * tail
    return mean, m2 + cap * cap * tail - mean * mean


def agreement(renders: np.ndarray, reference: np.ndarray, reference_var: np.ndarray | float = 0.0,
              sigmas: float = 6.0, channels: slice = slice(0, 3)) -> dict:
    """Is the mean of ``K`` independent renders equal to ``reference`` up to noise?

    ``renders``: ``(K, H, W, C)``; ``reference``: ``(H, W, C)``; ``reference_var``: the
    variance of the reference itself (per value or a scalar; e.g. from two independent
    halves, ``(r1 - r2)^2 / 4`` for their mean). Two statistics over the RGB values:

    - ``mse_ratio = MSE(mean, ref) / E0`` with ``E0 = mean(s^2)/K + mean(reference_var)``,
      ``s^2`` the unbiased per-value sample variance of the renders. Under the null
      hypothesis its expectation is 1. Its spread: the MSE is a sum of
      ``sigma_p^2 chi^2_1 / K`` terms, so its relative standard deviation is
      ``sqrt(2 / n_eff)`` with ``n_eff = (sum s^2)^2 / sum s^4`` (the effective number
      of independent values, small when a few noisy pixels dominate); ``E0`` itself
      has ``sqrt(2 / ((K - 1) n_eff))``. ``mse_tolerance = 1 + sigmas * sqrt(2/n_eff)
      * sqrt(1 + 1/(K-1))``.
    - ``mean_z2``: the mean of ``min(z^2, Z2_CAP)`` with
      ``z^2 = (mean - ref)^2 / (s^2/K + reference_var + floor^2)``, each value weighted
      alike (so low-noise pixels count as much as HDR ones). Under the null hypothesis
      ``z ~ t_{K-1}``. Rare bright samples (HDR highlights, thin features seen through
      a small part of the aperture) make the errors heavy-tailed: a pixel whose K
      renders all missed the feature has a tiny ``s^2`` and a huge ``z``. Capping ``z^2``
      at 25 (``|z| = 5``) bounds each pixel's weight to ``25 / n``; the mean and variance
      of ``min(t^2, 25)`` under the null hypothesis are integrated numerically, and
      ``z2_tolerance = E + sigmas * sqrt(Var / n_pixels)`` (the three channels of a
      pixel share its samples, so only the pixel count is taken as independent).
      ``floor = 1e-4`` (radiance units) keeps values that no sample varied (in-focus,
      uniform) from dividing by zero; it is far below any error the test looks for.
      A fault moves most pixels to ``z^2 >> 25``, so the cap does not hide it.

    ``K >= 6``. Returns both statistics, their
    tolerances, ``n_eff``, ``psnr`` (of the mean, peak 1) and ``ok`` (both pass).
    """
    renders = np.asarray(renders, np.float64)[..., channels]
    ref = np.asarray(reference, np.float64)[..., channels]
    k = renders.shape[0]
    if k < 6:
        raise ValueError(f"need K >= 6 independent renders, got {k}")
    rvar = np.asarray(reference_var, np.float64)
    if rvar.ndim == np.ndim(reference):
        rvar = rvar[..., channels]
    rvar = np.broadcast_to(rvar, ref.shape)
    mean = renders.mean(axis=0)
    s2 = renders.var(axis=0, ddof=1)
    err2 = (mean - ref) ** 2
    mse = float(err2.mean())
    var_mean = s2 / k + rvar
    e0 = float(var_mean.mean())
    n_eff = float(var_mean.sum() ** 2 / max((var_mean ** 2).sum(), 1e-300))
    mse_tol = 1.0 + sigmas * math.sqrt(2.0 / n_eff) * math.sqrt(1.0 + 1.0 / (k - 1))
    floor = 1e-4
    z2 = np.minimum(err2 / (var_mean + floor ** 2), Z2_CAP)
    ez2, varz2 = _capped_t2_moments(k - 1, Z2_CAP)
    n_pix = ref.shape[0] * ref.shape[1]
    z2_tol = ez2 + sigmas * math.sqrt(varz2 / n_pix)
    mse_ratio = mse / max(e0, 1e-300)
    mean_z2 = float(z2.mean())
    psnr = math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)
    return {"k": k, "mse": mse, "expected_mse": e0, "mse_ratio": mse_ratio,
            "mse_tolerance": mse_tol, "n_eff": n_eff, "mean_z2": mean_z2,
            "z2_expected": ez2, "z2_tolerance": z2_tol, "psnr": psnr,
            "ok": bool(mse_ratio <= mse_tol and mean_z2 <= z2_tol)}


# --------------------------------------------------------------------------------------
# Blur radius from point-like sources


def dot_grid_scene(width: int = 96, per_side: int = 6, radius: float = 6.0,
                   disparity: float = 0.25, focus_disparity: float = 0.5,
                   radiance: float = 1.0) -> tuple[Scene, list[tuple[int, int]], int]:
    """A transparent fronto-parallel card with a ``per_side`` x ``per_side`` grid of single
    opaque emitting texels, blurred to ``radius`` pixels (``A = radius / |d - d_f|``).

    Returns ``(scene, centres, step)``: the (row, column) of each dot's texel (= its
    in-focus pixel) and the grid step in pixels (each dot owns a ``step`` x ``step``
    window; ``step > 2 radius + 3``)."""
    from mpib_validate.runtime.camera import Camera
    from mpib_validate.cards.scene import Card, Plane

    step = width // per_side
    if step <= 2 * radius + 3:
        raise ValueError(f"dots {step} px apart do not fit radius {radius}")
    cam = Camera(width, width, radius / abs(disparity - focus_disparity), focus_disparity)
    rgba = np.zeros((width, width, 4), np.float32)
    centres = []
    for i in range(per_side):
        for j in range(per_side):
            y, x = i * step + step // 2, j * step + step // 2
            rgba[y, x] = [radiance, radiance, radiance, 1.0]
            centres.append((y, x))
    return Scene(cam, [Card("dots", rgba, Plane.fronto(disparity), (0, 0))]).validate(), \
        centres, step


#: Second moment of one pixel-box or texel-box about its centre, per image (2 axes).
BOX_MOMENT = 2.0 / 12.0


def dot_radii(image: np.ndarray, centres, step: int, boxes: int = 2) -> np.ndarray:
    """Blur radius of each dot from the second moment of its window (pixels).

    About the centroid, ``E[rho^2] = r^2/2 + boxes/6``: a uniform disk of radius r has
    ``r^2/2``, and each unit box (the texel, the pixel) adds ``1/12`` per axis. The
    canonical pixel model has two boxes. Returns ``sqrt(2 (E - boxes/6))`` per dot."""
    lum = np.asarray(image, np.float64)[..., :3].mean(axis=-1)
    h, w = lum.shape
    out = []
    half = step // 2
    for (y, x) in centres:
        y0, y1 = max(0, y - half), min(h, y - half + step)
        x0, x1 = max(0, x - half), min(w, x - half + step)
        p = lum[y0:y1, x0:x1]
        yy, xx = np.mgrid[y0:y1, x0:x1]
        s = p.sum()
        cy, cx = (p * yy).sum() / s, (p * xx).sum() / s
        e = (p * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum() / s
        out.append(math.sqrt(max(0.0, 2.0 * (e - boxes * BOX_MOMENT))))
    return np.array(out)


# --------------------------------------------------------------------------------------
# Benchmark helper


def noise_vs_spp(scene: Scene, spp_list, seeds=(0, 1), dof: bool = True, threads: int = 0) -> list[dict]:
    """Cycles time and noise per sample count.

    For each ``spp``: two renders with independent seeds. ``noise_rmse`` is the RMS
    noise of one render, ``sqrt(mean((a - b)^2) / 2)`` over the RGB values (linear
    radiance); ``noise_psnr`` the matching PSNR (peak 1); ``seconds`` the mean render
    operator time (:func:`render_exr`), ``build_seconds`` the mean bpy scene build.
    """
    rows = []
    for spp in spp_list:
        imgs, secs, builds = [], [], []
        for s in seeds[:2]:
            rgba, _, meta = render(scene, int(spp), int(s), dof, depth=False, threads=threads)
            imgs.append(rgba)
            secs.append(meta["seconds"])
            builds.append(meta["build_seconds"])
        d = (imgs[0][..., :3].astype(np.float64) - imgs[1][..., :3]) ** 2
        rmse = math.sqrt(float(d.mean()) / 2.0)
        rows.append({"spp": int(spp), "seconds": float(np.mean(secs)),
                     "build_seconds": float(np.mean(builds)), "noise_rmse": rmse,
                     "noise_psnr": math.inf if rmse == 0 else -20.0 * math.log10(rmse),
                     "width": scene.camera.width, "height": scene.camera.height})
    return rows
