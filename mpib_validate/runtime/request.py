"""One refocus, described once: the input, the lens and focus, the resolved preset, the
far limit, the background render and the disparity refinement.

A :class:`RefocusRequest` is made at the edge (``mpib refocus``, the Blender add-on, a
bench) and handed whole to the pipeline (:func:`mpib_validate.runtime.refocus.refocus`:
build the MPI, render it, describe the result), to the memory estimate
(:func:`mpib_validate.runtime.budget.estimate_request`), the disk cache and the session.
The preset name is looked up here, once; everything downstream reads the
:class:`~mpib_validate.runtime.presets.Preset` itself.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from mpib_validate.runtime.layers.passes import DEFAULT_FAR_LIMIT, PassError
from mpib_validate.runtime.presets import Preset, get_preset


@dataclass(frozen=True, eq=False)
class RefocusRequest:
    """Everything one refocus depends on.

    Attributes:
        passes: the input (:class:`mpib_validate.runtime.refocus.Passes`: rendered passes,
            a layered render, or a photograph with its disparity).
        blur_parameter: ``A`` in pixels per unit disparity: the blur radius of content at
            disparity ``d`` is ``r = A |d - d_f|`` px.
        focus_disparity: ``d_f`` in 1/scene-unit (``1/Z`` of the focus distance; on a
            normalised disparity map, the map's own unit).
        preset: the quality settings, resolved (:class:`~mpib_validate.runtime.presets.Preset`;
            a name is looked up once, on construction). With ``refine`` given, its
            layer settings (``preset.passes``, what the layer builder reads) carry that
            refinement.
        far_limit: depth at or beyond this (scene units) is infinitely far, ``d = 0``.
        background: optional ``(colour, valid[, disparity])`` of what lies behind the
            foreground (:func:`mpib_validate.runtime.refocus.read_background`).
        refine: the disparity refinement asked for (``"off"``, ``"guided"``,
            ``"guided-thin"``), or None for the preset's own (off in every preset).
        aperture: the lens's shape (:class:`mpib_validate.runtime.camera.Aperture`:
            blades, rotation, ratio), or None for a disk. The layers are blurred with its
            kernels, and the MPI is built for its reach (:attr:`build_blur_parameter`).

    Raises :class:`PassError` for an ``A`` or ``d_f`` that is not finite, ``A <= 0`` or
    ``d_f < 0``, and ValueError naming the presets for an unknown preset name.
    """

    passes: object
    blur_parameter: float
    focus_disparity: float
    preset: Preset | str = "default"
    far_limit: float = DEFAULT_FAR_LIMIT
    background: tuple | None = None
    refine: str | None = None
    aperture: object = None

    def __post_init__(self):
        A, d_f = self.blur_parameter, self.focus_disparity
        if not (A > 0) or not math.isfinite(A):
            raise PassError(f"the blur parameter must be finite and > 0 (a zero aperture has "
                            f"no defocus), got {A}")
        if not (d_f >= 0) or not math.isfinite(d_f):
            raise PassError(f"the focus disparity must be finite and >= 0, got {d_f}")
        preset = self.preset if isinstance(self.preset, Preset) else get_preset(self.preset)
        if self.refine is not None and preset.passes.refine != self.refine:
            preset = dataclasses.replace(
                preset, passes=dataclasses.replace(preset.passes, refine=self.refine))
        object.__setattr__(self, "preset", preset)

    @property
    def preset_key(self) -> str:
        """The preset's name, with ``+refine=<mode>`` when its layer settings refine the
        disparity (what the MPI depends on besides the pixels, ``A`` and the far limit;
        the disk cache's key). A preset is known by its name: a custom
        :class:`~mpib_validate.runtime.presets.Preset` needs a name of its own."""
        name, refine = self.preset.name, self.preset.passes.refine
        return name if refine == "off" else f"{name}+refine={refine}"

    @property
    def build_blur_parameter(self) -> float:
        """The ``A`` the MPI is built for (plane spacing, edge threshold, fill reach, the
        cache key): the blur's largest reach, ``A extent`` (``extent = max(1, 1/ratio)``:
        a polygon lies inside the circle of radius ``A |d - d_f|``, a ratio below 1
        widens it along x); ``A`` itself for a disk, a polygon, or a ratio >= 1."""
        ap = self.aperture
        return self.blur_parameter * (1.0 if ap is None else ap.extent)

    def with_lens(self, blur_parameter: float | None = None,
                  focus_disparity: float | None = None) -> "RefocusRequest":
        """The same request at another ``A`` and/or ``d_f`` (validated again)."""
        return dataclasses.replace(
            self,
            blur_parameter=self.blur_parameter if blur_parameter is None else blur_parameter,
            focus_disparity=(self.focus_disparity if focus_disparity is None
                             else focus_disparity))


__all__ = ["RefocusRequest"]
