"""Mitsuba 3 thin-lens references for the card scenes.

Public API (Mitsuba is imported only when a function needs it)::

    render(scene, spp, seed=0, variant=None) -> (image (H, W, 4) float32, meta)
    render_with_variance(scene, spp, seed=0, variant=None) -> (image, sample_variance, meta)
    render_result(scene, spp, seed=0, variant=None) -> mpib_validate.cards.trace.TraceResult
    render_stock(scene, spp, seed=0, variant=None) -> (image, meta)   # to_xml files: path + mask
    render_stock_with_variance(scene, spp, seed=0, variant=None) -> (image, sample_variance, meta)
    to_xml(scene, directory, spp=64) -> path of scene.xml               # for the mitsuba CLI
    noise_vs_spp(scene, spp_list) -> [{spp, seconds, rmse, ...}]
    choose_variant(requested=None) -> Variant(name, reason, ...)
    agreement(test, test_var, n, ref, ref_var, n_ref, bound) -> Agreement  # noise-aware test
    value_bound(scene) -> (H, W, 4) bound on any sample value (for the agreement floor)

Images are premultiplied linear radiance + coverage, the form of
:func:`mpib_validate.cards.trace.trace`.
"""

from .compare import Agreement, agreement, value_bound
from .export import to_xml
from .render import (noise_vs_spp, render, render_result, render_stock,
                     render_stock_with_variance, render_with_variance)
from .variants import MitsubaUnavailable, Variant, choose_variant

__all__ = ["Agreement", "agreement", "choose_variant", "MitsubaUnavailable", "noise_vs_spp",
           "render", "render_result", "render_stock", "render_stock_with_variance",
           "render_with_variance", "to_xml", "value_bound", "Variant"]
