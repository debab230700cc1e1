"""Card scenes: planar RGBA cards with disparity planes, seen by one thin-lens camera.

This is the scene model of the MPIB supplement's generator (section 2). Each card is

- an image-space RGBA texture (straight alpha, linear radiance, HDR allowed): its
  all-in-focus appearance. Texel ``(i, j)`` covers the frame pixel
  ``(oy + i, ox + j)`` when the card is in focus, so a texture may be larger than
  the frame (negative offset) where a blurred view must see beyond the frame edge;
- a disparity plane (Eq. 6) ``d(x, y) = (1 - a x - b y) / c`` over image
  coordinates (pixels from the image centre, y down). In 3D this is the plane
  ``Z = a f_px X + b f_px Y + c`` (Eq. 9 with ``z_s = f_px``).

On disk a scene is a directory holding ``scene.json`` and one RGBA EXR per card; the
format is documented in ``docs/scene-format.md`` and is meant to be written by hand.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpib_validate.runtime.io.atomic import InputError, check_input, write_text
from mpib_validate.runtime.io.camera_header import MAX_SIDE, shown, load_json
from mpib_validate.runtime.camera import Aperture, ApertureError, Camera

FORMAT_NAME = "mpib-scene"
FORMAT_VERSION = 1
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


class SceneError(ValueError):
    """A scene that cannot be used. The message names the file, the card and the field."""


@dataclass(frozen=True)
class Plane:
    """Disparity plane ``d(x, y) = (1 - a x - b y) / c`` (Eq. 6), x and y in pixels from the centre.

    ``a`` and ``b`` are in 1/pixel, ``c`` in scene units (``c`` is the depth where
    the plane crosses the optical axis).
    """

    a: float
    b: float
    c: float

    @classmethod
    def fronto(cls, disparity: float) -> "Plane":
        """Fronto-parallel plane at constant disparity ``d`` (``c = 1/d``)."""
        if not disparity > 0:
            raise SceneError(f"a fronto-parallel plane needs disparity > 0, got {disparity}")
        return cls(0.0, 0.0, 1.0 / float(disparity))

    @classmethod
    def from_gradient(cls, disparity: float, grad_x: float, grad_y: float,
                      at: tuple[float, float] = (0.0, 0.0)) -> "Plane":
        """Plane with disparity ``disparity`` at point ``at`` and gradient (1/scene-unit per pixel).

        ``d(x, y) = d0 + gx (x - x0) + gy (y - y0)``, so ``1/c = d0 - gx x0 - gy y0``,
        ``a = -gx c`` and ``b = -gy c``. Raises :class:`SceneError` if the plane's
        disparity at the image centre is not positive (``c`` would be ``<= 0``).
        """
        inv_c = disparity - grad_x * at[0] - grad_y * at[1]
        if not inv_c > 0:
            raise SceneError(
                f"plane with disparity {disparity} at {at} and gradient ({grad_x}, {grad_y}) "
                f"has disparity {inv_c:.4g} <= 0 at the image centre (c would be <= 0)")
        c = 1.0 / inv_c
        return cls(-grad_x * c, -grad_y * c, c)

    @property
    def is_fronto(self) -> bool:
        return self.a == 0.0 and self.b == 0.0

    def disparity(self, x, y):
        """Disparity (1/scene-unit) at image coordinates ``x, y`` (pixels from the centre)."""
        return (1.0 - self.a * np.asarray(x) - self.b * np.asarray(y)) / self.c

    def max_shift(self, blur_parameter: float, focus_disparity: float,
                  x0: float, x1: float, y0: float, y1: float) -> float:
        """Largest ray displacement ``|x_n - x|`` (pixels, Eq. 15) over sensor points in
        ``[x0, x1] x [y0, y1]`` and the whole aperture.

        Eq. 15's numerator ``1 - a x - b y - c d_f`` is linear in ``(x, y)``, so its
        largest magnitude is at a corner; the denominator ``a A mu + b A nu + c`` is
        smallest on the aperture rim, at ``c - A hypot(a, b)``. The bound is
        ``A max|num| / (c - A hypot(a, b))``; it is exact for fronto-parallel planes
        (``A |d - d_f|``).
        """
        xs = np.array([x0, x1, x0, x1])
        ys = np.array([y0, y0, y1, y1])
        num = np.abs(1.0 - self.a * xs - self.b * ys - self.c * focus_disparity).max()
        den = self.c - blur_parameter * math.hypot(self.a, self.b)
        if den <= 0:
            return math.inf
        return float(blur_parameter * num / den)

    def to_dict(self) -> dict:
        return {"a": float(self.a), "b": float(self.b), "c": float(self.c)}


@dataclass(eq=False)
class Card:
    """One planar RGBA card.

    Attributes:
        name: identifier, also the texture's file stem (letters, digits, ``_.-``).
        rgba: ``(H_t, W_t, 4)`` float32 texture, straight alpha, linear radiance.
        plane: its disparity plane.
        offset: ``(ox, oy)``, the frame pixel (column, row) that texel ``(0, 0)``
            covers; may be negative.
    """

    name: str
    rgba: np.ndarray
    plane: Plane
    offset: tuple[int, int] = (0, 0)

    @property
    def size(self) -> tuple[int, int]:
        """Texture size ``(W_t, H_t)`` in texels."""
        return int(self.rgba.shape[1]), int(self.rgba.shape[0])

    def extent(self, camera: Camera) -> tuple[float, float, float, float]:
        """Texture extent in image coordinates: ``(x0, x1, y0, y1)``, half-open."""
        w, h = self.size
        x0 = self.offset[0] - 0.5 * camera.width
        y0 = self.offset[1] - 0.5 * camera.height
        return x0, x0 + w, y0, y0 + h

    def disparity_range(self, camera: Camera) -> tuple[float, float]:
        """Smallest and largest disparity over the texture's extent (a plane: at its corners)."""
        x0, x1, y0, y1 = self.extent(camera)
        d = self.plane.disparity(np.array([x0, x1, x0, x1]), np.array([y0, y0, y1, y1]))
        return float(d.min()), float(d.max())

    def premultiplied(self) -> np.ndarray:
        """``(H_t, W_t, 4)`` float32 texture with colour multiplied by alpha."""
        out = np.array(self.rgba, dtype=np.float32, copy=True)
        out[..., :3] *= out[..., 3:4]
        return out


