"""The lens aperture's shape (blades, rotation, ratio): the model, its kernels, the CLI."""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from mpib_validate.cards import trace
from mpib_validate.cards.generate import GeneratorSettings, generate
from mpib_validate.cards.render_io import write_render
from mpib_validate.runtime import samples
from mpib_validate.runtime.camera import DISK, Aperture, ApertureError
from mpib_validate.runtime.compositor import kernels as K
from mpib_validate.runtime.io.exr import read_exr
from mpib_validate.runtime.refocus import Passes, refocus
from mpib_validate.runtime.request import RefocusRequest

HEX = Aperture(6, math.radians(15), 1.5)


def mpib(*args):
    return subprocess.run([sys.executable, "-m", "mpib_validate.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


# -- the model -----------------------------------------------------------------------------

@pytest.mark.parametrize("kw, field", [
    ({"blades": 1}, "blades"), ({"blades": 2}, "blades"), ({"blades": 17}, "blades"),
    ({"blades": -3}, "blades"), ({"blades": 6.0}, "blades"), ({"ratio": 0.0}, "ratio"),
    ({"ratio": -1.5}, "ratio"), ({"ratio": math.nan}, "ratio"), ({"ratio": math.inf}, "ratio"),
    ({"rotation": math.nan}, "rotation"), ({"rotation": math.inf}, "rotation"),
])
def test_bad_apertures_are_refused_naming_the_field(kw, field):
    with pytest.raises(ApertureError, match=f"^{field} must") as e:
        Aperture(**kw)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("aperture", [HEX, Aperture(3, 0.3), Aperture(5, -1.0, 0.7),
                                      Aperture(0, 0.0, 1.5), Aperture(16, 0.1, 2.0)])
def test_the_aperture_map_is_uniform_over_the_shape(aperture):
    """The map of the unit square is area preserving: a 512^2 grid lands inside the
    shape, with its density 1/area on a 16^2 histogram of the bounding box's inner
    cells (counts of ~1000 points: 3 % relative noise, 10 % allowed), and the moments
    of a regular polygon are isotropic before the ratio (the ratio divides x^2 by
    ratio^2)."""
    g = (np.arange(512) + 0.5) / 512
    u, v = np.meshgrid(g, g)
    mu, nu = samples.aperture_map(u.ravel(), v.ravel(), aperture)
    # on the boundary up to rounding
    assert aperture.contains(mu * (1 - 1e-9), nu * (1 - 1e-9)).all()
    e = aperture.extent
    H, xe, ye = np.histogram2d(mu, nu, bins=16, range=[[-e, e], [-e, e]])
    xc, yc = np.meshgrid(0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1]), indexing="ij")
    h = 2 * e / 16
    inner = np.ones_like(H, bool)
    for dx in (-0.5, 0.5):
        for dy in (-0.5, 0.5):
            inner &= aperture.contains(xc + dx * h, yc + dy * h)
    density = H[inner] / mu.size / h ** 2
    assert np.abs(density * aperture.area - 1).max() < 0.10
    mx, my = K.shape_moments(aperture)
    assert mx * aperture.ratio ** 2 == pytest.approx(my, rel=1e-3)


def test_cycles_orientation_at_rotation_zero():
    """Cycles' polygon (kernel/sample/mapping.h regular_polygon_sample): corners at
    rotation + (2k + 1) pi / n counter-clockwise on screen (y up), an edge's midpoint on
    +x at rotation 0. In the image axes (y down) 3 blades: a corner at (-1, 0), the
    edge x = cos(60 deg) = 0.5 on the right; 30 degrees turn the corner at 180 deg to
    210 deg on screen: (-cos 30, +sin 30) in y-down axes."""
    tri = Aperture(3)
    assert tri.contains(np.array([-0.999, 0.499, 0.0]), np.array([0.0, 0.0, 0.0])).all()
    assert not tri.contains(np.array([0.501]), np.array([0.0]))[0]
    turned = Aperture(3, math.radians(30))
    c = (-math.cos(math.radians(30)), math.sin(math.radians(30)))
    assert turned.contains(np.array([c[0] * 0.999]), np.array([c[1] * 0.999]))[0]
    assert not turned.contains(np.array([-0.999]), np.array([0.0]))[0]
    # the ratio divides x: ratio 1.5 is taller than wide
    assert Aperture(0, 0, 1.5).contains(np.array([0.0, 0.66]), np.array([0.99, 0.0])).all()
    assert not Aperture(0, 0, 1.5).contains(np.array([0.67]), np.array([0.0]))[0]


# -- kernels -------------------------------------------------------------------------------

