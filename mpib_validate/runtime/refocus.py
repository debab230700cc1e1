"""Refocusing a rendered picture: read colour + depth, choose focus and aperture, render.

This is what ``mpib refocus`` and the Blender add-on run. Inputs are EXR files: a
Blender multilayer file (``ViewLayer.Combined.*`` and ``ViewLayer.Depth.Z``), one of
this project's renders (``AllInFocus.*`` and ``Depth.Z``), or colour and depth as two
files. The camera travels in the header (:mod:`mpib_validate.runtime.io.camera_header`).

A photograph with a disparity map (``mpib refocus photo.jpg --disparity disp.png``, read
by :mod:`mpib_validate.runtime.io.photo`) comes in as :class:`Passes` whose ``disparity`` is
given directly instead of ``1/depth``; the rest is the same.

A layered render (one view layer per depth group, ``mpib_group_<k>.Combined.*`` and
``mpib_group_<k>.Depth.Z``, see :mod:`mpib_validate.runtime.blender.layers`) is read by
:func:`load_layered_passes` and refocused from its group layers
(:mod:`mpib_validate.runtime.layers.layered`): what nearer groups hide is rendered, not filled.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpib_validate.runtime.io.camera_header import HeaderCamera, read_camera
from mpib_validate.runtime.compositor.composite import render_subapertures
from mpib_validate.runtime.io.exr import ExrError, find_pass, read_exr, rgba_from
from mpib_validate.runtime.layers.layered import composite_over, group_layers, layers_from_layered_passes
from mpib_validate.runtime.layers.passes import (DEFAULT_FAR_LIMIT, PassError, depth_to_disparity, layers_from_passes,
                                                passes_disparity)
from mpib_validate.runtime.request import RefocusRequest


@dataclass
class Passes:
    """Colour (``(H, W, 3)`` linear) and depth (``(H, W)`` scene units) with their origin."""

    colour: np.ndarray
    depth: np.ndarray
    colour_source: str
    depth_source: str
    camera: HeaderCamera | None = None  # the camera the input's header carries, if any
    #: ``(H, W)`` film alpha (coverage) of the colour, premultiplied into it; None = opaque
    alpha: np.ndarray | None = None
    #: layered input (:func:`load_layered_passes`): far to near, ``(colour (H, W, 3)
    #: premultiplied, alpha (H, W), depth (H, W)[, coverage (H, W)])`` per depth group
    #: (coverage: the farthest group's own where the world is added in); ``colour``,
    #: ``alpha`` and ``depth`` above are then the groups composited with "over" (and the
    #: nearest covering group's depth), for focusing and display
    groups: list | None = None
    notices: list = field(default_factory=list)  # one line each, e.g. clamped negatives
    #: ``(H, W)`` disparity given directly (a photograph's disparity map, 0 = infinitely
    #: far), used instead of ``1/depth``; ``depth`` then holds ``1/disparity`` for display
    disparity: np.ndarray | None = None
    #: how the colour samples the scene, which sets the blur kernel (see
    #: :data:`PIXEL_MODELS`): ``"texel"`` for this project's card-scene renders,
    #: ``"continuous"`` for everything else (Blender renders, photographs)
    pixel_model: str = "continuous"


#: The pixel models of an input and the compositor kernel each one needs:
#: ``texel`` (the card scenes' nearest-texel textures, each pixel a constant patch: the
#: canonical kernel, exact against the ray tracer) and ``continuous`` (continuous
#: geometry filtered by the pixel, or a photograph: the canonical kernel at
#: :func:`~mpib_validate.runtime.compositor.kernels.continuous_radius`, which has the disk's
#: own second moment). Measured: the continuous kernel on card scenes loses 3.5 dB
#: PSNR_ob (constant family), the canonical one on the Blender suite makes small
#: bokeh 3-4 % too wide at 3.4 px.
PIXEL_MODELS = {"texel": "canonical", "continuous": "continuous"}


def pixel_model_of(header: dict) -> str:
    """``"texel"`` for a card-scene render of this project (``mpib render``: its
    ``mpib`` header lists the scene's ``cards``), else ``"continuous"``."""
    text = header.get("mpib") if isinstance(header, dict) else None
    if isinstance(text, str):
        try:
            meta = json.loads(text)
        except ValueError:
            return "continuous"
        if isinstance(meta, dict) and isinstance(meta.get("cards"), list):
            return "texel"
    return "continuous"


def view_layers(img) -> list[str]:
    """Blender view layers in an EXR: the ``<layer>`` of each ``<layer>.Combined.R``."""
    return sorted(n[:-len(".Combined.R")] for n in img.channels if n.endswith(".Combined.R"))


def _colour_prefix(img, all_in_focus: bool = True, view_layer: str | None = None) -> str:
    """Channel prefix of the colour: ``AllInFocus.`` in an mpib render (its own R, G, B
    are already defocused) when ``all_in_focus``, else plain R, G, B, else Blender's
    ``<layer>.Combined.`` (the one view layer, or ``view_layer``)."""
    ch = img.channels
    layers = view_layers(img)
    if view_layer is not None:
        if view_layer in layers:
            return f"{view_layer}.Combined."
        found = ", ".join(layers) if layers else "none"
        raise ExrError(f"no view layer '{view_layer}' in '{img.path}' (view layers with a "
                       f"Combined pass: {found})")
    if all_in_focus and "AllInFocus.R" in ch:
        return "AllInFocus."
    if "R" in ch:
        return ""
    if len(layers) == 1:
        return f"{layers[0]}.Combined."
    if len(layers) > 1:
        raise ExrError(f"'{img.path}' holds {len(layers)} view layers ({', '.join(layers)}); "
                       f"choose one with --view-layer NAME")
    raise ExrError(f"no colour channels (R, G, B, AllInFocus.* or *.Combined.*) in "
                   f"'{img.path}'; channels: {', '.join(sorted(ch))}")


def _refuse_non_finite(rgba: np.ndarray, source: str, what: str = "colour",
                       letters: str = "RGBA") -> None:
    """Raise :class:`PassError` naming ``source`` and the first NaN or infinite value
    (one would turn a whole blurred channel into NaN)."""
    bad = ~np.isfinite(rgba)
    if bad.any():
        y, x, c = np.argwhere(bad)[0]
        raise PassError(f"{source}: {what} is NaN or infinite at {int(bad.sum())} value(s), "
                        f"first at (row {y}, column {x}, channel {letters[c]}): "
                        f"{rgba[y, x, c]}")


def image_rgba(img, prefix: str, source: str | None = None) -> np.ndarray:
    """``(H, W, 4)`` float32 colour and alpha of the channels ``prefix`` + R, G, B(, A)
    of an EXR image: the one way an image enters a result (the input's colour, a
    layered render's groups and world, a background render, an image compared), so
    every one is checked the same way. Raises :class:`PassError` naming ``source``
    (default: the file and the channels) and the first NaN or infinite value."""
    rgba = rgba_from(img, prefix)
    _refuse_non_finite(rgba, source or f"'{img.path}' ({prefix or 'R, G, B'})")
    return rgba


def read_colour(path, all_in_focus: bool = True, view_layer: str | None = None) -> np.ndarray:
    """``(H, W, 4)`` colour of an EXR (see :func:`_colour_prefix` for which channels).
    Raises :class:`PassError` naming the file and the first pixel for NaN or infinite
    values."""
    img = read_exr(path)
    return image_rgba(img, _colour_prefix(img, all_in_focus, view_layer))


def _depth_channel(img, path) -> np.ndarray:
    try:
        return img.channels[find_pass(img, "Depth")].astype(np.float64)
    except ExrError:
        pass
    singles = [n for n in ("Y", "R") if n in img.channels]
    if len(img.channels) == 1 or singles:
        name = singles[0] if singles else next(iter(img.channels))
        return img.channels[name].astype(np.float64)
    raise PassError(f"no Depth pass in '{path}' (enable the Z / Depth pass in Blender's View "
                    f"Layer properties); channels: {', '.join(sorted(img.channels))}")


def _clamp_negative(colour: np.ndarray, source: str) -> str | None:
    """Clamp negative colour to 0 in place; return a one-line notice, or None.

    Radiance cannot be negative; small negative values come from denoisers, sharpening
    pixel filters or compositing, and would darken what they are blurred over."""
    neg = colour < 0
    if not neg.any():
        return None
    y, x, _ = np.argwhere(neg)[0]
    lowest = float(colour.min())
    np.maximum(colour, 0.0, out=colour)
    return (f"{source}: {int(neg.sum())} negative colour value(s) (lowest {lowest:.4g}, first "
            f"at row {y}, column {x}) clamped to 0")


def load_passes(path, depth_path=None, view_layer: str | None = None) -> Passes:
    """Read colour and depth, and the camera of the colour file's header (see
    :mod:`mpib_validate.runtime.io.camera_header`). Raises :class:`PassError`/:class:`ExrError`
    naming the file for a missing depth pass, mismatched sizes or NaN/infinite colour,
    and :class:`~mpib_validate.runtime.io.camera_header.CameraHeaderError` for a malformed camera;
    negative colour is clamped to 0 with a notice in ``Passes.notices``. ``view_layer``
    picks one of several Blender view layers in the file."""
    img = read_exr(path)
    prefix = _colour_prefix(img, view_layer=view_layer)
    source = f"'{path}' ({prefix or 'R, G, B'})"
    rgba = image_rgba(img, prefix, source)
    colour = rgba[..., :3]
    camera = read_camera(img.header, path)
    if depth_path is None:
        try:
            if view_layer is not None and f"{view_layer}.Depth.Z" in img.channels:
                name = f"{view_layer}.Depth.Z"
            else:
                name = find_pass(img, "Depth")
            depth = img.channels[name].astype(np.float64)
        except ExrError:
            raise PassError(f"no Depth pass in '{path}': enable the Z (Depth) pass in Blender's "
                            f"View Layer properties, or give the depth as a separate file; "
                            f"channels: {', '.join(sorted(img.channels))}") from None
        dsrc = str(path)
    else:
        depth = _depth_channel(read_exr(depth_path), depth_path)
        dsrc = str(depth_path)
    if depth.shape != colour.shape[:2]:
        raise PassError(f"sizes differ: colour in '{path}' is {colour.shape[1]}x{colour.shape[0]}, "
                        f"depth in '{dsrc}' is {depth.shape[1]}x{depth.shape[0]}")
    colour = colour.astype(np.float32)
    notice = _clamp_negative(colour, source)
    return Passes(colour, depth, f"{path}:{prefix or 'RGB'}", dsrc, camera,
                  rgba[..., 3].astype(np.float32), notices=[notice] if notice else [],
                  pixel_model=pixel_model_of(img.header))


def passes_from_photo(photo, disparity: np.ndarray, disparity_source: str) -> Passes:
    """The :class:`Passes` of a photograph (:class:`mpib_validate.runtime.io.photo.Photo`: straight
    linear colour, alpha or None) and its ``(H, W)`` disparity (0 = infinitely far; a
    normalised map as it is, the paper's convention): colour premultiplied by the
    alpha as passes hold it, ``depth = 1/disparity`` (inf at 0) for display, and the
    disparity itself, which :func:`refocus` then uses."""
    D = np.asarray(disparity, np.float64)
    if D.shape != photo.rgb.shape[:2]:
        raise PassError(f"sizes differ: the photograph '{photo.path}' is {photo.rgb.shape[1]}x"
                        f"{photo.rgb.shape[0]}, the disparity '{disparity_source}' is "
                        f"{D.shape[1]}x{D.shape[0]}")
    depth = np.divide(1.0, D, out=np.full(D.shape, np.inf), where=D > 0)
    colour = photo.rgb if photo.alpha is None else photo.rgb * photo.alpha[..., None]
    alpha = None if photo.alpha is None else photo.alpha.astype(np.float32)
    return Passes(colour.astype(np.float32), depth,
                  f"{photo.path} ({photo.format}, {photo.encoding.describe()})",
                  disparity_source, None, alpha, disparity=D)


#: View layers named like this (``mpib_group_0`` farthest, see
#: :mod:`mpib_validate.runtime.blender.layers`) are read as a layered input automatically.
GROUP_LAYER = re.compile(r"^mpib_group_(\d+)$")


def _median_depth(z, alpha, far_limit):
    sel = (alpha > 0.5) & np.isfinite(z) & (z > 0) & (z < far_limit)
    return float(np.median(z[sel])) if sel.any() else math.inf


def load_layered_passes(path, layered: bool | None = None,
                        far_limit: float = DEFAULT_FAR_LIMIT) -> Passes | None:
    """Read a multilayer EXR with one view layer per depth group
    (``<layer>.Combined.R/G/B/A`` and ``<layer>.Depth.Z``), or None if it is not one.

    ``layered=None`` (automatic): the view layers named ``mpib_group_<k>``, if there
    are two or more; ``True``: every view layer with Combined and Depth (an error
    naming the file if fewer than two); ``False``: None. The groups are ordered far to
    near: ``mpib_group_<k>`` by ``k`` (:mod:`mpib_validate.runtime.blender.layers` numbers them
    far to near and puts an object spanning the depth range, a ground plane, into group
    0 with the world, although its median depth may be nearer than the next group's);
    other view layers by their median depth (over pixels with alpha > 1/2 and a finite
    Z), a layer with an Environment pass first (the world lies behind everything). Where
    the farthest group has an Environment pass (the world), it is added to that group's
    colour, which is then opaque; its entry in ``Passes.groups`` carries the group's own
    coverage as a fourth member (where it is 0 the pixel is the world: disparity 0)."""
    if layered is False:
        return None
    img = read_exr(path)
    layers = sorted({n[:-len(".Combined.R")] for n in img.channels if n.endswith(".Combined.R")})
    if layered is None:
        layers = [n for n in layers if GROUP_LAYER.match(n)]
        if len(layers) < 2:
            return None
    else:
        layers = [n for n in layers if f"{n}.Depth.Z" in img.channels]
        if len(layers) < 2:
            raise PassError(f"--layered: '{path}' has {len(layers)} view layer(s) with "
                            f"Combined and Depth passes, need two or more")
    groups = []
    for name in layers:
        if f"{name}.Depth.Z" not in img.channels:
            raise PassError(f"no Depth pass for view layer '{name}' in '{path}' (enable the "
                            f"Z pass of every mpib_group_ view layer)")
        rgba = image_rgba(img, f"{name}.Combined.").astype(np.float64)
        z = img.channels[f"{name}.Depth.Z"].astype(np.float64)
        groups.append((name, rgba[..., :3], np.clip(rgba[..., 3], 0.0, 1.0), z))
    if all(GROUP_LAYER.match(g[0]) for g in groups):  # the renderer's order, far to near
        groups.sort(key=lambda g: int(GROUP_LAYER.match(g[0]).group(1)))
    else:  # far to near by median depth, the world's layer first
        groups.sort(key=lambda g: (f"{g[0]}.Environment.R" not in img.channels,
                                   -_median_depth(g[3], g[2], far_limit)))
    far = groups[0][0]
    if f"{far}.Environment.R" in img.channels:
        # the world behind the farthest group (blender.layers: the artist's film was
        # opaque): Combined + Environment is that layer over the world, opaque; its
        # own coverage still tells the world (disparity 0) from the group's content
        env = image_rgba(img, f"{far}.Environment.")[..., :3].astype(np.float64)
        _, P0, a0, z0 = groups[0]
        groups[0] = (far, P0 + env, np.ones_like(a0), z0, a0)
    colour, alpha = composite_over([g[1:] for g in groups])
    depth = groups[0][3].copy()
    for _, _, a, z in groups[1:]:
        depth = np.where(a >= 0.5, z, depth)
    order = ", ".join(g[0] for g in groups)
    return Passes(colour.astype(np.float32), depth, f"{path}:{order} (layered)",
                  f"{path}:{order} (layered)", read_camera(img.header, path),
                  alpha.astype(np.float32), [g[1:] for g in groups])


class Cancelled(Exception):
    """Raised by a progress callback to stop :func:`refocus` (the artist pressed Esc)."""


@dataclass
class RefocusResult:
    """``image``: ``(H, W, 4)`` float32, straight linear colour and alpha (the input's
    film alpha, refocused; 1 everywhere for an opaque input); the EXR holds
    ``colour * alpha`` (premultiplied), as Blender writes renders."""

    image: np.ndarray
    info: dict


def read_background(path, shape, far_limit: float = DEFAULT_FAR_LIMIT):
    """What lies behind the foreground, from a second render without it (e.g. the
    foreground excluded or held out): ``(colour (H, W, 4) premultiplied RGB + alpha,
    valid (H, W), disparity (H, W) or None)``, valid where its alpha is above 1/2
    (everywhere if it has none); the disparity from its Depth pass if it has one (it
    tells :func:`passes.known_background_mask` which hidden pixels it shows). Raises
    :class:`PassError` naming the file if its size is not ``shape``."""
    img = read_exr(path)
    rgba = image_rgba(img, _colour_prefix(img, True))
    if rgba.shape[:2] != tuple(shape):
        raise PassError(f"sizes differ: the background '{path}' is {rgba.shape[1]}x"
                        f"{rgba.shape[0]}, the passes are {shape[1]}x{shape[0]}")
    disparity = None
    try:
        z = img.channels[find_pass(img, "Depth")].astype(np.float64)
    except ExrError:
        pass
    else:
        z = np.where(np.isfinite(z) & (z > 0), z, np.inf)
        disparity = np.where(z >= far_limit, 0.0, 1.0 / z)
    return rgba, rgba[..., 3] > 0.5, disparity


@dataclass
class BuiltMPI:
    """What :func:`build_mpi` makes of a request: the MPI, whether the output is opaque
    (no film channel), the disparities the input holds (for the largest blur radius),
    the builder's info and the ``A`` it was built for. None of it depends on the focus."""

    mpi: object
    opaque: bool
    disparity: np.ndarray  # its smallest and largest value (or any array with them)
    info: object
    blur_parameter: float
    #: the input's pixel model (:data:`PIXEL_MODELS`): which kernel Eq. 1 uses
    pixel_model: str = "continuous"


def build_mpi(request: RefocusRequest, progress=None) -> BuiltMPI:
    """The focus-independent half of :func:`refocus`: the MPI of ``request.passes`` for
    the blur parameter ``A`` (px per unit disparity; it sets the plane spacing
    ``2 tol / A``, the edge threshold and how far behind each edge the background is
    filled), with the request's layer settings (its preset's, with its refinement:
    ``"guided"`` or ``"guided-thin"`` moves a predicted disparity's edges onto the
    colour edges, :mod:`mpib_validate.runtime.layers.refine`) and background render.
    ``A`` is the request's :attr:`~mpib_validate.runtime.request.RefocusRequest.build_blur_parameter`
    (the aperture's reach)."""
    passes, A, far_limit = request.passes, request.build_blur_parameter, request.far_limit
    settings, background = request.preset.passes, request.background
    D = passes_disparity(passes, far_limit)
    # The film alpha travels as a fourth colour channel (premultiplied like the colour),
    # so the output's alpha is its normalised blur: what the refocused view covers. An
    # opaque input needs no such channel: the normalised blur of ones is one wherever
    # the normaliser is positive, which is everywhere for passes (each pixel holds
    # content, and every kernel has weight at its centre).
    film = passes.alpha
    if passes.groups is not None:
        if background is not None:
            raise PassError(f"{passes.colour_source}: a layered input holds what lies behind "
                            f"the foreground; no background render is needed")
        # layered input: its own film channel unless the farthest group is opaque
        groups = group_layers(passes.groups, far_limit, passes.depth_source)
        mpi, info = layers_from_layered_passes(groups, A, settings, progress=progress)
        opaque = mpi.channels == 4
        D = np.concatenate([g[2][g[1] > 0] for g in groups] + [D.ravel()])
    else:
        opaque = film is None or bool(np.all(film >= 1.0))
        colour = passes.colour if opaque else np.concatenate(
            [passes.colour, np.clip(film, 0.0, 1.0)[..., None]], axis=-1)
        mpi, info = layers_from_passes(colour, D, A, settings,
                                       background=background, progress=progress)
    # only the range is read (the largest blur radius), as a cached entry keeps it: the
    # full map would hold 8 B per pixel through the compositing
    return BuiltMPI(mpi, opaque, np.array([float(D.min()), float(D.max())]), info,
                    float(A), passes.pixel_model)


def render_built(built: BuiltMPI, request: RefocusRequest, progress=None,
                 scale: int = 1) -> np.ndarray:
    """The focus-dependent half of :func:`refocus`: Eq. 1 (or the preset's middle
    setting) on ``built.mpi`` at the request's ``d_f`` and ``A / scale`` (``built.mpi``
    at ``1/scale`` of the request's resolution per axis: a blur radius of ``A |d - d_f|``
    full-resolution pixels is ``A |d - d_f| / scale`` of its pixels), as ``(H, W, 4)``
    float32 straight colour and alpha (see :class:`RefocusResult`)."""
    p = request.preset
    A = request.blur_parameter if scale == 1 else request.blur_parameter / scale
    settings = p.composite
    if settings.kernel == "canonical":  # the input's pixel model picks the kernel
        settings = dataclasses.replace(settings, kernel=PIXEL_MODELS[built.pixel_model])
    if request.aperture is not None and not request.aperture.is_disk:  # the lens's shape
        settings = dataclasses.replace(settings, aperture=request.aperture)
    img = render_subapertures(built.mpi, A, request.focus_disparity, p.subapertures,
                              settings, progress=progress)
    covered = img[..., 3] > 0
    if built.opaque:  # alpha 1 where covered: the colour itself there, 0 elsewhere
        out = np.empty(img.shape[:2] + (4,), np.float32)
        np.multiply(img[..., :4], covered[..., None], out=out)  # one contiguous pass
        out[..., 3] = covered
        return out
    alpha = np.where(covered, img[..., 4], 0.0)
    out = np.zeros(img.shape[:2] + (4,), np.float32)
    # straight colour: the normalised (premultiplied) colour over the normalised alpha
    np.divide(img[..., :3], alpha[..., None], out=out[..., :3], where=alpha[..., None] > 0)
    out[..., 3] = alpha
    return out


def result_info(request: RefocusRequest, built: BuiltMPI, seconds: float) -> dict:
    """The ``info`` of a :class:`RefocusResult` (written into the output's header). The
    largest blur radius is along the aperture's larger axis (``A extent |d - d_f|``)."""
    passes, A, d_f = request.passes, request.blur_parameter, request.focus_disparity
    D, info = built.disparity, built.info
    reach = request.build_blur_parameter
    radius = reach * max(abs(float(D.max()) - d_f), abs(float(D.min()) - d_f))
    return {
        "preset": request.preset.name, "planes": info.planes, "largest_radius_px": radius,
        "fill_fraction": info.fill_fraction, "edge_fraction": info.edge_fraction,
        "blur_parameter": A, "focus_disparity": d_f,
        "seconds": seconds, "layers_seconds": info.seconds,
        "colour": passes.colour_source, "depth": passes.depth_source,
        "pixel_model": built.pixel_model,
        "groups": 1 if passes.groups is None else len(passes.groups)}


def split_progress(progress):
    """``(first, second)``: ``progress`` mapped onto [0, 0.5] (the layers) and [0.5, 1]
    (the compositing); ``(None, None)`` without one."""
    if progress is None:
        return None, None
    return (lambda f: progress(0.5 * f)), (lambda f: progress(0.5 + 0.5 * f))


def refocus(request: RefocusRequest, progress=None, cache=None) -> RefocusResult:
    """The pipeline: the MPI of the request (:func:`build_mpi`), or the one ``cache``
    keeps for it, rendered at its focus (:func:`render_built`), and its
    :func:`result_info`.

    ``cache``: None (build), or where the MPI is kept: an object with
    ``fetch(request, progress) -> (BuiltMPI, info)`` whose info is added to the result's
    (:class:`mpib_validate.runtime.layers.cache.DiskCache`, a folder of MPIs, adds
    ``mpi_cache``; :class:`mpib_validate.runtime.session.RefocusSession`, in memory, adds
    ``mpi``). To refocus one picture many times, keep the MPI in a session.

    ``progress(fraction)``, if given, is called as the work goes on (layers up to 0.5,
    then compositing); raising from it stops the work, e.g. :class:`Cancelled`.
    """
    t0 = time.perf_counter()
    first, second = split_progress(progress)
    if cache is None:
        built, extra = build_mpi(request, first), {}
    else:
        built, extra = cache.fetch(request, first)
    img = render_built(built, request, second)
    info = result_info(request, built, time.perf_counter() - t0)
    info.update(extra)
    return RefocusResult(img, info)


def focus_from_pixel(passes: Passes, x: int, y: int, far_limit: float = DEFAULT_FAR_LIMIT) -> float:
    """Disparity to focus on pixel ``(x, y)``: the median over its 3x3 neighbourhood."""
    H, W = passes.depth.shape
    if not (0 <= x < W and 0 <= y < H):
        raise PassError(f"focus pixel ({x}, {y}) is outside the {W}x{H} image")
    D = passes_disparity(passes, far_limit)
    return float(np.median(D[max(0, y - 1):y + 2, max(0, x - 1):x + 2]))


def refuse_non_finite_result(image: np.ndarray, path) -> None:
    """The last guard before an output is written: a refocused image holding NaN or
    infinite values is never written (every input was checked, so this is a bug)."""
    if not np.isfinite(image).all():
        raise PassError(f"the refocused image for '{path}' holds NaN or infinite values (a "
                        f"bug; please report it with the inputs); nothing was written")


def write_result(path, result: RefocusResult, preview: bool = True) -> list[Path]:
    """EXR (premultiplied RGBA, linear; the settings in the ``mpib`` attribute) and PNG."""
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr
    from mpib_validate.runtime.io.preview import write_png

    path = Path(path)
    refuse_non_finite_result(result.image, path)
    img = result.image.copy()
    img[..., :3] *= img[..., 3:4]
    write_exr(path, channels_from_rgba(img), attributes={"mpib": json.dumps(result.info, default=float)})
    written = [path]
    if preview:
        write_png(path.with_suffix(".png"), result.image[..., :3])
        written.append(path.with_suffix(".png"))
    return written
