"""Rendering card scenes with Mitsuba 3: images in the form of ``mpib_validate.cards.trace``.

Every image is ``(H, W, 4)`` float32: premultiplied linear radiance (RGB, the pixel's
average over its area and the aperture) and coverage ``1 - T`` (the pixel's average
opacity), like :func:`mpib_validate.cards.trace.trace`.
"""

from __future__ import annotations

import time

import numpy as np

from mpib_validate.cards.scene import Scene

from . import build as _build
from . import variants as _variants


def _meta(chosen, spp, seed, sampler, integrator, seconds, render_seconds, mi) -> dict:
    """Render metadata; ``backend``, ``samples`` and ``sample_count`` mirror the keys of
    :func:`mpib_validate.cards.trace.trace`'s metadata."""
    return {"engine": "mitsuba", "mitsuba_version": mi.__version__, "variant": chosen.name,
            "variant_reason": chosen.reason, "llvm_library": chosen.llvm_library,
            "backend": chosen.name, "integrator": integrator, "sampler": sampler,
            "spp": int(spp), "seed": int(seed), "sample_count": int(spp),
            "samples": f"mitsuba-{sampler}{int(spp)}-seed{int(seed)}",
            "seconds": seconds, "render_seconds": render_seconds}


def render_with_variance(scene: Scene, spp: int, seed: int = 0, variant: str | None = None,
                         *, sampler: str = "independent", fault: str | None = None):
    """Render with the compositing integrator; also return each pixel's sample variance.

    Args:
        scene: the card scene.
        spp: samples per pixel (each one pixel position and one aperture point).
        seed: sampler seed; the same seed gives the same image.
        variant: a Mitsuba variant, or ``None`` to probe for the best one.
        sampler: ``independent`` (default) or ``stratified`` (square ``spp`` only).
        fault: tests only, see :data:`mitsuba_scenes.build.FAULTS`.

    Returns:
        ``(image, sample_variance, meta)``: image ``(H, W, 4)`` float32 as in
        :func:`render`; ``sample_variance`` ``(H, W, 4)`` float64, the unbiased
        per-pixel variance of *one sample* ``E[v^2] - E[v]^2`` times ``n / (n - 1)``,
        from the film's mean of squares (the variance of the pixel value is this over
        ``spp`` for the independent sampler; it overestimates it for the stratified
        one). Float32 cancellation makes it uncertain by about ``1e-6 E[v^2]``.
    """
    mi, chosen = _variants.set_variant(variant)
    t0 = time.perf_counter()
    mscene, integrator = _build.build(mi, scene, spp, sampler, fault)
    t1 = time.perf_counter()
    out = mi.render(mscene, integrator=integrator, spp=int(spp), seed=int(seed))
    arr = np.array(out, dtype=np.float32)  # forces evaluation
    t2 = time.perf_counter()
    n_aov = len(_build.AOV_NAMES)
    if arr.shape[-1] != 3 + n_aov:
        raise RuntimeError(f"unexpected Mitsuba film layout: {arr.shape[-1]} channels, "
                           f"expected R, G, B + {_build.AOV_NAMES}")
    img, var = _split_moments(arr, spp, 4)  # R, G, B, coverage, then their squares
    meta = _meta(chosen, spp, seed, sampler, _build.INTEGRATOR_NAME, t2 - t0, t2 - t1, mi)
    if fault is not None:
        meta["fault"] = fault
    return np.ascontiguousarray(img), var, meta


def render(scene: Scene, spp: int, seed: int = 0, variant: str | None = None, *,
           sampler: str = "independent"):
    """Render ``scene`` with Mitsuba 3 (thin lens, exact front-to-back compositing).

    Returns:
        ``(image, meta)``: ``(H, W, 4)`` float32 premultiplied radiance + coverage, and
        a dict with the variant that ran and why, the sample count, the seed, and the
        time in seconds: ``seconds`` (scene conversion + render) and ``render_seconds``
        (``mi.render`` alone; JIT compilation included, cached across calls).
    """
    img, _var, meta = render_with_variance(scene, spp, seed, variant, sampler=sampler)
    return img, meta


def _split_moments(arr: np.ndarray, spp: int, n_first: int):
    """Film channels ``[v_1..v_n, (extra), m2_1..m2_n]`` -> mean and unbiased sample variance."""
    mean = arr[..., :n_first]
    m2 = arr[..., -n_first:].astype(np.float64)
    var = np.maximum(m2 - mean.astype(np.float64) ** 2, 0.0)
    if spp > 1:
        var *= spp / (spp - 1.0)
    return mean, var