def _brute(rho, aperture, m=2500):
    """The tent splat of an ``m x m`` grid of the shape (np.bincount: millions of points
    in seconds)."""
    g = (np.arange(m) + 0.5) / m
    u, v = np.meshgrid(g, g)
    mu, nu = samples.aperture_map(u.ravel(), v.ravel(), aperture)
    x, y = mu * rho, nu * rho
    R = int(math.ceil(max(np.abs(x).max(), np.abs(y).max()) - 1e-9))
    n = 2 * R + 1
    x0, y0 = np.floor(x + R), np.floor(y + R)
    fx, fy = x + R - x0, y + R - y0
    out = np.zeros(n * n)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                      (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        ix = np.minimum(x0 + dx, n - 1).astype(np.int64)
        iy = np.minimum(y0 + dy, n - 1).astype(np.int64)
        out += np.bincount(iy * n + ix, w, n * n)
    return (out / out.sum()).reshape(n, n)


def _pad(a, R):
    return np.pad(a, R - K.kernel_radius(a))


@pytest.mark.parametrize("aperture", [HEX, Aperture(3, 0.2), Aperture(0, 0, 1.5),
                                      Aperture(5, 1.0, 0.7)])
@pytest.mark.parametrize("rho", [3.3, -12.7, 31.0])
def test_shape_kernel_matches_a_dense_splat(aperture, rho):
    """The plateau-and-rim kernel against the splat of 6 million points of the shape:
    its rim taps are a ~45-points-per-square-pixel estimate, measured within 0.71 % of
    the plateau value (1 % allowed, as the disk's); it sums to one, and a polygon's
    plateau taps are exact."""
    k = K.aperture_kernel(rho, aperture)
    b = _brute(rho, aperture)
    R = max(K.kernel_radius(k), K.kernel_radius(b))
    plateau = 1.0 / (aperture.area * rho * rho)
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.abs(_pad(k, R) - _pad(b, R)).max() < 0.01 * plateau
    assert R <= math.ceil(abs(rho) * aperture.extent) + 1


def test_odd_blades_turn_with_the_sign_of_the_radius():
    """A point in front of the focus sees the aperture turned 180 degrees: the kernel of
    -rho is that of rho flipped (3 blades: not symmetric), 6 blades are symmetric."""
    tri = Aperture(3, 0.4)
    a, b = K.aperture_kernel(9.0, tri), K.aperture_kernel(-9.0, tri)
    assert not np.allclose(a, b, atol=1e-4)
    assert np.allclose(a, b[::-1, ::-1], atol=1e-12)
    assert K.aperture_kernel(-9.0, HEX) is K.aperture_kernel(9.0, HEX)


def test_subaperture_kernels_average_to_the_whole():
    """The k x k sub-aperture kernels of the polygon are equal-area parts: their mean is
    the whole kernel (to the rim estimate's 1 % of the plateau)."""
    rho = -14.0
    whole = K.aperture_kernel(rho, HEX)
    parts = [K.aperture_kernel(rho, HEX, (i, j, 2)) for i in range(2) for j in range(2)]
    R = max(K.kernel_radius(p) for p in parts + [whole])
    mean = sum(_pad(p, R) for p in parts) / 4
    assert np.abs(mean - _pad(whole, R)).max() < 0.01 / (HEX.area * rho * rho)


def test_continuous_axes_give_the_shapes_second_moment():
    """The continuous kernel has, per axis, the shape's own second moment V rho^2 (the
    canonical kernel adds the tent's 1/6): within 0.02 px^2 at 3 px, where the splat
    adds 1/6."""
    for rho in (3.0, 7.5):
        axes = K.continuous_axes(rho, HEX)
        k = K.aperture_kernel(rho, HEX, None, axes)
        R = K.kernel_radius(k)
        q = np.arange(-R, R + 1)
        mx = float((k * q[None, :] ** 2).sum())
        my = float((k * q[:, None] ** 2).sum())
        vx, vy = K.shape_moments(HEX)
        assert mx == pytest.approx(vx * rho * rho, abs=0.02)
        assert my == pytest.approx(vy * rho * rho, abs=0.02)
        assert axes[0] < 1 and axes[1] < 1


# -- a disk stays bit-identical ------------------------------------------------------------

#: sha256 (first 16 hex) of the refocused image of a 96x72 card scene (seed 3, constant,
#: A six times the generator's: blur radius up to 15.6 px, so draft's reduced blur
#: runs) made by the release before the aperture shape (commit 6c66594), per pixel model
#: and preset: a disk must give the same bits.
DISK_DIGESTS = {
    "texel-draft": "dafe2fd743ccf04e", "texel-default": "7c31584e8a5245f6",
    "texel-best": "79aee115818dda0e", "continuous-draft": "76974c51acc3e868",
    "continuous-default": "457aff627acdd1b3", "continuous-best": "41a92e3f36b9bf7c",
}


@pytest.fixture(scope="module")
def disk_scene():
    scene = generate(3, "constant", settings=GeneratorSettings(width=96, height=72))
    aif, _ = trace.trace(scene, samples.pinhole(2), backend="numpy", notices=False)
    depth = trace.pinhole_maps(scene)["depth"].astype(np.float64)
    scene = scene.with_camera(blur_parameter=scene.camera.blur_parameter * 6)
    return scene, aif, depth


@pytest.mark.parametrize("aperture", [DISK, Aperture(0, 0.7, 1.0)])
def test_a_disk_is_bit_identical_to_before(disk_scene, aperture):
    scene, aif, depth = disk_scene
    cam = scene.camera
    kw = {} if aperture == DISK else {"aperture": aperture}  # left out, or a rotated disk
    for key, want in DISK_DIGESTS.items():
        model, preset = key.split("-")
        p = Passes(aif[..., :3].copy(), depth, "c", "d", pixel_model=model)
        img = refocus(RefocusRequest(p, cam.blur_parameter, cam.focus_disparity, preset,
                                     **kw)).image
        got = hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest()[:16]
        assert got == want, key


# -- the CLI -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def render_exr(tmp_path_factory):
    d = tmp_path_factory.mktemp("aperture")
    scene = generate(0, "constant", settings=GeneratorSettings(width=64, height=48))
    res = trace.render(scene, samples.pinhole(2), backend="numpy", notices=False)
    write_render(d / "in.exr", res, scene, preview=False)
    return d


@pytest.mark.parametrize("args, option", [
    (["--blades", "1"], "--blades"), (["--blades", "2"], "--blades"),
    (["--blades", "17"], "--blades"), (["--ratio", "0"], "--ratio"),
    (["--ratio", "-1.5"], "--ratio"), (["--ratio", "nan"], "--ratio"),
    (["--rotation", "nan"], "--rotation"), (["--rotation", "inf"], "--rotation"),
])
def test_refocus_refuses_a_bad_aperture_naming_the_option(render_exr, args, option):
    out = render_exr / "bad.exr"
    r = mpib("refocus", render_exr / "in.exr", "-o", out, "--no-preview", "-q", *args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and option in lines[0] and "Traceback" not in r.stderr
    assert not out.exists()


def test_refocus_records_the_aperture_it_used(render_exr):
    out = render_exr / "hex.exr"
    r = mpib("refocus", render_exr / "in.exr", "-o", out, "--no-preview", "-q",
             "--blades", "6", "--rotation", "15", "--ratio", "1.5")
    assert r.returncode == 0, r.stderr
    assert "6 blades at 15 deg, ratio 1.5" in r.stdout
    cam = json.loads(read_exr(out).header["mpib"])["camera"]
    assert cam["aperture"] == {"blades": 6, "rotation": pytest.approx(math.radians(15)),
                               "ratio": 1.5}
    assert cam["from"]["aperture_blades"] == "--blades"
    # the output's header carries the aperture on to the next refocus
    again = render_exr / "again.exr"
    r = mpib("refocus", out, "--depth", render_exr / "in.exr", "-o", again, "--no-preview",
             "-q")
    assert r.returncode == 0, r.stderr
    assert json.loads(read_exr(again).header["mpib"])["camera"]["aperture"]["blades"] == 6


# -- the compositor with a shaped aperture -------------------------------------------------

from mpib_validate.cards import mpi as CM  # noqa: E402
from mpib_validate.cards.scene import Card, Plane, Scene  # noqa: E402
from mpib_validate.metrics import psnr  # noqa: E402
from mpib_validate.runtime.camera import Camera  # noqa: E402
from mpib_validate.runtime.compositor import composite as C  # noqa: E402
from mpib_validate.runtime.compositor.composite import PLAIN, CompositeSettings  # noqa: E402


@pytest.mark.parametrize("aperture, rho", [(HEX, 7.3), (HEX, -4.6), (Aperture(3, 0.4), 4.2),
                                           (Aperture(3, 0.4), -4.2), (Aperture(0, 0, 0.7), 3.1)])
def test_shape_kernel_is_the_tracers_point_response(aperture, rho):
    """The kernel equals the tracer's image of one texel seen through the same aperture
    (4096 samples of it: standard error of a tap below sqrt(K (1 - K) / 4096) <= 0.008;
    0.01 allowed), both signs: a point in front of the focus sees the shape turned."""
    W = 41
    cam = Camera(W, W, 10.0, 0.5, aperture=aperture)
    rgba = np.zeros((W, W, 4), np.float32)
    rgba[20, 20] = 1.0
    scene = Scene(cam, [Card("dot", rgba, Plane.fronto(0.5 + rho / 10.0), (0, 0))])
    img, _ = trace.trace(scene, samples.stratified(4096, seed=5, aperture=aperture),
                         backend="numpy")
    k = K.aperture_kernel(rho, aperture)
    R = K.kernel_radius(k)
    got = img[20 - R:21 + R, 20 - R:21 + R, 0][::-1, ::-1]
    assert np.abs(got - k).max() < 0.01
    # the other orientation (odd blades) or the disk is further off, in total
    wrong = K.aperture_kernel(-rho, aperture) if not aperture.symmetric else K.disk_kernel(rho)
    Rw = max(R, K.kernel_radius(wrong))
    big = img[20 - Rw:21 + Rw, 20 - Rw:21 + Rw, 0][::-1, ::-1]
    assert 2.0 * np.abs(big - _pad(k, Rw)).sum() < np.abs(big - _pad(wrong, Rw)).sum()


def test_tracer_refuses_samples_of_another_aperture():
    scene = generate(0, "constant", settings=GeneratorSettings(width=32, height=24))
    scene = scene.with_camera(aperture=HEX)
    with pytest.raises(ValueError, match="not of the camera's aperture"):
        trace.trace(scene, samples.stratified(16), backend="numpy", notices=False)
    trace.trace(scene, samples.pinhole(2), backend="numpy", notices=False)  # any aperture


def test_shaped_eq1_gap_shrinks_with_subapertures_and_fast_paths_agree():
    """With 6 blades at 15 deg and ratio 1.5: the exact renderer (the tracer over the
    MPI with the polygon's samples) against Eq. 1 and the 2 x 2 sub-apertures of the
    polygon: the sub-apertures gain (measured 96x96 seed 0: Eq. 1 47.7 dB, k=2 56.6 dB,
    k=3 60.7 dB, the exact renderer's own floor 59.7 dB; 3 dB required); the FFT and
    crop paths agree with the plain path to 120 dB (float32 rounding, as for disks); the
    disk's composite is 38.6 dB from the polygon's (38.0 from the exact: the shape
    matters)."""
    scene = generate(0, "constant", settings=GeneratorSettings(width=96, height=96))
    cam = scene.with_camera(aperture=HEX).camera
    mpi = CM.layers_from_cards(scene)
    ex = np.clip(CM.render_exact(mpi, cam, samples.stratified(1024, seed=0, aperture=HEX)),
                 0, 1)
    st = CompositeSettings(aperture=HEX)
    gaps = [psnr(ex, np.clip(C.render_subapertures(mpi, cam.blur_parameter,
                                                   cam.focus_disparity, k, st), 0, 1))
            for k in (1, 2)]
    assert gaps[0] + 3 < gaps[1], gaps
    plain = C.composite(mpi, cam.blur_parameter, cam.focus_disparity,
                        CompositeSettings(conv="direct", crop=False, aperture=HEX))
    for s in (CompositeSettings(conv="fft", crop=False, aperture=HEX), st):
        out = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, s)
        assert psnr(plain, out, peak=float(plain.max())) > 120.0
    disk = C.composite(mpi, cam.blur_parameter, cam.focus_disparity, PLAIN)
    assert psnr(plain, disk, peak=float(plain.max())) < 60.0  # the shape is not ignored


def test_generate_and_render_carry_the_aperture(tmp_path):
    """``mpib generate --blades/--rotation/--ratio`` writes the camera's aperture into
    scene.json; ``mpib render`` traces it with samples of that aperture; the official
    grid (a disk's) and Mitsuba (a disk only) are refused in one line."""
    scene_dir = tmp_path / "s"
    r = mpib("generate", "--seed", 1, "--size", "48x32", "--out", scene_dir, "--blades", 6,
             "--rotation", 15, "--ratio", 1.5)
    assert r.returncode == 0, r.stderr
    cam = json.loads((scene_dir / "scene.json").read_text())["camera"]
    assert cam["aperture"]["blades"] == 6 and cam["aperture"]["ratio"] == 1.5
    assert cam["aperture"]["rotation"] == pytest.approx(math.radians(15))
    r = mpib("render", scene_dir, "-o", tmp_path / "r.exr", "--spp", 16, "--backend",
             "numpy", "--no-preview", "-q")
    assert r.returncode == 0, r.stderr
    assert "blades6" in r.stdout
    for extra, word in ((["--aperture", "grid"], "--aperture grid"),
                        (["--engine", "mitsuba"], "--engine mitsuba")):
        r = mpib("render", scene_dir, "-o", tmp_path / "x.exr", "--no-preview", "-q", *extra)
        assert r.returncode == 2 and word in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = mpib("generate", "--out", tmp_path / "t", "--blades", 2)
    assert r.returncode == 2 and "--blades" in r.stderr
