"""Named quality presets: plane placement, tolerance, fast paths and the middle setting.

Each preset's speed and error are measured by ``mpib bench --suite refocus`` (``docs/benchmark.md``
quotes the latest figures); they are not typed in here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mpib_validate.runtime.compositor.composite import CompositeSettings
from mpib_validate.runtime.layers.passes import PassesSettings


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    passes: PassesSettings = field(default_factory=PassesSettings)
    composite: CompositeSettings = field(default_factory=CompositeSettings)
    subapertures: int = 1  # 1 = Eq. 1; k > 1 = the middle setting with k x k parts


# The split of content between planes is chosen per preset by measurement on both the
# card suites and the Blender scene suite (``mpib bench --suite refocus`` and
# ``--suite blender``): the additive interval groups conserve the energy of small
# out-of-focus highlights and gain on continuous depth (ground planes), but crack slightly
# where two groups of one surface meet; summing groups within 2 px of blur radius as one
# slab (``slab_px``) halves that. ``best`` adds the 2x2 sub-apertures; with them too the
# additive split measures better than the over split on both worlds.
#
# Every preset composites the slabs in chains (``CompositeSettings.chain_px``, see
# ``composite._Chain``): slabs of one surface (consecutive slabs of continuous content
# share a plane, a gap of 0; an empty stretch of disparity between two surfaces is a
# gap; within CHAIN_PX of blur radius counts as one surface) are combined with the
# disjoint over, which closes the cracks at their seams, and each chain is laid on the
# farther composite renormalised, which fills the holes that the fill leaves behind an
# occluder (Eq. 1's division would give their share to the occluder's colour: the far
# objects against the sky of the Blender suite's ground scene). ``tests/test_chain.py``
# measures both effects against the exact renderer; the presets' PSNR_ob with chains is
# reported by the two bench suites above, their cost by ``--suite refocus``. The gap
# (0.75, 1.5 or 3 px) changes no suite figure by more than 0.01 dB.
CHAIN_PX = 1.5
PRESETS = {
    "draft": Preset("draft", "1 px plane tolerance, large blurs at reduced resolution",
                    PassesSettings(tolerance_px=1.0, split="additive", slab_px=2.0),
                    CompositeSettings(reduce_above=8.0, chain_px=CHAIN_PX)),
    "default": Preset("default", "0.5 px plane tolerance, exact kernels (FFT + crop)",
                      PassesSettings(tolerance_px=0.5, split="additive", slab_px=2.0),
                      CompositeSettings(chain_px=CHAIN_PX)),
    "best": Preset("best", "0.25 px plane tolerance, middle setting with 2x2 sub-apertures",
                   PassesSettings(tolerance_px=0.25, split="additive", slab_px=2.0),
                   CompositeSettings(chain_px=CHAIN_PX), subapertures=2),
}


def get_preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}") from None
