"""The seeded scene generator: determinism, families and the named hard cases."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from mpib_validate.cards.generate import FAMILIES, HARD_CASES, GeneratorSettings, generate
from mpib_validate.cards.scene import save_scene

SMALL = GeneratorSettings(width=96, height=72)


def _digest(directory: Path) -> dict:
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("family", FAMILIES)
def test_same_seed_same_scene_byte_for_byte(tmp_path, family):
    save_scene(generate(11, family, settings=SMALL), tmp_path / "a")
    save_scene(generate(11, family, settings=SMALL), tmp_path / "b")
    a, b = _digest(tmp_path / "a"), _digest(tmp_path / "b")
    assert a == b and "scene.json" in a and len(a) >= 3
    save_scene(generate(12, family, settings=SMALL), tmp_path / "c")
    assert _digest(tmp_path / "c") != a


def test_families():
    for seed in range(4):
        const = generate(seed, "constant", settings=SMALL)
        assert all(c.plane.is_fronto for c in const.cards)
        vary = generate(seed, "varying", settings=SMALL)
        assert all(not c.plane.is_fronto for c in vary.cards)


@pytest.mark.parametrize("seed", range(3))
def test_background_covers_every_defocused_ray(seed):
    """The background card must be hit by every ray through the frame: its extent covers
    the frame grown by Plane.max_shift (an upper bound of Eq. 15's displacement)."""
    for family in FAMILIES:
        scene = generate(seed, family, settings=SMALL)
        bg = scene.cards[0]
        cam = scene.camera
        x0, x1, y0, y1 = bg.extent(cam)
        shift = bg.plane.max_shift(cam.blur_parameter, cam.focus_disparity,
                                   -cam.width / 2, cam.width / 2, -cam.height / 2, cam.height / 2)
        assert x0 <= -cam.width / 2 - shift and x1 >= cam.width / 2 + shift
        assert y0 <= -cam.height / 2 - shift and y1 >= cam.height / 2 + shift
        assert (bg.rgba[..., 3] == 1).all()


def _object_radii(scene):
    cam = scene.camera
    return [max(cam.blur_radius(d) for d in c.disparity_range(cam)) for c in scene.cards[1:]]


@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_cases_have_their_difficulty(case):
    scene = generate(5, "constant", case=case, settings=SMALL)
    cam = scene.camera
    meta = scene.metadata
    assert meta["case"] == case
    objects = scene.cards[1:]
    if case in ("thin", "hair", "soft"):
        assert meta["masks"][0] == case
    elif case == "hdr":
        assert max(float(c.rgba[..., :3].max()) for c in scene.cards) > 10.0
    elif case == "near-focus":
        assert min(_object_radii(scene)) <= 1.5
    elif case == "grazing":
        lo, hi = objects[0].disparity_range(cam)
        assert not objects[0].plane.is_fronto and hi - lo > 0.25 and hi / lo > 1.5
    elif case == "large-blur":
        assert scene.max_blur_radius() > 0.1 * cam.width
    elif case == "focus-fg":
        nearest = max(c.disparity_range(cam)[1] for c in objects)
        assert cam.focus_disparity == pytest.approx(nearest)
    elif case == "focus-bg":
        assert cam.focus_disparity == pytest.approx(scene.cards[0].disparity_range(cam)[0])


def test_generator_rejects_bad_arguments():
    with pytest.raises(ValueError, match="family"):
        generate(0, "curved")
    with pytest.raises(ValueError, match="case"):
        generate(0, "constant", case="fog")
    with pytest.raises(ValueError, match="seed"):
        generate(-1)


def test_content_is_linear_hdr_rgba():
    scene = generate(3, "constant")
    for card in scene.cards:
        assert card.rgba.dtype == np.float32 and card.rgba.shape[2] == 4
        assert card.rgba[..., :3].min() >= 0
    # foreground objects have transparent surroundings and opaque or partial interiors
    for card in scene.cards[1:]:
        a = card.rgba[..., 3]
        assert a.min() == 0.0 and a.max() > 0.25
