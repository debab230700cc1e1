"""The camera in an EXR header: how a render tells ``mpib refocus`` its lens.

A render carries its camera as one JSON object, in one of two header attributes:

- ``mpib`` (a string attribute): written by this project (``mpib render``,
  ``mpib refocus`` and the Blender extension's saved refocused EXRs);
- ``Note``: Blender's stamp note, holding the text ``mpib:`` followed by the same JSON
  object. The extension's ``render_pre`` handler sets it for every render, so every
  EXR that Blender writes of a render carries the camera: F12 then Image > Save As,
  ``write_still``, animation frames, and the extension's own kept passes. Blender keeps
  at most 511 bytes of a note (:data:`NOTE_LIMIT`), the camera needs about 250.

The object's ``camera`` member has one or both of these forms:

``camera.blender``: a Blender perspective camera, every field required
    ``lens_mm``            focal length in mm (Camera > Lens), > 0
    ``sensor_width_mm``    sensor width in mm, > 0
    ``sensor_height_mm``   sensor height in mm, > 0
    ``sensor_fit``         ``"AUTO"``, ``"HORIZONTAL"`` or ``"VERTICAL"``
    ``fstop``              f-number N, finite and > 0
    ``focus_distance``     planar depth in focus (scene units), > 0 (a focus object's
                           depth along the view axis, not its distance)
    ``unit_scale``         metres per scene unit as the lens sees it: 1 for Blender,
                           whose depth of field ignores the scene's Unit Scale
    ``width``, ``height``  rendered size in pixels (resolution times percentage)

  and optionally the aperture's shape (Camera > Depth of Field > Aperture; a disk when
  left out):
    ``aperture_blades``    0 (a disk) or 3 to 16; 1 and 2 render a disk in Cycles
    ``aperture_rotation``  radians, counter-clockwise on screen, finite
    ``aperture_ratio``     anamorphic ratio (x divided by it), finite and > 0

  which :func:`mpib_validate.runtime.camera.blender_camera` turns into ``A = R f_px``,
  ``d_f = 1 / focus_distance`` and the :class:`~mpib_validate.runtime.camera.Aperture`;

image-space (``mpib render``, and what a refocus used)
    ``width``, ``height``, ``blur_parameter`` (A, pixels per unit disparity),
    ``focus_disparity`` (1/scene unit), ``focal_length_px`` (optional), ``aperture``
    (optional: ``{"blades", "rotation", "ratio"}`` as above, rotation in radians).

The Blender form wins where both are given. Without either, Blender's own ``Lens``
stamp (Metadata > Lens, two decimals) gives the focal length and nothing else: the
f-stop, sensor and focus are then options. A ``mpib refocus`` output records in
``camera`` the image-space values it used, the lens fields that gave ``A`` under
``lens``, and where each field came from under ``from``.

:func:`read_camera` parses and checks a header (errors name the file and the field);
:func:`resolve` merges it with command-line values field by field into a
:class:`~mpib_validate.runtime.camera.Camera` (:func:`camera_from_header` with none);
:func:`stamp_note` writes the note.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from mpib_validate.runtime.camera import (DEFAULT_SENSOR_FIT, DEFAULT_SENSOR_HEIGHT_MM, DEFAULT_SENSOR_MM, DISK, MAX_BLADES, SENSOR_FITS, Aperture, ApertureError, Camera, blender_aperture, blender_camera)

ATTRIBUTE = "mpib"
NOTE_ATTRIBUTE = "Note"
NOTE_MARKER = "mpib:"
NOTE_LIMIT = 511  # bytes Blender keeps of a stamp note (measured with bpy 5.0.1)
LENS_STAMP = "Lens"

#: The lens fields (what gives ``A``) and the full Blender form.
LENS_FIELDS = ("lens_mm", "sensor_width_mm", "sensor_height_mm", "sensor_fit", "fstop",
               "unit_scale")
BLENDER_FIELDS = LENS_FIELDS + ("focus_distance", "width", "height")
#: The aperture's shape, optional in the Blender form (a disk when left out).
APERTURE_FIELDS = ("aperture_blades", "aperture_rotation", "aperture_ratio")
#: Blender's defaults for what a header or the user may leave out.
DEFAULTS = {"sensor_width_mm": DEFAULT_SENSOR_MM, "sensor_height_mm": DEFAULT_SENSOR_HEIGHT_MM,
            "sensor_fit": DEFAULT_SENSOR_FIT, "unit_scale": 1.0}
#: The ``mpib refocus`` option of each field (for messages and the ``from`` record).
OPTIONS = {"lens_mm": "--focal-mm", "sensor_width_mm": "--sensor-mm",
           "sensor_height_mm": "--sensor-height-mm", "sensor_fit": "--sensor-fit",
           "fstop": "--fstop", "unit_scale": "--scene-unit-m", "focus_distance": "--focus-depth",
           "focus_disparity": "--focus-disparity", "blur_parameter": "--blur-parameter",
           "aperture_blades": "--blades", "aperture_rotation": "--rotation",
           "aperture_ratio": "--ratio"}
_WHAT = {"lens_mm": "focal length", "fstop": "f-stop"}


class CameraHeaderError(ValueError):
    """A camera in a header or on the command line that cannot be used; the message
    names the file (or option) and the field."""


@dataclass(frozen=True)
class HeaderCamera:
    """The checked camera fields of one header.

    Attributes:
        source: where they were found, for messages (``"'r.exr' header 'mpib'"``).
        blender: Blender-form fields (all of :data:`BLENDER_FIELDS`, or only ``lens_mm``
            from Blender's Lens stamp).
        image: image-space fields (``blur_parameter``, ``focus_disparity``, ...).
    """

    source: str
    blender: dict
    image: dict


# -- checking ------------------------------------------------------------------------------

#: JSON read from files (headers, notes, scene.json) nested deeper than this is refused:
#: a camera header is four levels deep, and Python's parser and writer recurse once per
#: level (a RecursionError near a thousand).
MAX_JSON_DEPTH = 64


def _json_depth(obj) -> int:
    """Nesting depth of parsed JSON (a scalar is 0), without recursion."""
    deepest, stack = 0, [(obj, 0)]
    while stack:
        o, d = stack.pop()
        if isinstance(o, dict):
            o = list(o.values())
        if isinstance(o, list):
            deepest = max(deepest, d + 1)
            if d + 1 > MAX_JSON_DEPTH:
                break
            stack.extend((v, d + 1) for v in o)
    return deepest


def load_json(text, source: str, error=None, raw: bool = False):
    """Parse JSON read from a file: ``json.loads`` (or, with ``raw``, the first JSON
    value of ``text`` as ``(value, end)``), refusing malformed text, nesting deeper than
    :data:`MAX_JSON_DEPTH` and integers of more than Python's 4300 digits with one
    ``error`` (default :class:`CameraHeaderError`) that names ``source``."""
    error = error or CameraHeaderError
    try:
        out = json.JSONDecoder().raw_decode(text) if raw else json.loads(text)
    except RecursionError:
        raise error(f"{source} is JSON nested too deeply (more than {MAX_JSON_DEPTH} "
                    f"levels)") from None
    except (TypeError, ValueError) as exc:
        raise error(f"{source} is not valid JSON ({' '.join(str(exc).split())[:200]})") from None
    if _json_depth(out[0] if raw else out) > MAX_JSON_DEPTH:
        raise error(f"{source} is JSON nested too deeply (more than {MAX_JSON_DEPTH} levels)")
    return out


def shown(value) -> str:
    """``repr(value)``, shortened for a message (a 400-digit integer, a long string)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10 ** 15:
        return f"an integer of {len(str(abs(value)))} digits"
    text = repr(value)
    return text if len(text) <= 80 else text[:60] + "..." + text[-10:]

def _number(value, where: str, positive: bool = True) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if ok:
        try:
            number = float(value)
        except OverflowError:  # an integer beyond the float range
            number = math.inf
        ok = math.isfinite(number) and (number > 0 if positive else number >= 0)
    if not ok:
        raise CameraHeaderError(f"{where} must be a finite number {'>' if positive else '>='} 0, "
                                f"got {shown(value)}")
    return number


#: The largest image side a header may state (the renderers index pixels with 32-bit
#: integers).
MAX_SIDE = (1 << 31) - 1


def _size(value, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_SIDE:
        raise CameraHeaderError(f"{where} must be a whole number of pixels from 1 to {MAX_SIDE}, "
                                f"got {shown(value)}")
    return int(value)


def _fit(value, where: str) -> str:
    if not isinstance(value, str) or value.upper() not in SENSOR_FITS:
        raise CameraHeaderError(f"{where} must be one of {', '.join(SENSOR_FITS)}, got "
                                f"{shown(value)}")
    return value.upper()


def check_field(name: str, value, where: str):
    """``value`` of field ``name`` checked and normalised; ``where`` names it in the
    message of the :class:`CameraHeaderError` raised otherwise."""
    if name in ("width", "height"):
        return _size(value, where)
    if name == "sensor_fit":
        return _fit(value, where)
    if name == "focus_disparity":
        return _number(value, where, positive=False)
    if name == "aperture_blades":
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_BLADES:
            raise CameraHeaderError(f"{where} must be 0 (a disk) or 3 to {MAX_BLADES} blades, "
                                    f"got {value!r}")
        return int(value)
    if name == "aperture_rotation":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise CameraHeaderError(f"{where} must be a finite angle in radians, got {value!r}")
        return float(value)
    if name == "fstop":
        try:
            return _number(value, where)
        except CameraHeaderError as exc:
            raise CameraHeaderError(f"{exc} (no aperture, no defocus)") from None
    return _number(value, where)


def _check_blender(obj, where: str) -> dict:
    if not isinstance(obj, dict):
        raise CameraHeaderError(f"{where} must be a JSON object, got {shown(obj)}")
    missing = [k for k in BLENDER_FIELDS if k not in obj]
    if missing:
        raise CameraHeaderError(f"{where} lacks field(s) {', '.join(missing)}")
    return {k: check_field(k, obj[k], f"{where}.{k}") for k in BLENDER_FIELDS + APERTURE_FIELDS
            if k in obj}


def _check_aperture(obj, where: str) -> Aperture:
    """The image-space form's ``aperture`` object ``{"blades", "rotation", "ratio"}``."""
    if not isinstance(obj, dict):
        raise CameraHeaderError(f"{where} must be a JSON object, got {obj!r}")
    fields = {k: check_field("aperture_" + k, obj[k], f"{where}.{k}")
              for k in ("blades", "rotation", "ratio") if k in obj}
    return blender_aperture(fields.get("blades", 0), fields.get("rotation", 0.0),
                            fields.get("ratio", 1.0))


def _check_image(obj: dict, where: str) -> dict:
    out = {}
    for k, positive in (("width", True), ("height", True), ("blur_parameter", False),
                        ("focus_disparity", False), ("focal_length_px", True)):
        if k in obj:
            if k in ("width", "height"):
                out[k] = _size(obj[k], f"{where}.{k}")
            else:
                out[k] = _number(obj[k], f"{where}.{k}", positive)
    if "aperture" in obj:
        out["aperture"] = _check_aperture(obj["aperture"], f"{where}.aperture")
    return out


def parse_camera_json(text, source: str) -> HeaderCamera | None:
    """The camera of one header JSON object (see the module docstring), ``None`` when
    it holds none. ``source`` names the file and attribute in messages."""
    doc = load_json(text, source)
    if not isinstance(doc, dict):
        raise CameraHeaderError(f"{source} must hold a JSON object, got {type(doc).__name__}")
    if "camera" not in doc:
        return None
    cam = doc["camera"]
    if not isinstance(cam, dict):
        raise CameraHeaderError(f"{source} field camera must be a JSON object, got {shown(cam)}")
    blender = _check_blender(cam["blender"], f"{source} field camera.blender") if "blender" in cam else {}
    image = _check_image(cam, f"{source} field camera")
    if not blender and not image:
        return None
    return HeaderCamera(source, blender, image)


def read_camera(header: dict, path) -> HeaderCamera | None:
    """The camera an EXR header carries: the ``mpib`` attribute, else the extension's
    stamp note, else Blender's Lens stamp (focal length only); ``None`` if none.
    Raises :class:`CameraHeaderError` naming ``path`` and the field when it is malformed."""
    if ATTRIBUTE in header:
        found = parse_camera_json(header[ATTRIBUTE], f"'{path}' header '{ATTRIBUTE}'")
        if found is not None:
            return found
    note = header.get(NOTE_ATTRIBUTE)
    if isinstance(note, str) and NOTE_MARKER + "{" in note:
        text = note[note.index(NOTE_MARKER + "{") + len(NOTE_MARKER):]
        source = f"'{path}' header '{NOTE_ATTRIBUTE}' (Blender's stamp note)"
        try:
            doc, _ = load_json(text, source, raw=True)
        except CameraHeaderError as exc:
            raise CameraHeaderError(f"{exc} after '{NOTE_MARKER}' (Blender keeps {NOTE_LIMIT} "
                                    f"bytes of a note)") from None
        found = parse_camera_json(json.dumps(doc), source)
        if found is not None:
            return found
    lens = header.get(LENS_STAMP)
    if isinstance(lens, str):
        source = f"'{path}' header '{LENS_STAMP}' (Blender's Lens stamp)"
        try:
            value = float(lens.replace("mm", "").strip())
        except ValueError:
            raise CameraHeaderError(f"{source} is not a focal length in mm: {lens!r}") from None
        return HeaderCamera(source, {"lens_mm": check_field("lens_mm", value, source)}, {})
    return None


# -- writing -----------------------------------------------------------------------------

def camera_json(blender: dict) -> str:
    """Compact JSON ``{"camera": {"blender": ...}}`` of a Blender camera, checked. A
    disk's aperture fields (fewer than 3 blades, ratio 1) are left out: a disk is what a
    header without them means."""
    fields = _check_blender(blender, "the camera")
    if fields.get("aperture_blades", 0) < 3 and fields.get("aperture_ratio", 1.0) == 1.0:
        for k in APERTURE_FIELDS:
            fields.pop(k, None)
    return json.dumps({"camera": {"blender": fields}}, separators=(",", ":"))


def stamp_note(blender: dict, user_note: str = "") -> str | None:
    """The stamp note text that carries ``blender``: ``mpib:{json}``, after the artist's
    own note if there is one; ``None`` if it would not fit in Blender's 511 bytes."""
    ours = NOTE_MARKER + camera_json(blender)
    text = f"{user_note} {ours}" if user_note else ours
    return text if len(text.encode("utf-8")) <= NOTE_LIMIT else None


def user_note(note: str) -> str:
    """The artist's part of a stamp note (what :func:`stamp_note` put before ours)."""
    i = note.find(NOTE_MARKER + "{")
    return note if i < 0 else note[:i].rstrip()


# -- resolving ---------------------------------------------------------------------------

@dataclass(frozen=True)
class ResolvedCamera:
    """The camera a refocus runs with and where each field came from.

    Attributes:
        camera: size, ``A``, ``d_f`` (and ``f_px`` when known).
        lens: the Blender lens fields that gave ``A`` (``None`` when ``A`` was given).
        sources: field -> origin (an option, a header, ``"default"``).
    """

    camera: Camera
    lens: dict | None
    sources: dict

    def header(self) -> dict:
        """The ``camera`` member of the output's ``mpib`` attribute: the image-space
        values used, ``lens`` and ``from`` (see the module docstring)."""
        out = self.camera.to_dict()
        if self.lens is not None:
            out["lens"] = dict(self.lens)
        out["from"] = dict(self.sources)
        return out


def _same_image(fields: dict, src: str, width: int, height: int, where: str) -> None:
    """Refuse a header camera whose stated image size is not the image's: its ``A`` (and
    focal length in pixels) scale with the width, so another size's would be wrong by
    that ratio."""
    for k, n in (("width", width), ("height", height)):
        if fields.get(k, n) != n:
            raise CameraHeaderError(
                f"{src} field {where}.{k} is {fields[k]} but the image is {width}x{height} "
                f"(cropped or resized after rendering?): give --blur-parameter")


def resolve(header: HeaderCamera | None, given: dict, width: int, height: int, path,
            labels: dict | None = None) -> ResolvedCamera:
    """Merge a header's camera with values given on the command line, field by field.

    ``given``: field -> value or ``None`` (not given), for :data:`LENS_FIELDS`,
    ``focus_distance``, ``focus_disparity`` and ``blur_parameter``; ``labels`` names
    a field's origin where it is not the option of :data:`OPTIONS` (e.g. a focus pixel).
    The aperture is ``A`` as given, else ``blender_camera`` of the lens fields (given,
    else the header's, else Blender's defaults for the sensor and unit scale), else
    the header's image-space ``A``. The focus is the given disparity or depth, else the
    header's. ``A`` given together with a lens field is refused. Raises
    :class:`CameraHeaderError` naming the option, or ``path`` and the field.
    """
    labels = {**OPTIONS, **(labels or {})}
    given = {k: check_field(k, v, labels[k]) if k != "blur_parameter" else v
             for k, v in given.items() if v is not None}
    if "blur_parameter" in given:
        A = given["blur_parameter"]
        if not (isinstance(A, (int, float)) and A > 0 and math.isfinite(A)):
            raise CameraHeaderError(f"{labels['blur_parameter']} must be finite and > 0 (a zero "
                                    f"aperture has no defocus), got {A}")
    mixed = [labels[k] for k in LENS_FIELDS if k in given]
    if "blur_parameter" in given and mixed:
        raise CameraHeaderError(f"{labels['blur_parameter']} gives A directly: do not combine it "
                                f"with {', '.join(mixed)}")
    hb = header.blender if header is not None else {}
    hi = header.image if header is not None else {}
    src = header.source if header is not None else ""
    sources = {}
    lens = None
    if "blur_parameter" in given:
        A, sources["blur_parameter"] = float(given["blur_parameter"]), labels["blur_parameter"]
        f_px = hi.get("focal_length_px")
        if f_px is not None and any(hi.get(k, n) != n for k, n in (("width", width),
                                                                  ("height", height))):
            f_px = None  # another image's focal length in pixels: not this one's
    elif mixed or hb:
        lens, missing = {}, []
        for k in LENS_FIELDS:
            if k in given:
                lens[k], sources[k] = given[k], labels[k]
            elif k in hb:
                lens[k], sources[k] = hb[k], src
            elif k in DEFAULTS:
                lens[k], sources[k] = DEFAULTS[k], "default"
            else:
                missing.append(k)
        if missing:
            opts = " and ".join(labels[k] for k in missing)
            what = " and ".join(_WHAT[k] for k in missing)
            where = (f"{src} gives only {', '.join(hb)}" if hb else
                     f"{src} holds no Blender lens" if src else f"'{path}' holds no camera")
            raise CameraHeaderError(f"no {what}: give {opts} ({where}; render with the MPIB "
                                    f"extension enabled to record the whole camera)")
        if src and src in sources.values():  # the header's lens must be this image's
            _same_image(hb, src, width, height, "camera.blender")
        # d_f below is 1/focus_distance, the very float blender_camera gives the add-on
        cam = blender_camera(**lens, width=width, height=height, focus_distance=1.0)
        A, f_px = cam.blur_parameter, cam.focal_length_px
        if not (A > 0 and math.isfinite(A)):  # e.g. --fstop 1e308: R f_px underflows to 0
            named = ", ".join(f"{sources[k]} {lens[k]}" if sources[k].startswith("--")
                              else f"{k} {lens[k]} ({sources[k]})" for k in LENS_FIELDS
                              if sources.get(k) not in (None, "default"))
            raise CameraHeaderError(f"the lens ({named}) gives a blur parameter A = {A} px per "
                                    f"unit disparity; it must be finite and > 0")
    elif "blur_parameter" in hi:
        _same_image(hi, src, width, height, "camera")
        A, sources["blur_parameter"] = hi["blur_parameter"], src
        f_px = hi.get("focal_length_px")
    else:
        raise CameraHeaderError(f"no aperture: give --blur-parameter, or --fstop and --focal-mm "
                                f"('{path}' holds no camera settings)")
    if "focus_disparity" in given:
        d_f, sources["focus_disparity"] = given["focus_disparity"], labels["focus_disparity"]
    elif "focus_distance" in given:
        d_f, sources["focus_distance"] = 1.0 / given["focus_distance"], labels["focus_distance"]
    elif "focus_distance" in hb:
        d_f, sources["focus_distance"] = 1.0 / hb["focus_distance"], src
    elif "focus_disparity" in hi:
        d_f, sources["focus_disparity"] = hi["focus_disparity"], src
    else:
        raise CameraHeaderError("no focus: give --focus-depth, --focus-disparity or --focus-pixel X,Y"
                                + (f" ({src} holds none)" if src else f" ('{path}' holds no camera)"))
    aperture = _resolve_aperture(given, labels, hb, hi, src, sources)
    camera = Camera(width, height, A, d_f, f_px, aperture)
    return ResolvedCamera(camera, lens, sources)


def resolve_aperture(given: dict, labels: dict | None = None) -> Aperture:
    """The aperture of options alone (``aperture_blades``, ``aperture_rotation`` in
    radians, ``aperture_ratio``; None or absent: a disk's), checked; the message of the
    :class:`CameraHeaderError` names the option (:data:`OPTIONS`)."""
    labels = {**OPTIONS, **(labels or {})}
    given = {k: check_field(k, v, labels[k]) for k, v in given.items() if v is not None}
    return _resolve_aperture(given, labels, {}, {}, "", {})


def _resolve_aperture(given: dict, labels: dict, hb: dict, hi: dict, src: str,
                      sources: dict) -> Aperture:
    """The aperture field by field: the option, else the header's Blender form, else its
    image-space ``aperture``, else a disk. A given blade count of 1 or 2 is refused
    (Blender's 1 and 2, which Cycles renders as a disk, are read as a disk from a header)."""
    b = given.get("aperture_blades")
    if b is not None and b in (1, 2):
        raise CameraHeaderError(f"{labels['aperture_blades']} must be 0 (a disk) or 3 to "
                                f"{MAX_BLADES}, got {b}")
    base = hi.get("aperture", DISK)
    fallback = {"aperture_blades": base.blades, "aperture_rotation": base.rotation,
                "aperture_ratio": base.ratio}
    value = {}
    for k in APERTURE_FIELDS:
        if k in given:
            value[k], sources[k] = given[k], labels[k]
        elif k in hb:
            value[k], sources[k] = hb[k], src
        else:
            value[k] = fallback[k]
            if "aperture" in hi:
                sources[k] = src
    try:
        return blender_aperture(value["aperture_blades"], value["aperture_rotation"],
                                value["aperture_ratio"])
    except ApertureError as exc:  # checked field by field above: not reached
        raise CameraHeaderError(str(exc)) from None



def camera_from_header(header: dict, path, width: int, height: int) -> Camera:
    """The :class:`Camera` an EXR header describes, with nothing overridden: a
    ``width`` x ``height`` image's ``A`` and ``d_f`` from :func:`read_camera`.
    Raises :class:`CameraHeaderError` naming ``path`` and the field."""
    return resolve(read_camera(header, path), {}, width, height, path).camera