def render_stock_with_variance(scene: Scene, spp: int, seed: int = 0,
                               variant: str | None = None, *, sampler: str = "independent"):
    """Render the files of :func:`mitsuba_scenes.to_xml` (stock ``path`` + ``mask`` BSDF).

    The scene is written to a temporary directory and loaded with ``mi.load_file``, so
    this checks exactly what the ``mitsuba`` command would render. Two renders:
    ``scene.xml`` (radiance) and ``coverage.xml`` (coverage). Each is wrapped in
    :func:`~mitsuba_scenes.build.moments_class` for the per-pixel sample variance.

    Returns:
        ``(image, sample_variance, meta)`` in the form of :func:`render_with_variance`.
    """
    import tempfile

    from .export import to_xml

    mi, chosen = _variants.set_variant(variant)
    wrapper = _build.moments_class(mi)
    planes, variances = [], []
    render_seconds = 0.0
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mpib-mitsuba-") as tmp:
        xml = to_xml(scene, tmp, spp, sampler)
        for path, channels in ((xml, 3), (xml.parent / "coverage.xml", 1)):
            mscene = mi.load_file(str(path), spp=int(spp))
            t0 = time.perf_counter()
            out = mi.render(mscene, integrator=wrapper(mscene.integrator()), spp=int(spp),
                            seed=int(seed))
            arr = np.array(out, dtype=np.float32)
            render_seconds += time.perf_counter() - t0
            if arr.shape[-1] != 6:
                raise RuntimeError(f"unexpected Mitsuba film layout: {arr.shape[-1]} channels")
            mean, var = _split_moments(arr, spp, 3)
            planes.append(mean[..., :channels])
            variances.append(var[..., :channels])
    img = np.ascontiguousarray(np.concatenate(planes, axis=-1))
    var = np.concatenate(variances, axis=-1)
    seconds = time.perf_counter() - t_start
    return img, var, _meta(chosen, spp, seed, sampler, "path+mask (to_xml)", seconds,
                           render_seconds, mi)


def render_stock(scene: Scene, spp: int, seed: int = 0, variant: str | None = None, *,
                 sampler: str = "independent"):
    """Like :func:`render`, with the stock ``path`` integrator and ``mask`` BSDFs (the files
    of :func:`mitsuba_scenes.to_xml`). Noisier: each card's alpha is sampled at random."""
    img, _var, meta = render_stock_with_variance(scene, spp, seed, variant, sampler=sampler)
    return img, meta


def noise_vs_spp(scene: Scene, spp_list, variant: str | None = None, *,
                 sampler: str = "independent", seeds: tuple[int, int] = (0, 1)) -> list[dict]:
    """Time and noise of :func:`render` per sample count, for the benchmark.

    For each ``spp``, two renders with different seeds. The noise of one render is
    estimated from their difference: ``rmse = sqrt(mean((I_1 - I_2)^2) / 2)`` over the
    RGB channels of all pixels (the two errors are independent with equal variance).
    A first render at the smallest count warms the JIT caches and is not timed.

    Returns:
        a list of dicts ``{spp, seconds (mean of the two renders, scene conversion
        included), render_seconds (mi.render alone), rmse (radiance units),
        rmse_coverage, variant}``, in the order of ``spp_list``.
    """
    spp_list = [int(s) for s in spp_list]
    render(scene, min(spp_list), seeds[0], variant, sampler=sampler)  # warm-up
    rows = []
    for spp in spp_list:
        (a, ma), (b, mb) = (render(scene, spp, s, variant, sampler=sampler) for s in seeds)
        d = a.astype(np.float64) - b.astype(np.float64)
        rows.append({"spp": spp, "seconds": 0.5 * (ma["seconds"] + mb["seconds"]),
                     "render_seconds": 0.5 * (ma["render_seconds"] + mb["render_seconds"]),
                     "rmse": float(np.sqrt(np.mean(d[..., :3] ** 2) / 2.0)),
                     "rmse_coverage": float(np.sqrt(np.mean(d[..., 3] ** 2) / 2.0)),
                     "variant": ma["variant"]})
    return rows


def render_result(scene: Scene, spp: int, seed: int = 0, variant: str | None = None, *,
                  sampler: str = "independent", backend: str = "auto"):
    """:func:`render` as a :class:`mpib_validate.cards.trace.TraceResult` (for the CLI's EXR
    writer): the bokeh image from Mitsuba; the all-in-focus image and the per-pixel maps
    from the ray tracer's pinhole pass (exact, deterministic), on ``backend``."""
    from mpib_validate.runtime import samples as _samples
    from mpib_validate.cards import trace as _trace

    bokeh, meta = render(scene, spp, seed, variant, sampler=sampler)
    aif, _ = _trace.trace(scene, _samples.pinhole(4), backend=backend, notices=False)
    maps = _trace.pinhole_maps(scene)
    return _trace.TraceResult(bokeh, aif, maps["disparity"], maps["depth"], maps["layer"],
                              maps["card_alpha"], maps["card_disparity"], meta)
