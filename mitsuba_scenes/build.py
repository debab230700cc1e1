"""Card scenes to Mitsuba 3 objects, and the front-to-back compositing integrator.

Two Mitsuba renderings of one :class:`~mpib_validate.cards.scene.Scene`:

- :func:`build` (used by :func:`mitsuba_scenes.render`): all cards in one mesh, two
  triangles per card, so triangle ``2k`` and ``2k + 1`` belong to card ``k`` and the
  hit's ``prim_index // 2`` names the card (no shape-pointer comparison needed). The
  Python integrator ``mpib_cards`` (:class:`CardCompositor`) follows each camera ray
  through every card it crosses, looks up the nearest texel from the hit point's
  pinhole projection (projective, exact for tilted cards) and composites front to
  back. It has no randomness beyond the camera's pixel and aperture samples.
- :func:`mitsuba_scenes.to_xml` (stock plugins only, for the ``mitsuba`` command): one
  shape per card with an area emitter whose radiance is the premultiplied texture and a
  ``mask`` BSDF whose opacity is alpha, plus a black backstop, rendered by the stock
  ``path`` integrator. It picks each card's alpha at random, but needs nothing but
  Mitsuba.

The sensor is a ``thinlens`` at the origin looking down +Z with OpenCV axes, ``fov``
along x from the camera, ``aperture_radius = R = A / f``, ``focus_distance = 1/d_f``,
a box pixel filter (each sample lands in exactly one pixel: the canonical pixel model).

``fault`` (tests only) injects one known error, to show the agreement statistic
rejects it: ``shift`` (cards half a pixel to the right), ``flip`` (image y axis
mirrored), ``aperture`` (1.5x aperture radius), ``alpha`` (straight colour used as if
it were premultiplied).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mpib_validate.cards.scene import Scene

from . import geometry

FAULTS = ("shift", "flip", "aperture", "alpha")
SAMPLERS = ("independent", "stratified")
INTEGRATOR_NAME = "mpib_cards"
#: Film channels of the compositing integrator, after R, G, B: coverage ``1 - T`` and
#: the per-pixel means of the squared sample values (for the per-pixel variance).
AOV_NAMES = ("coverage", "R2", "G2", "B2", "coverage2")
#: Focus "at infinity" (d_f = 0) is put this many times beyond the farthest card: the
#: focus disparity error is then < 1e-6 of the smallest card disparity.
FAR_FOCUS_FACTOR = 1e6


def _check_fault(fault):
    if fault is not None and fault not in FAULTS:
        raise ValueError(f"fault must be one of {FAULTS} or None, got {fault!r}")


def _check_sampler(sampler: str, spp: int) -> None:
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    if sampler == "stratified" and math.isqrt(int(spp)) ** 2 != spp:
        # Mitsuba would silently round it to a square
        raise ValueError(f"the stratified sampler needs a square spp, got {spp}")


def sensor_dict(mi, scene: Scene, spp: int, sampler: str = "independent",
                pixel_format: str = "rgb", fault: str | None = None) -> dict:
    """The ``thinlens`` sensor, film and sampler of ``scene.camera`` as a Mitsuba dict."""
    cam = scene.camera
    s = cam.mitsuba_settings()
    z_near, z_far = geometry.depth_range(scene)
    focus = s["focus_distance"]
    if not math.isfinite(focus):
        focus = FAR_FOCUS_FACTOR * z_far
    radius = s["aperture_radius"] * (1.5 if fault == "aperture" else 1.0)
    to_world = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0])
    if fault == "flip":  # mirror the camera's y axis: image rows come out upside down
        to_world = to_world @ mi.ScalarTransform4f().scale([1, -1, 1])
    return {
        "type": "thinlens",
        "to_world": to_world,
        "fov": float(s["fov"]),
        "fov_axis": "x",
        "aperture_radius": float(radius),
        "focus_distance": float(focus),
        # clip planes well outside the cards' depth range (rays leave the lens at any angle)
        "near_clip": float(min(1e-2, 1e-3 * z_near)),
        "far_clip": float(100.0 * z_far),
        "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height),
                 "pixel_format": pixel_format, "component_format": "float32",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": sampler, "sample_count": int(spp)},
    }


# --------------------------------------------------------------------------------------
# The compositing integrator


@dataclass
class CardTables:
    """Per-card lookup tables for :class:`CardCompositor` (numpy; moved to the device
    by :meth:`CardCompositor.set_tables`).

    Attributes:
        texels: ``(N, 4)`` float32 RGBA of all cards, card after card, row-major;
            colour premultiplied by alpha (straight with the ``alpha`` fault).
        origin: ``(K, 2)`` float32 frame pixel (x, y from the top-left corner) of
            texel (0, 0)'s corner (the card offset; +0.5 in x with the ``shift`` fault).
        size: ``(K, 2)`` int32 texture size ``(W_t, H_t)``.
        base: ``(K,)`` int32 index of each card's first texel in ``texels``.
        focal_px: ``f`` in pixels; half_w, half_h: ``W/2`` and ``H/2``.
    """

    texels: np.ndarray
    origin: np.ndarray
    size: np.ndarray
    base: np.ndarray
    focal_px: float
    half_w: float
    half_h: float


def card_tables(scene: Scene, fault: str | None = None) -> CardTables:
    """The tables of :class:`CardTables` for ``scene`` (with a test ``fault``, if any)."""
    cam = scene.camera
    shift = 0.5 if fault == "shift" else 0.0
    tex, origin, size, base = [], [], [], []
    start = 0
    for card in scene.cards:
        rgba = card.rgba.astype(np.float32) if fault == "alpha" else card.premultiplied()
        tex.append(rgba.reshape(-1, 4))
        origin.append((card.offset[0] + shift, card.offset[1]))
        size.append(card.size)
        base.append(start)
        start += card.size[0] * card.size[1]
    if 4 * start >= 2 ** 32:  # the float buffer must be addressable with 32-bit indices
        raise ValueError(f"scene textures hold {start} texels; at most 2^30 are supported")
    return CardTables(np.ascontiguousarray(np.concatenate(tex), np.float32),
                      np.asarray(origin, np.float32), np.asarray(size, np.int32),
                      np.asarray(base, np.int32), float(cam.focal_length_px),
                      0.5 * cam.width, 0.5 * cam.height)


_CLASSES: dict = {}


def compositor_class(mi):
    """The :class:`CardCompositor` class for the current variant, registered as the
    Mitsuba integrator plugin ``mpib_cards`` (classes are per variant in Mitsuba)."""
    variant = mi.variant()
    if variant in _CLASSES:
        return _CLASSES[variant]
    import drjit as dr

    scalar = variant.startswith("scalar")

    class CardCompositor(mi.SamplingIntegrator):
        """Front-to-back compositing of every card a camera ray crosses.

        Per ray: ``C += T * alpha * rgb`` (premultiplied texel), ``T *= 1 - alpha``,
        from the nearest hit on, until ``T == 0`` or the ray leaves the scene. Returns
        the radiance ``C`` and the AOVs ``coverage = 1 - T`` and the squares
        ``C_r^2, C_g^2, C_b^2, (1 - T)^2`` (the film averages them over the pixel's
        samples: their means are second moments, for the per-pixel variance).
        """

        def __init__(self, props=None):
            super().__init__(props if props is not None else mi.Properties())
            self.tables = None

        def set_tables(self, tables: CardTables) -> None:
            if scalar:  # plain numpy; indexed per sample
                self.tables = tables
                return
            self.tables = {
                "texels": mi.Float(tables.texels.ravel()),
                "ox": mi.Float(tables.origin[:, 0]), "oy": mi.Float(tables.origin[:, 1]),
                "wt": mi.Int32(tables.size[:, 0]), "ht": mi.Int32(tables.size[:, 1]),
                "base": mi.Int32(tables.base),
                "f": float(tables.focal_px), "hw": float(tables.half_w),
                "hh": float(tables.half_h),
            }

        def aov_names(self):
            return list(AOV_NAMES)

        def to_string(self):
            return "CardCompositor[]"

        # one lookup: the card's premultiplied RGBA at the hit, from its projection
        def _lookup(self, si, hit):
            t = self.tables
            k = si.prim_index // 2
            ox = dr.gather(mi.Float, t["ox"], k, hit)
            oy = dr.gather(mi.Float, t["oy"], k, hit)
            wt = dr.gather(mi.Int32, t["wt"], k, hit)
            ht = dr.gather(mi.Int32, t["ht"], k, hit)
            base = dr.gather(mi.Int32, t["base"], k, hit)
            # pinhole projection of the hit, in pixels from the frame's top-left corner
            px = t["f"] * si.p.x / si.p.z + t["hw"]
            py = t["f"] * si.p.y / si.p.z + t["hh"]
            col = dr.clip(mi.Int32(dr.floor(px - ox)), 0, wt - 1)
            row = dr.clip(mi.Int32(dr.floor(py - oy)), 0, ht - 1)
            idx = mi.UInt32(base + row * wt + col)
            return dr.gather(mi.Vector4f, t["texels"], idx, hit)

        def _lookup_scalar(self, si):
            t = self.tables
            k = int(si.prim_index) // 2
            px = t.focal_px * float(si.p.x) / float(si.p.z) + t.half_w
            py = t.focal_px * float(si.p.y) / float(si.p.z) + t.half_h
            w, h = int(t.size[k, 0]), int(t.size[k, 1])
            col = min(max(math.floor(px - float(t.origin[k, 0])), 0), w - 1)
            row = min(max(math.floor(py - float(t.origin[k, 1])), 0), h - 1)
            return [float(v) for v in t.texels[int(t.base[k]) + row * w + col]]

        def sample(self, scene, sampler, ray, medium=None, active=True):
            if scalar:
                return self._sample_scalar(scene, ray, active)
            ray = mi.Ray3f(ray)
            T = mi.Float(1.0)
            C = mi.Color3f(0.0)
            active = mi.Bool(active)

            def cond(ray, T, C, active):
                return active

            def body(ray, T, C, active):
                si = scene.ray_intersect(ray, active)
                hit = active & si.is_valid()
                rgba = self._lookup(si, hit)
                C = dr.select(hit, C + T * mi.Color3f(rgba.x, rgba.y, rgba.z), C)
                T = dr.select(hit, T * (1.0 - rgba.w), T)
                active = hit & (T > 0.0)
                ray = si.spawn_ray(ray.d)
                return ray, T, C, active

            ray, T, C, active = dr.while_loop((ray, T, C, active), cond, body,
                                              label="mpib_cards")
            cov = 1.0 - T
            return C, mi.Bool(True), [cov, C.x * C.x, C.y * C.y, C.z * C.z, cov * cov]

        def _sample_scalar(self, scene, ray, active):
            ray = mi.Ray3f(ray)
            T, C = 1.0, [0.0, 0.0, 0.0]
            while T > 0.0:
                si = scene.ray_intersect(ray)
                if not si.is_valid():
                    break
                r, g, b, a = self._lookup_scalar(si)
                C = [C[0] + T * r, C[1] + T * g, C[2] + T * b]
                T = T * (1.0 - a)
                ray = si.spawn_ray(ray.d)
            cov = 1.0 - T
            return (mi.Color3f(*C), True,
                    [cov, C[0] * C[0], C[1] * C[1], C[2] * C[2], cov * cov])

    mi.register_integrator(INTEGRATOR_NAME, lambda props: CardCompositor(props))
    _CLASSES[variant] = CardCompositor
    return CardCompositor


def cards_mesh(mi, scene: Scene, fault: str | None = None):
    """All cards in one ``mi.Mesh``: card ``k`` is triangles ``2k`` and ``2k + 1``."""
    shift = 0.5 if fault == "shift" else 0.0
    verts = [geometry.quad(card, scene.camera, shift)[0] for card in scene.cards]
    faces = [geometry.QUAD_FACES + 4 * k for k in range(len(scene.cards))]
    v = np.concatenate(verts).astype(np.float32)
    f = np.concatenate(faces).astype(np.uint32)
    mesh = mi.Mesh("cards", len(v), len(f))
    params = mi.traverse(mesh)
    params["vertex_positions"] = type(params["vertex_positions"])(v.ravel())
    params["faces"] = type(params["faces"])(f.ravel())
    params.update()
    return mesh


def build(mi, scene: Scene, spp: int, sampler: str = "independent", fault: str | None = None):
    """Mitsuba scene + compositing integrator for ``scene``: returns ``(mi.Scene, integrator)``."""
    _check_fault(fault)
    _check_sampler(sampler, spp)
    scene.validate()
    compositor_class(mi)  # registers the plugin for this variant
    integrator = mi.load_dict({"type": INTEGRATOR_NAME})
    integrator.set_tables(card_tables(scene, fault))
    mscene = mi.load_dict({
        "type": "scene",
        "sensor": sensor_dict(mi, scene, spp, sampler, "rgb", fault),
        "cards": cards_mesh(mi, scene, fault),
    })
    return mscene, integrator


# --------------------------------------------------------------------------------------
# The stock path tracer with mask BSDFs


def card_mesh_arrays(card, camera):
    """``(vertices, uv, faces)`` for the stock renderer: one quad for a fronto-parallel
    card (affine uv is exact there), one quad per texel for a tilted one."""
    if card.plane.is_fronto:
        v, uv = geometry.quad(card, camera)
        return v, uv, geometry.QUAD_FACES
    return geometry.texel_grid(card, camera)


def stock_card_textures(card) -> tuple[np.ndarray, np.ndarray]:
    """``(premultiplied RGB (H, W, 3), alpha (H, W, 1))`` float32 for the stock renderer.

    An area emitter under a ``mask`` BSDF emits fully wherever a ray meets it, whatever
    the mask then samples, so its radiance must be premultiplied (``alpha * rgb``). A
    ``bitmap`` keeps only 3 channels, so alpha lives in its own one-channel texture
    (which is also the coverage render's radiance: premultiplied white).
    """
    pre = card.premultiplied()
    return np.ascontiguousarray(pre[..., :3]), np.ascontiguousarray(pre[..., 3:4])


def stock_integrator_dict(n_cards: int) -> dict:
    """``path`` with enough depth for a ray to pass every card and reach the backstop
    (each mask crossing is one bounce; one more to spare) and Russian roulette off (it
    would add noise, not bias)."""
    depth = n_cards + 2
    return {"type": "path", "max_depth": depth, "rr_depth": depth + 1, "hide_emitters": False}


_MOMENT_CLASSES: dict = {}


def moments_class(mi):
    """A Python integrator that wraps another one (e.g. the stock ``path``) and adds the
    AOVs ``R2, G2, B2``: the film's means of the squared sample values, for per-pixel
    variances. (Mitsuba's own ``moment`` integrator reports them in XYZ, from which RGB
    variances cannot be recovered.)"""
    variant = mi.variant()
    if variant in _MOMENT_CLASSES:
        return _MOMENT_CLASSES[variant]

    class RGBMoments(mi.SamplingIntegrator):
        def __init__(self, nested):
            super().__init__(mi.Properties())
            self.nested = nested

        def aov_names(self):
            return ["R2", "G2", "B2"]

        def to_string(self):
            return f"RGBMoments[{self.nested}]"

        def sample(self, scene, sampler, ray, medium=None, active=True):
            L, valid, _ = self.nested.sample(scene, sampler, ray, medium, active)
            L = mi.Color3f(L)
            return L, valid, [L.x * L.x, L.y * L.y, L.z * L.z]

    _MOMENT_CLASSES[variant] = RGBMoments
    return RGBMoments
