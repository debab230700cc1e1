"""Refocusing a rendered picture: read colour + depth, choose focus and aperture, render.

This is what ``mpib refocus`` and the Blender add-on run. Inputs are EXR files: a
Blender multilayer file (``ViewLayer.Combined.*`` and ``ViewLayer.Depth.Z``), one of
this project's renders (``AllInFocus.*`` and ``Depth.Z``, with the camera in its
``mpib`` header attribute), or colour and depth as two files.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .composite import render_subapertures
from .exr import ExrError, find_pass, read_exr, rgba_from
from .passes import DEFAULT_FAR_LIMIT, PassError, depth_to_disparity, layers_from_passes
from .presets import get_preset


@dataclass
class Passes:
    """Colour (``(H, W, 3)`` linear) and depth (``(H, W)`` scene units) with their origin."""

    colour: np.ndarray
    depth: np.ndarray
    colour_source: str
    depth_source: str
    camera: dict = field(default_factory=dict)  # from an mpib render's header, if any
    notices: list = field(default_factory=list)  # one line each, e.g. clamped negatives


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


def _refuse_non_finite(rgba: np.ndarray, source: str) -> None:
    """Raise :class:`PassError` naming ``source`` and the first NaN or infinite value
    (one would turn a whole blurred channel into NaN)."""
    bad = ~np.isfinite(rgba)
    if bad.any():
        y, x, c = np.argwhere(bad)[0]
        raise PassError(f"{source}: colour is NaN or infinite at {int(bad.sum())} value(s), "
                        f"first at (row {y}, column {x}, channel {'RGBA'[c]}): "
                        f"{rgba[y, x, c]}")


def read_colour(path, all_in_focus: bool = True, view_layer: str | None = None) -> np.ndarray:
    """``(H, W, 4)`` colour of an EXR (see :func:`_colour_prefix` for which channels).
    Raises :class:`PassError` naming the file and the first pixel for NaN or infinite
    values."""
    img = read_exr(path)
    prefix = _colour_prefix(img, all_in_focus, view_layer)
    rgba = rgba_from(img, prefix)
    _refuse_non_finite(rgba, f"'{path}' ({prefix or 'R, G, B'})")
    return rgba


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
    """Read colour and depth. Raises :class:`PassError`/:class:`ExrError` naming the file
    for a missing depth pass, mismatched sizes or NaN/infinite colour; negative colour
    is clamped to 0 with a notice in ``Passes.notices``. ``view_layer`` picks one of
    several Blender view layers in the file."""
    img = read_exr(path)
    prefix = _colour_prefix(img, view_layer=view_layer)
    colour = rgba_from(img, prefix)[..., :3]
    source = f"'{path}' ({prefix or 'R, G, B'})"
    _refuse_non_finite(colour, source)
    camera = {}
    if "mpib" in img.header:
        try:
            camera = json.loads(img.header["mpib"]).get("camera", {})
        except (TypeError, ValueError, AttributeError):
            camera = {}
        if not isinstance(camera, dict):
            camera = {}
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
                  [notice] if notice else [])


def blur_parameter_from_lens(fstop: float, focal_mm: float, width_px: int,
                             sensor_mm: float = 36.0, scene_unit_m: float = 1.0) -> float:
    """``A = R f_px`` with ``R = f / (2 N)`` (scene units) and ``f_px = f / sensor * W``
    (sensor fit horizontal), as Blender's thin lens."""
    if not (fstop > 0) or math.isinf(fstop):
        raise PassError(f"the f-stop must be finite and > 0, got {fstop} (no aperture, no defocus)")
    if not (focal_mm > 0 and sensor_mm > 0):
        raise PassError("focal length and sensor width must be > 0")
    R = focal_mm * 1e-3 / scene_unit_m / (2.0 * fstop)
    return R * focal_mm / sensor_mm * width_px


class Cancelled(Exception):
    """Raised by a progress callback to stop :func:`refocus` (the artist pressed Esc)."""


@dataclass
class RefocusResult:
    image: np.ndarray  # (H, W, 4): normalised colour + coverage
    info: dict


