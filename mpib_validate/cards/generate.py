"""Seeded random card scenes in the manner of the MPIB supplement's generator (section 2).

A scene is a background card that covers the whole frame (and as far beyond it as a
defocused ray can land), plus a few foreground RGBA objects in front of it. Two
families, as in Table 1 of the supplement:

- ``constant``: every card fronto-parallel (constant disparity per object);
- ``varying``: every card on a tilted plane (disparity varies across it).

Disparities are normalised like the paper's, ``d`` in ``(0, 1]`` (1/scene-unit; depth
``Z = 1/d >= 1``). The blur parameter ``A`` (pixels per unit disparity) scales with the
image width, ``A = k W / 256`` with ``k`` drawn from ``[12, 40]`` (the official example:
``K = 50`` at 256 px; third parties used 4-32 at 1024 px).

Named hard cases (``HARD_CASES``) force one difficulty on purpose: thin structures,
hair-like masks, soft semi-transparent edges, HDR highlights (bokeh balls), an object
near the focus plane, a near-grazing tilted plane, a large blur (radius > 10 % of the
width), focus on the foreground, focus on the background.

Everything random comes from one ``numpy.random.Generator`` seeded with the scene's
seed, so the same seed gives the same scene, byte for byte.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mpib_validate.cards import textures as tx
from mpib_validate.runtime.camera import Camera
from mpib_validate.cards.scene import Card, Plane, Scene, SceneError

FAMILIES = ("constant", "varying")
HARD_CASES = ("thin", "hair", "soft", "hdr", "near-focus", "grazing", "large-blur",
              "focus-fg", "focus-bg")

_EVERYDAY_MASKS = ("disk", "ellipse", "rectangle", "blob", "horse", "hair", "thin", "soft")


@dataclass(frozen=True)
class GeneratorSettings:
    """Ranges the generator draws from (image sizes in pixels, disparity in 1/scene-unit)."""

    width: int = 256
    height: int = 256
    objects: tuple[int, int] = (2, 3)  # foreground objects, inclusive range
    blur_k: tuple[float, float] = (12.0, 40.0)  # A = k * width / 256
    background_disparity: tuple[float, float] = (0.02, 0.2)
    foreground_disparity: tuple[float, float] = (0.3, 1.0)
    object_size: tuple[float, float] = (0.3, 0.6)  # fraction of min(width, height)
    max_tilt: float = 0.35  # varying family: disparity change across an object
    hdr_probability: float = 0.3
    masks: tuple[str, ...] = _EVERYDAY_MASKS  # alpha-mask kinds to draw from


def _u(rng: np.random.Generator, lo_hi) -> float:
    return float(rng.uniform(lo_hi[0], lo_hi[1]))


def _tilted_plane(rng, d_centre: float, centre: tuple[float, float], span_px: float,
                  change: float) -> Plane:
    """A plane whose disparity changes by about ``change`` across ``span_px`` pixels."""
    theta = rng.uniform(0.0, 2.0 * math.pi)
    g = change / max(span_px, 1.0)
    return Plane.from_gradient(d_centre, g * math.cos(theta), g * math.sin(theta), at=centre)


def _object_card(rng, name: str, camera: Camera, settings: GeneratorSettings, family: str,
                 d_centre: float, mask_kind: str, hdr: bool, tilt: float | None) -> Card:
    side = int(round(_u(rng, settings.object_size) * min(camera.width, camera.height)))
    h = max(8, int(round(side * rng.uniform(0.75, 1.25))))
    w = max(8, int(round(side * rng.uniform(0.75, 1.25))))
    # the object's centre lands anywhere in the middle 80 % of the frame
    cx = int(round(rng.uniform(0.1, 0.9) * camera.width))
    cy = int(round(rng.uniform(0.1, 0.9) * camera.height))
    offset = (cx - w // 2, cy - h // 2)
    rgb = tx.random_texture(h, w, rng)
    if hdr:
        rgb = tx.hdr_highlights(rgb, rng, count=int(rng.integers(2, 6)))
    alpha = tx.alpha_mask(mask_kind, h, w, rng)
    rgba = np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.float32)
    centre = (offset[0] + 0.5 * w - 0.5 * camera.width, offset[1] + 0.5 * h - 0.5 * camera.height)
    if family == "constant" and tilt is None:
        plane = Plane.fronto(d_centre)
    else:
        change = tilt if tilt is not None else _u(rng, (0.3, 1.0)) * settings.max_tilt
        plane = _tilted_plane(rng, d_centre, centre, max(w, h), change)
    return Card(name, rgba, plane, offset)


def _background_card(rng, camera: Camera, family: str, d_bg: float, hdr: bool) -> Card:
    """A card covering the frame plus the widest ray displacement (Plane.max_shift)."""
    W, H = camera.width, camera.height
    if family == "constant":
        plane = Plane.fronto(d_bg)
    else:  # a receding ground-like plane: disparity grows downwards by up to ~60 %
        plane = Plane.from_gradient(d_bg, rng.uniform(-0.2, 0.2) * d_bg / W,
                                    rng.uniform(0.1, 0.6) * d_bg / H)
    shift = plane.max_shift(camera.blur_parameter, camera.focus_disparity,
                            -0.5 * W, 0.5 * W, -0.5 * H, 0.5 * H)
    margin = int(math.ceil(shift)) + 2
    rgb = tx.random_texture(H + 2 * margin, W + 2 * margin, rng)
    if hdr:
        rgb = tx.hdr_highlights(rgb, rng, count=int(rng.integers(4, 12)))
    rgba = np.concatenate([rgb, np.ones(rgb.shape[:2] + (1,), np.float32)], axis=-1)
    return Card("background", rgba.astype(np.float32), plane, (-margin, -margin))


def generate(seed: int, family: str = "constant", case: str | None = None,
             settings: GeneratorSettings | None = None, max_tries: int = 50) -> Scene:
    """Make a random card scene. Same ``(seed, family, case, settings)``, same scene.

    Args:
        seed: non-negative integer.
        family: ``constant`` or ``varying``.
        case: one of :data:`HARD_CASES`, or ``None`` for an everyday scene.
    """
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    if case is not None and case not in HARD_CASES:
        raise ValueError(f"case must be one of {HARD_CASES}, got {case!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    settings = settings or GeneratorSettings()
    rng = np.random.default_rng([int(seed), FAMILIES.index(family),
                                 0 if case is None else 1 + HARD_CASES.index(case)])
    last_error = None
    for _ in range(max_tries):  # resample the rare draws that make an invalid plane
        try:
            scene = _draw(rng, seed, family, case, settings)
            return scene.validate(f"generated scene (seed {seed})")
        except SceneError as exc:
            last_error = exc
    raise RuntimeError(f"could not draw a valid scene in {max_tries} tries: {last_error}")


def _draw(rng, seed, family, case, s: GeneratorSettings) -> Scene:
    W, H = s.width, s.height
    A = _u(rng, s.blur_k) * W / 256.0
    n_obj = int(rng.integers(s.objects[0], s.objects[1] + 1))
    d_bg = _u(rng, s.background_disparity)
    d_fg = np.sort(rng.uniform(*s.foreground_disparity, size=n_obj))[::-1]  # nearest first
    masks = [str(rng.choice(s.masks)) for _ in range(n_obj)]
    hdr = [bool(rng.random() < s.hdr_probability) for _ in range(n_obj + 1)]
    tilts: list[float | None] = [None] * n_obj

    # focus: anywhere between the background and the nearest object
    d_f = float(rng.uniform(d_bg, float(d_fg[0])))
    forced = {"thin": "thin", "hair": "hair", "soft": "soft"}
    if case in forced:
        masks[0] = forced[case]
    elif case == "hdr":
        hdr = [True] * (n_obj + 1)
        d_f = float(d_fg[0])  # background highlights blur into bokeh balls
    elif case == "focus-fg":
        d_f = float(d_fg[0])
    elif case == "focus-bg":
        d_f = d_bg
    elif case == "near-focus":
        # an object whose blur radius is only 0.3-1.5 px
        d_f = float(np.clip(d_fg[-1] + rng.choice([-1, 1]) * rng.uniform(0.3, 1.5) / A,
                            1e-3, 1.0))
    elif case == "grazing":
        tilts[0] = float(rng.uniform(0.7, 0.9)) * float(d_fg[0])  # disparity spans most of its range
    elif case == "large-blur":
        # focus on the nearest object; the background blurs to 12-20 % of the width
        d_f = float(d_fg[0])
        A = float(rng.uniform(0.12, 0.2)) * W / (d_f - d_bg)

    camera = Camera(W, H, A, d_f)
    cards = [_background_card(rng, camera, family, d_bg, hdr[0])]
    for i in range(n_obj):
        fam = "varying" if (case == "grazing" and i == 0) else family
        cards.append(_object_card(rng, f"object{i + 1}", camera, s, fam, float(d_fg[i]),
                                  masks[i], hdr[i + 1], tilts[i]))
    meta = {"generator": "mpib_validate.cards.generate", "seed": int(seed), "family": family,
            "case": case, "masks": masks, "hdr": hdr}
    return Scene(camera, cards, meta)


def official_example(width: int = 256, height: int | None = None, blur_parameter: float = 50.0,
                     focus_disparity: float = 0.5, seed: int = 0) -> Scene:
    """The official generator's example scene: a background and two objects at disparities
    0.01, 0.5 and 0.9, ``K = A = 50``, focus ``d_f = 0.5`` (fronto-parallel cards)."""
    height = height or width
    rng = np.random.default_rng([int(seed), 99])
    camera = Camera(width, height, blur_parameter, focus_disparity)
    bg_plane = Plane.fronto(0.01)
    margin = int(math.ceil(bg_plane.max_shift(blur_parameter, focus_disparity, -width / 2,
                                              width / 2, -height / 2, height / 2))) + 2
    bg = tx.shipped_image("chelsea", height + 2 * margin, width + 2 * margin, rng)
    bg_rgba = np.concatenate([bg, np.ones(bg.shape[:2] + (1,), np.float32)], axis=-1)
    cards = [Card("background", bg_rgba, bg_plane, (-margin, -margin))]
    for name, d, mask, image, (fx, fy) in (("middle", 0.5, "disk", "coffee", (0.3, 0.35)),
                                           ("near", 0.9, "horse", "astronaut", (0.62, 0.6))):
        h, w = int(0.5 * height), int(0.5 * width)
        rgb = tx.shipped_image(image, h, w, rng)
        alpha = tx.alpha_mask(mask, h, w, rng)
        rgba = np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.float32)
        offset = (int(fx * width - w / 2), int(fy * height - h / 2))
        cards.append(Card(name, rgba, Plane.fronto(d), offset))
    return Scene(camera, cards, {"generator": "official_example", "seed": seed}).validate()