@dataclass(eq=False)
class Scene:
    """A camera and its cards. Card order carries no meaning (rays sort by depth)."""

    camera: Camera
    cards: list[Card] = field(default_factory=list)
    metadata: dict = field(default_factory=dict)
    #: the files it was read from (``scene.json`` and every texture), when loaded
    sources: list[Path] = field(default_factory=list)

    def validate(self, source: str = "scene") -> "Scene":
        """Check everything a renderer relies on; raise :class:`SceneError` naming card and field."""
        validate_camera(self.camera, source)
        names = set()
        for i, card in enumerate(self.cards):
            validate_card(card, self.camera, source, i)
            if card.name in names:
                raise SceneError(f"{source}: card '{card.name}' field 'name': duplicate card name")
            names.add(card.name)
        if not self.cards:
            raise SceneError(f"{source}: field 'cards': a scene needs at least one card")
        return self

    def disparity_range(self) -> tuple[float, float]:
        """Smallest and largest disparity over all cards' extents."""
        ranges = [c.disparity_range(self.camera) for c in self.cards]
        return min(r[0] for r in ranges), max(r[1] for r in ranges)

    def max_blur_radius(self) -> float:
        """Largest blur radius ``A |d - d_f|`` (pixels) over all cards' extents."""
        lo, hi = self.disparity_range()
        return self.camera.blur_radius(lo) if abs(lo - self.camera.focus_disparity) > abs(
            hi - self.camera.focus_disparity) else self.camera.blur_radius(hi)

    def with_camera(self, **changes) -> "Scene":
        """Same cards, camera with some fields replaced (e.g. ``focus_disparity=0.3``)."""
        return Scene(dataclasses.replace(self.camera, **changes), self.cards,
                     dict(self.metadata), list(self.sources))


# --------------------------------------------------------------------------------------
# Validation


