"""One request, one plan: a refocus is described once (mpib_validate.runtime.request), the
disk cache and the session are options of the one pipeline, and the memory estimate
reads the layer builder's plan."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest

from mpib_validate.runtime import budget, presets
from mpib_validate.runtime.layers.cache import DiskCache
from mpib_validate.runtime.layers.passes import PassError, layer_plan, layers_from_passes
from mpib_validate.runtime.presets import PRESETS
from mpib_validate.runtime.refocus import Passes, refocus
from mpib_validate.runtime.request import RefocusRequest
from mpib_validate.runtime.session import RefocusSession

ROOT = Path(__file__).resolve().parents[1]


def _passes(h=40, w=56, seed=2):
    """A receding textured ground (many planes) under sky at infinity, with a box in
    front (depth edges: fill and unmixing)."""
    rng = np.random.default_rng(seed)
    colour = (0.2 + 0.6 * rng.random((h, w, 3))).astype(np.float32)
    rows = np.arange(h, dtype=np.float64)[:, None] * np.ones((1, w))
    depth = 1.0 / (0.05 + 0.6 * rows / h)
    depth[: h // 6] = 1e10
    depth[15:28, 20:34] = 1.0 / 0.9
    colour[15:28, 20:34] = [0.9, 0.3, 0.1]
    return Passes(colour, depth, "ground", "ground")


def test_the_request_resolves_its_preset_once_and_checks_its_lens():
    p = _passes()
    r = RefocusRequest(p, 12.0, 0.5, "best")
    assert r.preset is PRESETS["best"]
    assert RefocusRequest(p, 12.0, 0.5).preset is PRESETS["default"]
    assert RefocusRequest(p, 12.0, 0.5, PRESETS["draft"]).preset is PRESETS["draft"]
    g = RefocusRequest(p, 12.0, 0.5, "draft", refine="guided")
    assert g.preset.passes.refine == "guided" and g.preset.name == "draft"
    assert g.preset_key == "draft+refine=guided" and r.preset_key == "best"
    assert RefocusRequest(p, 12.0, 0.5, refine="off").preset is PRESETS["default"]
    # the refinement is read from the resolved settings, however it was asked for
    assert RefocusRequest(p, 12.0, 0.5, g.preset).preset_key == "draft+refine=guided"
    moved = r.with_lens(focus_disparity=0.25)
    assert (moved.blur_parameter, moved.focus_disparity, moved.preset) == (12.0, 0.25, r.preset)
    with pytest.raises(ValueError, match="unknown preset 'fast'; choose from draft, default"):
        RefocusRequest(p, 12.0, 0.5, "fast")
    for A, d_f in ((0.0, 0.5), (np.inf, 0.5), (12.0, -0.1), (12.0, np.nan)):
        with pytest.raises(PassError):
            RefocusRequest(p, A, d_f)
    with pytest.raises(AttributeError):
        r.blur_parameter = 3.0  # frozen: one description, passed whole


def test_mpib_refocus_looks_the_preset_up_once(tmp_path):
    """The preset name is resolved at the edge: one lookup per `mpib refocus` (the
    pipeline, the estimate and the compositor read the Preset itself)."""
    from clirun import run
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    p = _passes()
    rgba = np.concatenate([p.colour, np.ones(p.depth.shape + (1,), np.float32)], axis=-1)
    ch = channels_from_rgba(rgba)
    ch["Depth.Z"] = p.depth.astype(np.float32)
    write_exr(tmp_path / "in.exr", ch)
    code = presets.get_preset.__code__
    calls = []

    def count(frame, event, arg):
        if event == "call" and frame.f_code is code:
            calls.append(frame.f_locals.get("name"))

    sys.setprofile(count)
    try:
        rc, out, err = run("refocus", tmp_path / "in.exr", "-o", tmp_path / "out.exr", "-q",
                           "--no-preview", "--blur-parameter", 12, "--focus-disparity", 0.5,
                           "--preset", "draft")
    finally:
        sys.setprofile(None)
    assert rc == 0, err
    assert calls == ["draft"]


def test_the_disk_cache_and_the_session_are_options_of_the_one_pipeline(tmp_path):
    """refocus(request, cache=...) with the disk cache or a session gives the result of
    refocus(request) to the last bit, with the MPI built once."""
    p = _passes()
    request = RefocusRequest(p, 14.0, 0.6)
    fresh = refocus(request)
    disk = DiskCache(tmp_path / "cache")
    first, second = refocus(request, cache=disk), refocus(request.with_lens(None, 0.6), cache=disk)
    assert not first.info["mpi_cache"]["reused"] and second.info["mpi_cache"]["reused"]
    session = RefocusSession(p)
    a = refocus(session.request(0.6, 14.0), cache=session)
    b = refocus(session.request(0.3, 14.0), cache=session)
    assert (a.info["mpi"], b.info["mpi"], session.builds) == ("built", "cached", 1)
    for res in (first, second, a):
        assert np.array_equal(res.image, fresh.image)
    assert np.array_equal(b.image, refocus(request.with_lens(None, 0.3)).image)
    assert np.array_equal(b.image, session.render(0.3, 14.0).image)
    # a request of the same picture and settings is the session's; another preset is not
    assert np.array_equal(refocus(request, cache=session).image, fresh.image)
    with pytest.raises(ValueError, match="not this session's"):
        refocus(RefocusRequest(p, 14.0, 0.6, "draft"), cache=session)


def test_the_builder_follows_its_plan():
    """The MPI's planes and layers are those of layer_plan of the disparities it was
    cut from: every layer lies on a planned plane, in the planned slab, and a frame of
    random depth (every plane reaches every tile) has exactly the planned layers."""
    rng = np.random.default_rng(5)
    D = 1.0 / rng.uniform(1, 10, (48, 64))
    colour = rng.random((48, 64, 3)).astype(np.float32)
    settings = PRESETS["default"].passes
    A = 40.0
    mpi, _ = layers_from_passes(colour, D, A, settings)
    plan = layer_plan(D, A, settings)
    assert plan.split == "additive" and plan.plane_count > 10
    planned = {(float(plan.planes[p]), sl) for sl, members in plan.slabs for p, _ in members}
    got = {(l.disparity, l.group) for l in mpi.layers}
    assert got <= planned
    # random depth fills every plane's interval; the fill and edge sheets add no plane
    assert got == planned
    assert len(mpi.layers) == sum(len(m) for _, m in plan.slabs)
    # the estimate counts a straddling plane's two layers, as the builder lays them
    area, count = plan.tile_area(D)
    assert int(count.sum()) == len(mpi.layers)


def test_budget_holds_no_copy_of_the_builder():
    """budget.py imports no private name of the runtime, and the estimate's planes are
    the builder's plan (the same function) on the disparity map."""
    tree = ast.parse((ROOT / "mpib_validate/runtime/budget.py").read_text())
    private = [(node.module, a.name) for node in ast.walk(tree)
               if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mpib_")
               for a in node.names if a.name.startswith("_")]
    assert private == []
    source = (ROOT / "mpib_validate/runtime/budget.py").read_text()
    for builder_logic in ("adaptive_planes", "searchsorted", "slab_of", "plane_spacing"):
        assert builder_logic not in source, builder_logic
    D = 1.0 / np.random.default_rng(1).uniform(1, 10, (64, 64))
    for name, p in PRESETS.items():
        est = budget.refocus_estimate(D, 30.0, 0.4, p)
        assert est.planes == layer_plan(D, 30.0, p.passes).plane_count
