"""Named quality presets: plane placement, tolerance, fast paths and the middle setting.

Each preset's speed and error are measured by ``mpib bench --suite refocus`` (the
README quotes the latest figures); they are not typed in here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mpib_validate.compositor.composite import CompositeSettings
from mpib_validate.layers.passes import PassesSettings


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    passes: PassesSettings = field(default_factory=PassesSettings)
    composite: CompositeSettings = field(default_factory=CompositeSettings)
    subapertures: int = 1  # 1 = Eq. 1; k > 1 = the middle setting with k x k parts


# The split of content between planes is chosen per preset by measurement on both the
# card suites and the Blender scene suite (mpib bench --suite refocus / blender): the
# additive interval groups conserve the energy of small out-of-focus highlights and gain
# on continuous depth (ground planes), but crack slightly where two groups of one surface
# meet (summing groups within 2 px of blur radius as one slab halves that: +1.1 dB
# PSNR_ob on varying cards, +0.5 dB on the Blender suite). ``best`` adds the 2x2
# sub-apertures, which remove most of Eq. 1's error where an occluder's blur and the
# background's differ (the far objects against the sky of the ground scene: 34.3 dB with
# one aperture, 38.5 dB with 2x2, 40.4 dB for the exact renderer on the same layers);
# with them the additive split measured better than the over split on both worlds
# (cards 38.30 / 35.15 dB PSNR_ob constant / varying against 38.30 / 34.61; Blender
# suite mean 32.8 against 32.0 dB).
PRESETS = {
    "draft": Preset("draft", "1 px plane tolerance, large blurs at reduced resolution",
                    PassesSettings(tolerance_px=1.0, split="additive", slab_px=2.0),
                    CompositeSettings(reduce_above=8.0)),
    "default": Preset("default", "0.5 px plane tolerance, exact kernels (FFT + crop)",
                      PassesSettings(tolerance_px=0.5, split="additive", slab_px=2.0),
                      CompositeSettings()),
    "best": Preset("best", "0.25 px plane tolerance, middle setting with 2x2 sub-apertures",
                   PassesSettings(tolerance_px=0.25, split="additive", slab_px=2.0),
                   CompositeSettings(), subapertures=2),
}


def get_preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}") from None