def _finite_number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise SceneError(f"{where}: must be a number, got {shown(value)}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond the float range
        number = math.inf
    if not math.isfinite(number):
        raise SceneError(f"{where}: must be finite, got {shown(value)}")
    return number


def validate_camera(camera: Camera, source: str = "scene") -> None:
    where = f"{source}: camera field"
    for f in ("width", "height"):
        v = getattr(camera, f)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise SceneError(f"{where} '{f}': must be a positive integer, got {v!r}")
    a = _finite_number(camera.blur_parameter, f"{where} 'blur_parameter'")
    if a <= 0:
        raise SceneError(f"{where} 'blur_parameter': the blur parameter A (pixels per unit "
                         f"disparity) must be > 0, got {a} (a zero aperture has no defocus)")
    df = _finite_number(camera.focus_disparity, f"{where} 'focus_disparity'")
    if df < 0:
        raise SceneError(f"{where} 'focus_disparity': must be >= 0 (0 = focus at infinity), got {df}")
    f = _finite_number(camera.focal_length_px, f"{where} 'focal_length_px'")
    if f <= 0:
        raise SceneError(f"{where} 'focal_length_px': must be > 0, got {f}")


def validate_card(card: Card, camera: Camera, source: str = "scene", index: int = 0) -> None:
    """Raise :class:`SceneError` unless ``card`` is renderable with ``camera``."""
    label = f"{source}: card '{card.name}'" if isinstance(card.name, str) else f"{source}: card #{index}"
    if not isinstance(card.name, str) or not _NAME_RE.match(card.name):
        raise SceneError(f"{label} field 'name': must match {_NAME_RE.pattern}, got {card.name!r}")
    a = _finite_number(card.plane.a, f"{label} field 'plane.a'")
    b = _finite_number(card.plane.b, f"{label} field 'plane.b'")
    c = _finite_number(card.plane.c, f"{label} field 'plane.c'")
    if c <= 0:
        raise SceneError(f"{label} field 'plane.c': must be > 0 (depth where the plane crosses "
                         f"the optical axis), got {c}")
    rgba = card.rgba
    if not isinstance(rgba, np.ndarray) or rgba.ndim != 3 or rgba.shape[2] != 4:
        raise SceneError(f"{label} field 'texture': needs an (H, W, 4) RGBA array, got shape "
                         f"{getattr(rgba, 'shape', None)}")
    if rgba.shape[0] < 1 or rgba.shape[1] < 1:
        raise SceneError(f"{label} field 'texture': empty texture {rgba.shape}")
    if not np.issubdtype(rgba.dtype, np.floating):
        raise SceneError(f"{label} field 'texture': must be floating point, got {rgba.dtype}")
    if not np.isfinite(rgba).all():
        bad = np.argwhere(~np.isfinite(rgba))[0]
        raise SceneError(f"{label} field 'texture': NaN or infinite value at texel "
                         f"(row {bad[0]}, column {bad[1]}, channel {'RGBA'[bad[2]]})")
    if (rgba[..., :3] < 0).any():
        raise SceneError(f"{label} field 'texture': negative radiance")
    alpha = rgba[..., 3]
    if (alpha < 0).any() or (alpha > 1).any():
        raise SceneError(f"{label} field 'texture': alpha outside [0, 1] "
                         f"(min {alpha.min():.4g}, max {alpha.max():.4g})")
    for k, v in zip(("offset.x", "offset.y"), card.offset):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise SceneError(f"{label} field '{k}': must be an integer pixel offset, got {v!r}")
    d_lo, _ = card.disparity_range(camera)
    if not d_lo > 0:
        raise SceneError(f"{label} field 'plane': disparity reaches {d_lo:.4g} <= 0 inside the "
                         f"card's extent (zero or negative depth); shrink the texture or "
                         f"change the plane")
    # Eq. 15's denominator a A mu + b A nu + c must stay positive over the aperture disk:
    # otherwise the plane passes through the lens.
    lens_margin = c - camera.blur_parameter * math.hypot(a, b)
    if not lens_margin > 0:
        raise SceneError(f"{label} field 'plane': the plane passes through the lens aperture "
                         f"(needs c > A*hypot(a, b): {c:.4g} <= "
                         f"{camera.blur_parameter * math.hypot(a, b):.4g})")


# --------------------------------------------------------------------------------------
# On-disk format


def _card_to_json(card: Card, texture_path: str) -> dict:
    entry = {
        "name": card.name,
        "texture": texture_path,
        "size": list(card.size),
        "offset": [int(card.offset[0]), int(card.offset[1])],
    }
    if card.plane.is_fronto:  # for the reader; "plane" keeps c exact (1/(1/c) may differ)
        entry["disparity"] = 1.0 / card.plane.c
    entry["plane"] = card.plane.to_dict()
    return entry


def save_scene(scene: Scene, directory: str | os.PathLike, *, half: bool = False) -> Path:
    """Write ``scene.json`` and ``cards/<name>.exr`` under ``directory``; returns the JSON path.

    Every file is written atomically; ``scene.json`` is written last, so a directory
    with a ``scene.json`` is complete. Output is byte-for-byte deterministic.
    """
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    scene.validate(str(directory))
    directory = Path(directory)
    entries = []
    for card in scene.cards:
        rel = f"cards/{card.name}.exr"
        write_exr(directory / rel, channels_from_rgba(card.rgba), half=half)
        entries.append(_card_to_json(card, rel))
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "camera": scene.camera.to_dict(),
        "cards": entries,
    }
    if scene.metadata:
        doc["metadata"] = scene.metadata
    path = directory / "scene.json"
    write_text(path, json.dumps(doc, indent=2, sort_keys=True) + "\n")
    return path