def read_background(path, shape) -> tuple[np.ndarray, np.ndarray]:
    """What lies behind the foreground, from a second render without it (e.g. the
    foreground excluded or held out): ``(colour (H, W, 3), valid (H, W))``, valid where
    its alpha is above 1/2 (everywhere if it has none). Raises :class:`PassError`
    naming the file if its size is not ``shape``."""
    rgba = read_colour(path, all_in_focus=True)
    if rgba.shape[:2] != tuple(shape):
        raise PassError(f"sizes differ: the background '{path}' is {rgba.shape[1]}x"
                        f"{rgba.shape[0]}, the passes are {shape[1]}x{shape[0]}")
    return rgba[..., :3], rgba[..., 3] > 0.5


def refocus(passes: Passes, blur_parameter: float, focus_disparity: float,
            preset: str = "default", far_limit: float = DEFAULT_FAR_LIMIT,
            progress=None, background=None) -> RefocusResult:
    """Build the MPI from the passes and render it with the preset's settings.

    ``background``: optional ``(colour, valid)`` of what lies behind the foreground (see
    :func:`read_background`); it replaces the hidden-background fill where valid.

    ``progress(fraction)``, if given, is called as the work goes on (layers up to 0.5,
    then compositing); raising from it stops the work, e.g. :class:`Cancelled`.
    """
    if not (blur_parameter > 0) or not math.isfinite(blur_parameter):
        raise PassError(f"the blur parameter must be finite and > 0 (a zero aperture has no "
                        f"defocus), got {blur_parameter}")
    if not (focus_disparity >= 0) or not math.isfinite(focus_disparity):
        raise PassError(f"the focus disparity must be finite and >= 0, got {focus_disparity}")
    p = get_preset(preset)
    t0 = time.perf_counter()
    D = depth_to_disparity(passes.depth, far_limit, source=passes.depth_source)
    first = second = None
    if progress is not None:
        first = lambda f: progress(0.5 * f)  # noqa: E731
        second = lambda f: progress(0.5 + 0.5 * f)  # noqa: E731
    mpi, info = layers_from_passes(passes.colour, D, blur_parameter, p.passes,
                                   background=background, progress=first)
    img = render_subapertures(mpi, blur_parameter, focus_disparity, p.subapertures,
                              p.composite, progress=second)
    seconds = time.perf_counter() - t0
    radius = blur_parameter * max(abs(float(D.max()) - focus_disparity),
                                  abs(float(D.min()) - focus_disparity))
    return RefocusResult(img, {
        "preset": preset, "planes": info.planes, "largest_radius_px": radius,
        "fill_fraction": info.fill_fraction, "edge_fraction": info.edge_fraction,
        "blur_parameter": blur_parameter, "focus_disparity": focus_disparity,
        "seconds": seconds, "layers_seconds": info.seconds,
        "colour": passes.colour_source, "depth": passes.depth_source})


def focus_from_pixel(passes: Passes, x: int, y: int, far_limit: float = DEFAULT_FAR_LIMIT) -> float:
    """Disparity to focus on pixel ``(x, y)``: the median over its 3x3 neighbourhood."""
    H, W = passes.depth.shape
    if not (0 <= x < W and 0 <= y < H):
        raise PassError(f"focus pixel ({x}, {y}) is outside the {W}x{H} image")
    D = depth_to_disparity(passes.depth, far_limit, source=passes.depth_source)
    return float(np.median(D[max(0, y - 1):y + 2, max(0, x - 1):x + 2]))


def write_result(path, result: RefocusResult, preview: bool = True) -> list[Path]:
    """EXR (premultiplied RGBA, linear; the settings in the ``mpib`` attribute) and PNG."""
    from .exr import channels_from_rgba, write_exr
    from .preview import write_png

    path = Path(path)
    img = result.image.copy()
    img[..., :3] *= img[..., 3:4]
    write_exr(path, channels_from_rgba(img), attributes={"mpib": json.dumps(result.info, default=float)})
    written = [path]
    if preview:
        write_png(path.with_suffix(".png"), result.image[..., :3])
        written.append(path.with_suffix(".png"))
    return written
