"""Shared fixtures: small hand-made card scenes and the backends this machine runs."""

from __future__ import annotations

import numpy as np
import pytest

from mpib_validate.runtime.compositor import backend
from mpib_validate.runtime.camera import Camera
from mpib_validate.cards.scene import Card, Plane, Scene


def opaque_card(name, h, w, rgb, plane, offset):
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = rgb
    return Card(name, rgba, plane, offset)


def dot_card(name, size, disparity, radiance=1.0, offset=(0, 0)):
    """A transparent card with one opaque emitting texel at its centre."""
    rgba = np.zeros((size, size, 4), np.float32)
    rgba[size // 2, size // 2] = [radiance, radiance, radiance, 1.0]
    return Card(name, rgba, Plane.fronto(disparity), offset)


def jit_backends():
    """The Dr.Jit backends that run here (LLVM, CUDA), as pytest params."""
    found = []
    for name in ("llvm", "cuda"):
        if backend.resolve(name).name == name:
            found.append(name)
    return found


@pytest.fixture(scope="session")
def llvm_or_skip():
    be = backend.resolve("llvm")
    if be.name != "llvm":
        pytest.skip(f"Dr.Jit LLVM backend unavailable: {be.notice}")
    return "llvm"


@pytest.fixture
def camera64():
    return Camera(64, 64, blur_parameter=20.0, focus_disparity=0.5)


@pytest.fixture
def three_card_scene():
    """Background, a tilted card and a fronto card whose depth ranges overlap."""
    rng = np.random.default_rng(1)
    cam = Camera(48, 40, blur_parameter=12.0, focus_disparity=0.45)
    bg = np.ones((60, 68, 4), np.float32)
    bg[..., :3] = rng.random((60, 68, 3))
    tilt = np.ones((30, 36, 4), np.float32)
    tilt[..., :3] = rng.random((30, 36, 3)) * 4.0  # some HDR
    tilt[::3, :, 3] = 0.4
    fg = np.zeros((20, 20, 4), np.float32)
    fg[4:16, 4:16] = [0.9, 0.2, 0.1, 1.0]
    fg[8:10, :, 3] = 0.5
    fg[8:10, :, :3] = 0.7
    return Scene(cam, [
        Card("bg", bg, Plane.fronto(0.1), (-10, -10)),
        Card("tilt", tilt, Plane.from_gradient(0.6, 0.012, -0.004, at=(0.0, 0.0)), (5, 4)),
        Card("fg", fg, Plane.fronto(0.62), (14, 12)),
    ]).validate()