#: The fields each object of ``scene.json`` may have (docs/scene-format.md).
TOP_FIELDS = ("format", "version", "camera", "cards", "metadata")
CAMERA_FIELDS = ("width", "height", "blur_parameter", "focus_disparity", "focal_length_px",
                 "aperture")
#: The fields of the camera's optional ``aperture`` (a disk when left out).
APERTURE_FIELDS = ("blades", "rotation", "ratio")
CARD_FIELDS = ("name", "texture", "size", "offset", "disparity", "plane")
PLANE_FIELDS = ("a", "b", "c")


def _refuse_unknown(obj: dict, known, where: str) -> None:
    """Raise :class:`SceneError` for a key that is not a field, naming the nearest one
    (a typo such as ``ofset`` would otherwise be ignored silently)."""
    for key in obj:
        if key in known:
            continue
        near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.5)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        raise SceneError(f"{where}: unknown field '{key}'{hint} (fields: {', '.join(known)})")


def _field(obj: dict, key: str, where: str, default=KeyError):
    if key not in obj:
        if default is KeyError:
            raise SceneError(f"{where}: missing field '{key}'")
        return default
    return obj[key]


def _int_pair(value, where: str) -> tuple[int, int]:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        raise SceneError(f"{where}: must be a pair of integers [x, y], got {shown(value)}")
    if not all(abs(v) <= MAX_SIDE for v in value):
        raise SceneError(f"{where}: must be a pair of integers of at most {MAX_SIDE} in size, "
                         f"got {shown(value)}")
    return int(value[0]), int(value[1])


def _plane_from_json(entry: dict, where: str) -> Plane:
    if "plane" in entry:
        p = entry["plane"]
        if not isinstance(p, dict):
            raise SceneError(f"{where} field 'plane': must be an object {{a, b, c}}, got {p!r}")
        _refuse_unknown(p, PLANE_FIELDS, f"{where} field 'plane'")
        vals = [_finite_number(_field(p, k, f"{where} field 'plane'"), f"{where} field 'plane.{k}'")
                for k in ("a", "b", "c")]
        plane = Plane(*vals)
        if "disparity" in entry:
            d = _finite_number(entry["disparity"], f"{where} field 'disparity'")
            if not plane.is_fronto or not math.isclose(d * plane.c, 1.0, rel_tol=1e-9):
                raise SceneError(f"{where} fields 'disparity' and 'plane' disagree "
                                 f"(disparity {d}, plane {plane})")
        return plane
    if "disparity" in entry:
        d = _finite_number(entry["disparity"], f"{where} field 'disparity'")
        if d <= 0:
            raise SceneError(f"{where} field 'disparity': must be > 0, got {d}")
        return Plane(0.0, 0.0, 1.0 / d)
    raise SceneError(f"{where}: needs a 'disparity' (fronto-parallel) or a 'plane' {{a, b, c}}")


#: A ``scene.json`` larger than this is refused before it is read (a scene of a thousand
#: cards is about 300 kB).
MAX_SCENE_JSON_BYTES = 16 << 20
#: Bytes per texel of reading the textures: each kept as float32 RGBA and, premultiplied,
#: by the tracer (``budget.TEXEL_BYTES``), plus one texture's decoding at a time (its
#: channels, at most 4 B each, and the float32 RGBA assembled from them).
READ_BYTES_PER_TEXEL_CHANNEL = 4
READ_BYTES_PER_TEXEL = 16


def _texture_path(json_path: Path, tex_rel: str, where: str, allow_outside: bool) -> Path:
    """The texture file a card names, relative to the scene folder. A path that leads
    outside the folder (``..``, an absolute path, a symbolic link pointing out) is
    refused unless ``allow_outside``: a scene folder from elsewhere must not read other
    files of this machine into a render (docs/scene-format.md, "Texture paths")."""
    tex_path = json_path.parent / tex_rel
    if not allow_outside:
        root = json_path.parent.resolve()
        try:
            inside = tex_path.resolve().is_relative_to(root)
        except (OSError, RuntimeError):  # a symbolic link loop
            inside = False
        if not inside:
            raise SceneError(f"{where} field 'texture': '{tex_rel}' lies outside the scene "
                             f"folder '{root}'; textures are read only from inside it (give "
                             f"--allow-outside-textures to read it anyway)")
    try:
        check_input(tex_path, "texture")
    except InputError as exc:
        what = str(exc).rsplit("': ", 1)[-1].removeprefix("file ").removeprefix("it ")
        raise SceneError(f"{where} field 'texture': file '{tex_path}' {what}") from None
    return tex_path


def load_scene(path: str | os.PathLike, *, allow_outside: bool = False,
               memory_limit: int | None = None) -> Scene:
    """Read a scene directory (or its ``scene.json``) and validate it.

    Raises :class:`SceneError` naming the file, the card and the field on any problem:
    missing or unreadable files, NaN, ``c <= 0``, non-positive depth inside a card,
    a texture whose size disagrees with the declared ``size``, and so on.

    ``allow_outside``: read texture paths that lead outside the scene folder (refused
    by default, see :func:`_texture_path`). ``memory_limit``: bytes; the textures'
    sizes are read from their headers and a scene whose textures would need more
    (:data:`READ_BYTES_PER_TEXEL` and per channel) is refused before any is decoded
    (:class:`~mpib_validate.runtime.budget.BudgetError` naming ``--max-memory-gb``).
    """
    from mpib_validate.runtime.io.exr import ExrError, header_size, read_exr, rgba_from

    path = Path(path)
    json_path = path / "scene.json" if path.is_dir() else path
    if not json_path.exists():
        raise SceneError(f"{json_path}: scene file does not exist")
    try:
        check_input(json_path, "scene file")
    except InputError as exc:
        raise SceneError(str(exc)) from None
    size = json_path.stat().st_size
    if size > MAX_SCENE_JSON_BYTES:
        raise SceneError(f"{json_path}: scene file is {size:,} bytes, more than the "
                         f"{MAX_SCENE_JSON_BYTES:,} a scene.json may have")
    try:
        text = json_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{json_path}: cannot parse scene JSON: {exc}") from None
    src = str(json_path)
    doc = load_json(text, f"{src}: cannot parse scene JSON: the file", SceneError)
    if not isinstance(doc, dict):
        raise SceneError(f"{src}: top level must be a JSON object")
    _refuse_unknown(doc, TOP_FIELDS, src)
    if doc.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise SceneError(f"{src}: field 'format' must be '{FORMAT_NAME}', got "
                         f"{shown(doc.get('format'))}")
    if doc.get("version", FORMAT_VERSION) != FORMAT_VERSION:
        raise SceneError(f"{src}: field 'version': unsupported version "
                         f"{shown(doc.get('version'))}")

    cam = _field(doc, "camera", src)
    if not isinstance(cam, dict):
        raise SceneError(f"{src}: field 'camera' must be an object")
    _refuse_unknown(cam, CAMERA_FIELDS, f"{src}: camera")
    for key in ("width", "height", "blur_parameter", "focus_disparity"):
        _field(cam, key, f"{src}: camera")
    for key in ("width", "height"):  # Camera derives its default focal length from them
        v = cam[key]
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_SIDE:
            raise SceneError(f"{src}: camera field '{key}': must be a positive integer of at "
                             f"most {MAX_SIDE}, got {shown(v)}")
    for key in ("blur_parameter", "focus_disparity", "focal_length_px"):
        if key in cam:
            _finite_number(cam[key], f"{src}: camera field '{key}'")
    cam = dict(cam)
    if "aperture" in cam:
        ap = cam["aperture"]
        if not isinstance(ap, dict):
            raise SceneError(f"{src}: camera field 'aperture' must be an object")
        _refuse_unknown(ap, APERTURE_FIELDS, f"{src}: camera aperture")
        try:
            cam["aperture"] = Aperture(**ap)
        except ApertureError as exc:
            raise SceneError(f"{src}: camera aperture: {exc}") from None
        except (TypeError, OverflowError) as exc:  # a field of the wrong type
            raise SceneError(f"{src}: camera aperture: {' '.join(str(exc).split())[:200]}") from None
    camera = Camera(**cam)
    validate_camera(camera, src)

    cards_json = _field(doc, "cards", src)
    if not isinstance(cards_json, list):
        raise SceneError(f"{src}: field 'cards' must be a list")
    metadata = doc.get("metadata", {})
    if not isinstance(metadata, dict):
        raise SceneError(f"{src}: field 'metadata' must be an object, got {shown(metadata)}")
    entries = []
    for i, entry in enumerate(cards_json):
        if not isinstance(entry, dict):
            raise SceneError(f"{src}: card #{i} must be an object")
        name = _field(entry, "name", f"{src}: card #{i}")
        where = f"{src}: card '{name}'" if isinstance(name, str) else f"{src}: card #{i}"
        _refuse_unknown(entry, CARD_FIELDS, where)
        tex_rel = _field(entry, "texture", where)
        if not isinstance(tex_rel, str) or not tex_rel.strip():
            raise SceneError(f"{where} field 'texture': must be the path of an EXR file "
                             f"(relative to scene.json), got {shown(tex_rel)}")
        entries.append((entry, name, where, _texture_path(json_path, tex_rel, where,
                                                          allow_outside)))
    if memory_limit is not None:  # sizes from the headers, before decoding any texture
        from mpib_validate.runtime import budget

        texels, decode = 0, 0
        for _, _, where, tex_path in entries:
            try:
                w, h, nch = header_size(tex_path)
            except ExrError as exc:
                raise SceneError(f"{where} field 'texture': {exc}") from None
            texels += w * h
            decode = max(decode, (READ_BYTES_PER_TEXEL_CHANNEL * nch + READ_BYTES_PER_TEXEL)
                         * w * h)
        budget.check(budget.Estimate(f"reading the textures of {src}",
                                     {"textures": budget.TEXEL_BYTES * texels,
                                      "decoding one texture": decode}), memory_limit)
    cards = []
    sources = [json_path]
    for entry, name, where, tex_path in entries:
        sources.append(tex_path)
        try:
            rgba = rgba_from(read_exr(tex_path)).astype(np.float32, copy=False)
        except ExrError as exc:
            raise SceneError(f"{where} field 'texture': {exc}") from None
        if "size" in entry:
            size = _int_pair(entry["size"], f"{where} field 'size'")
            if size != (rgba.shape[1], rgba.shape[0]):
                raise SceneError(f"{where} field 'size': declared {size[0]}x{size[1]} but "
                                 f"'{tex_path}' is {rgba.shape[1]}x{rgba.shape[0]}")
        if "offset" in entry:
            offset = _int_pair(entry["offset"], f"{where} field 'offset'")
        else:  # centred on the frame
            offset = ((camera.width - rgba.shape[1]) // 2, (camera.height - rgba.shape[0]) // 2)
        cards.append(Card(name, rgba, _plane_from_json(entry, where), offset))
    return Scene(camera, cards, dict(metadata), sources).validate(src)
