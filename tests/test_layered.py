"""Layered rendering from Blender: one view layer per depth group (real Cycles renders).

A tiny scene (64x48): a checkered diffuse wall at z = 3 filling the view, a small
sphere at z = 1.2 whose shadow falls on the wall, and a thin wire (about one pixel
wide) at z = 1; a sun with no angle (one deterministic shadow ray) and no bounces, so
the only noise is the anti-aliasing and lens sampling. One F12 render gives the
artist's view layer (the single pass) and the ``mpib_group_<k>`` layers of
:mod:`mpib_validate.runtime.blender.layers`, with the same seed; Cycles' depth of field of the
same scene (focus on the wall) is the truth. A glass ball before the wall (with
glossy and transmission bounces) measures what the Indirect Only trick gets wrong.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mpib_validate.runtime.blender import layers as blender_layers

from mpib_validate import cli, metrics
from mpib_validate.runtime.io.exr import read_exr, rgba_from, write_exr
from mpib_validate.runtime.layers.layered import composite_over, group_disparity, layers_from_layered_passes
from mpib_validate.runtime.layers.passes import PassesSettings, depth_to_disparity
from mpib_validate.runtime.refocus import Passes, load_layered_passes, refocus
from mpib_validate.runtime.request import RefocusRequest

W, H = 64, 48
LENS_MM, SENSOR_MM, FSTOP, Z_WALL = 100.0, 36.0, 1.0, 3.0
F_PX = LENS_MM / SENSOR_MM * W
A = LENS_MM * 1e-3 / (2.0 * FSTOP) * F_PX  # A = R f_px (px per 1/m), R = lens / (2 N)
D_F = 1.0 / Z_WALL
SHARP_SPP, TRUTH_SPP, SEED = 64, 512, 3


def _glass(bpy, name):
    """Clear glass (IOR 1.45): what is behind it reaches the camera refracted."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    nt.nodes.clear()
    glass = nt.nodes.new("ShaderNodeBsdfGlass")
    glass.inputs["IOR"].default_value = 1.45
    glass.inputs["Roughness"].default_value = 0.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(glass.outputs[0], out.inputs["Surface"])
    return m


def _material(bpy, name, colour=None, checker=False, transparent=0.0):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = 1.0
    if checker:
        t = nt.nodes.new("ShaderNodeTexChecker")
        t.inputs["Scale"].default_value = 12.0
        t.inputs["Color1"].default_value = (0.9, 0.6, 0.2, 1.0)
        t.inputs["Color2"].default_value = (0.1, 0.2, 0.6, 1.0)
        nt.links.new(t.outputs[0], bsdf.inputs["Base Color"])
    else:
        bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    if transparent:
        # Cycles' own coverage: a fraction ``transparent`` of the rays pass straight on
        bsdf.inputs["Alpha"].default_value = 1.0 - transparent
    return m


def build(spp, seed, dof, objects=("wall", "sphere", "wire"), bounces=0):
    """Reset Blender and build the scene (objects in an artist's collection);
    ``bounces``: Cycles' glossy and transmission bounces (the glass needs them)."""
    bpy = pytest.importorskip("bpy")

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    r = sc.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.film_transparent = False
    r.use_compositing = r.use_sequencer = False
    c = sc.cycles
    c.device, c.samples, c.seed = "CPU", int(spp), int(seed)
    c.use_adaptive_sampling = c.use_denoising = False
    c.max_bounces = c.glossy_bounces = c.transmission_bounces = int(bounces)
    c.diffuse_bounces = 0  # the wall: direct light only, as without the glass
    c.pixel_filter_type = "BOX"
    c.use_auto_tile = False
    sc.view_settings.view_transform = "Standard"
    im = r.image_settings
    im.media_type, im.file_format, im.color_depth = "MULTI_LAYER_IMAGE", "OPEN_EXR_MULTILAYER", "32"
    sc.view_layers[0].use_pass_z = True
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs[0].default_value = (0.05, 0.05, 0.08, 1.0)
    sc.world = world
    cam = bpy.data.cameras.new("Camera")
    cam.sensor_fit, cam.sensor_width, cam.lens = "HORIZONTAL", SENSOR_MM, LENS_MM
    cam.dof.use_dof = bool(dof)
    cam.dof.aperture_fstop, cam.dof.focus_distance, cam.dof.aperture_blades = FSTOP, Z_WALL, 0
    cam_obj = bpy.data.objects.new("Camera", cam)
    cam_obj.rotation_euler = (math.pi, 0.0, 0.0)  # looks down world +Z, world -Y up
    sc.collection.objects.link(cam_obj)
    sc.camera = cam_obj
    coll = bpy.data.collections.new("Artist")
    sc.collection.children.link(coll)
    add = {"wall": lambda: bpy.ops.mesh.primitive_plane_add(size=2.0, location=(0.0, 0.0, Z_WALL)),
           "sphere": lambda: bpy.ops.mesh.primitive_uv_sphere_add(radius=0.05,
                                                                  location=(0.06, 0.04, 1.2)),
           # 3 mm radius at 1 m: 1.07 px wide (a pixel is 1 / F_PX = 5.6 mm there)
           "wire": lambda: bpy.ops.mesh.primitive_cylinder_add(
               radius=0.003, depth=1.0, location=(-0.05, 0.0, 1.0),
               rotation=(math.pi / 2, 0.0, 0.3)),
           # a veil: half transparent, at 1.5 m, over the right half of the view
           "veil": lambda: bpy.ops.mesh.primitive_plane_add(size=0.5, location=(0.25, 0.0, 1.5)),
           # a glass ball, 8 cm across at 1.2 m: 12 px radius
           "glass": lambda: bpy.ops.mesh.primitive_uv_sphere_add(radius=0.08, segments=48,
                                                                 ring_count=24,
                                                                 location=(0.02, 0.0, 1.2)),
           # the same ball, diffuse (the comparison for the glass)
           "ball": lambda: bpy.ops.mesh.primitive_uv_sphere_add(radius=0.08, segments=48,
                                                                ring_count=24,
                                                                location=(0.02, 0.0, 1.2))}
    mats = {"wall": lambda: _material(bpy, "wall", checker=True),
            "sphere": lambda: _material(bpy, "sphere", (0.8, 0.2, 0.2)),
            "wire": lambda: _material(bpy, "wire", (0.95, 0.95, 0.95)),
            "veil": lambda: _material(bpy, "veil", (0.9, 0.9, 0.3), transparent=0.5),
            "glass": lambda: _glass(bpy, "glass"),
            "ball": lambda: _material(bpy, "ball", (0.7, 0.7, 0.7))}
    for name in objects:
        add[name]()
        obj = bpy.context.object
        obj.name = name
        obj.data.materials.append(mats[name]())
        if name in ("glass", "ball"):
            for poly in obj.data.polygons:
                poly.use_smooth = True
        for u in list(obj.users_collection):
            u.objects.unlink(obj)
        coll.objects.link(obj)
    sun = bpy.data.lights.new("Sun", "SUN")
    sun.energy, sun.angle = 3.0, 0.0
    sun_obj = bpy.data.objects.new("Sun", sun)
    sun_obj.rotation_euler = (math.pi + 0.12, 0.1, 0.0)  # shines along +Z, a little tilted
    coll.objects.link(sun_obj)
    return sc


def render(sc, path):
    import bpy

    sc.render.filepath = str(path)
    bpy.ops.render.render(write_still=True, scene=sc.name)
    return read_exr(path)


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("layered")
    sc = build(SHARP_SPP, SEED, dof=False)
    names, report = blender_layers.prepare(sc)
    layered = render(sc, tmp / "layers.exr")
    artist = [vl.name for vl in sc.view_layers if not vl.name.startswith("mpib_group_")]
    # the artist's layer does not see the group collections (its render is unchanged)
    excluded = [c.exclude for c in sc.view_layers["ViewLayer"].layer_collection.children
                if c.name.startswith("mpib_group_")]
    removed = blender_layers.remove_layers(sc)
    after = [vl.name for vl in sc.view_layers]
    film_after = sc.render.film_transparent
    # the same scene, another seed (the single pass's own noise) and the truth
    other = render(build(SHARP_SPP, SEED + 1, dof=False), tmp / "other.exr")
    truth = render(build(TRUTH_SPP, 1, dof=True), tmp / "truth.exr")
    bare = render(build(SHARP_SPP, SEED, dof=False, objects=("wall",)), tmp / "bare.exr")
    return {"bare": bare, "excluded": excluded, "path": tmp / "layers.exr", "img": layered, "names": names, "report": report,
            "artist": artist, "removed": removed, "after": after, "film_after": film_after,
            "other": other, "truth": truth}


def single_pass(img):
    rgba = rgba_from(img, "ViewLayer.Combined.")
    return Passes(rgba[..., :3].astype(np.float32), img.channels["ViewLayer.Depth.Z"].astype(np.float64),
                  "ViewLayer.Combined", "ViewLayer.Depth.Z", None, rgba[..., 3].astype(np.float32))


def test_one_view_layer_per_group_and_removed_again(renders):
    # wall | sphere | wire: the disparity gaps (0.47 and 0.13 /m) are the two largest
    assert renders["names"] == ["mpib_group_0", "mpib_group_1", "mpib_group_2"]
    assert renders["report"].startswith("3 depth groups, far to near: wall; sphere; wire")
    assert renders["artist"] == ["ViewLayer"] and renders["after"] == ["ViewLayer"]
    assert renders["removed"] == 3 and renders["film_after"] is False
    assert renders["excluded"] == [True, True, True]
    img = renders["img"]
    for k, z_lo, z_hi in ((0, 3.0, 3.0), (1, 1.15, 1.25), (2, 0.99, 1.01)):
        a = img.channels[f"mpib_group_{k}.Combined.A"]
        z = img.channels[f"mpib_group_{k}.Depth.Z"]
        centre = z < 1e9  # the pixel centre's sample hit the group
        # each layer sees its own group only (the others are Indirect Only); Cycles'
        # float32 depth is exact to 1e-5 relative
        assert centre.any() and np.all((z[centre] > z_lo * (1 - 1e-5)) & (z[centre] < z_hi * (1 + 1e-5)))
        assert (k == 0) == bool(np.all(a == 1.0))  # the wall fills the view


def test_groups_composited_over_give_back_the_single_pass(renders):
    img, other = renders["img"], renders["other"]
    single = rgba_from(img, "ViewLayer.Combined.")[..., :3].astype(np.float64)
    lp = load_layered_passes(renders["path"])
    colour, alpha = composite_over(lp.groups)
    np.testing.assert_allclose(alpha, 1.0, atol=1e-6)  # coverage adds up to the opaque wall
    rms = float(np.sqrt(((colour - single) ** 2).mean()))
    # noise of one render: the same scene with another seed differs by sqrt(2) sigma
    # per value; the same seed's layers must be closer than that (they share samples)
    noise = float(np.sqrt(((rgba_from(other, "ViewLayer.Combined.")[..., :3] - single) ** 2).mean()))
    print(f"over-composite vs single pass: rms {rms:.2e}, max {np.abs(colour - single).max():.3f}; "
          f"another seed: rms {noise:.2e}")
    assert rms < 0.5 * noise


def test_shadows_of_other_groups_stay_in_a_layer(renders):
    # the sphere's shadow on the wall: the wall's layer against the wall rendered alone
    img = renders["img"]
    wall = rgba_from(img, "mpib_group_0.Combined.")[..., :3]
    bare = rgba_from(renders["bare"], "ViewLayer.Combined.")[..., :3]
    single = rgba_from(img, "ViewLayer.Combined.")[..., :3]
    shadow = (bare - wall).mean(axis=-1) > 0.05  # measured: 77 px, up to 0.54 darker
    assert shadow.sum() >= 20
    uncovered = shadow & (img.channels["mpib_group_1.Combined.A"] == 0) & (
        img.channels["mpib_group_2.Combined.A"] == 0)
    assert uncovered.sum() >= 20
    # where no nearer group covers it, the wall's layer is the single pass: same seed,
    # same samples (measured: equal to the bit); 1e-5 is float32 rounding
    np.testing.assert_allclose(wall[uncovered], single[uncovered], rtol=1e-5, atol=1e-6)


def _psnr_ob(truth, image, depth, mask=None):
    D = depth_to_disparity(depth)
    if mask is None:
        mask = metrics.occlusion_mask(metrics.boundaries_from_disparity(D, 1.0 / A), D, A, D_F)
    return metrics.psnr(np.clip(truth, 0, 1), np.clip(image, 0, 1), mask), mask


def test_layered_path_closer_to_cycles_depth_of_field_at_occlusion_boundaries(renders):
    img, truth = renders["img"], rgba_from(renders["truth"], "ViewLayer.Combined.")[..., :3]
    sp = single_pass(img)
    lp = load_layered_passes(renders["path"])
    assert len(lp.groups) == 3
    single = refocus(RefocusRequest(sp, A, D_F, "default"))
    layered = refocus(RefocusRequest(lp, A, D_F, "default"))
    assert layered.info["groups"] == 3 and np.isfinite(layered.image).all()
    p_single, mask = _psnr_ob(truth, single.image[..., :3] * single.image[..., 3:], sp.depth)
    p_layered, _ = _psnr_ob(truth, layered.image[..., :3] * layered.image[..., 3:], sp.depth, mask)
    print(f"PSNR_ob single pass {p_single:.2f} dB, layered {p_layered:.2f} dB, "
          f"mask {100 * mask.mean():.0f} %")
    # measured: single pass 27.7 dB, layered 46.3 dB (truth's own noise floor there,
    # from a second seed: 53.3 dB); 10 dB is well inside that margin, and above what
    # any change of fill or unmixing in the single pass has gained on such scenes
    assert p_layered > p_single + 10.0
    # no sharp fragments of the wire: on its pixels the sharp input differs from the
    # truth by the wire's full contrast; the single pass keeps most of it (measured:
    # 0.55 of 0.55), the layered path less than a tenth (measured 0.014, the truth's
    # noise between two seeds there is 0.019)
    wire = lp.groups[2][1] > 0.3
    contrast = np.abs(sp.colour - truth)[wire].max()
    assert np.abs(single.image[..., :3] - truth)[wire].max() > 0.5 * contrast
    assert np.abs(layered.image[..., :3] - truth)[wire].max() < 0.1 * contrast


@pytest.fixture(scope="module")
def veil(tmp_path_factory):
    """Wall, a half-transparent veil at 1.5 m over the right half, and the wire."""
    tmp = tmp_path_factory.mktemp("veil")
    objs = ("wall", "veil", "wire")
    sc = build(SHARP_SPP, SEED, dof=False, objects=objs)
    names, report = blender_layers.prepare(sc)
    img = render(sc, tmp / "layers.exr")
    truth = render(build(TRUTH_SPP, 1, dof=True, objects=objs), tmp / "truth.exr")
    return {"path": tmp / "layers.exr", "img": img, "report": report, "truth": truth}


def test_a_half_transparent_veil_blurs_as_in_cycles(veil):
    assert veil["report"].startswith("3 depth groups, far to near: wall; veil; wire")
    truth = rgba_from(veil["truth"], "ViewLayer.Combined.")[..., :3]
    sp, lp = single_pass(veil["img"]), load_layered_passes(veil["path"])
    # the veil's layer holds Cycles' own coverage: 1/2 up to the noise of 64 samples
    # (the binomial sd of a fraction at 64 spp is 0.0625)
    veil_alpha = lp.groups[1][1]
    assert np.all(np.abs(veil_alpha[veil_alpha > 0.2] - 0.5) < 3 * 0.0625)
    single = refocus(RefocusRequest(sp, A, D_F, "default")).image
    layered = refocus(RefocusRequest(lp, A, D_F, "default")).image
    p_single, mask = _psnr_ob(truth, single[..., :3], sp.depth)
    p_layered, _ = _psnr_ob(truth, layered[..., :3], sp.depth, mask)
    print(f"veil: PSNR_ob single pass {p_single:.2f} dB, layered {p_layered:.2f} dB")
    # measured: single pass 23.8 dB, layered 46.2 dB (the truth's noise floor, from a
    # second seed, 50.9 dB)
    assert p_layered > p_single + 10.0


def test_mpib_refocus_reads_the_group_layers(renders, tmp_path, capsys):
    out = tmp_path / "refocused.exr"
    rc = cli.main(["refocus", str(renders["path"]), "-o", str(out), "--blur-parameter", str(A),
                   "--focus-disparity", str(D_F), "--no-preview"])
    assert rc == 0 and "3 depth groups" in capsys.readouterr().out
    want = refocus(RefocusRequest(load_layered_passes(renders["path"]), A, D_F, "default")).image
    got = rgba_from(read_exr(out), "")
    np.testing.assert_allclose(got[..., :3], want[..., :3] * want[..., 3:], rtol=1e-6, atol=1e-7)
    # --layered on a file with one view layer: one line, exit 2, nothing written
    one = tmp_path / "one.exr"
    write_exr(one, {"ViewLayer.Combined.R": np.ones((4, 4), np.float32),
                    "ViewLayer.Combined.G": np.ones((4, 4), np.float32),
                    "ViewLayer.Combined.B": np.ones((4, 4), np.float32),
                    "ViewLayer.Combined.A": np.ones((4, 4), np.float32),
                    "ViewLayer.Depth.Z": np.ones((4, 4), np.float32)})
    bad = tmp_path / "bad.exr"
    rc = cli.main(["refocus", str(one), "-o", str(bad), "--layered", "--blur-parameter", "2",
                   "--focus-disparity", "0.5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "one.exr" in err[0] and "--layered" in err[0]
    assert not bad.exists()
    rc = cli.main(["refocus", str(renders["path"]), "-o", str(bad), "--background",
                   str(renders["path"]), "--blur-parameter", "2", "--focus-disparity", "0.5"])
    assert rc == 2 and "drop --background" in capsys.readouterr().err and not bad.exists()


def test_groups_from_the_collections_an_artist_picks():
    import bpy

    sc = build(4, 0, dof=False)
    front, back = bpy.data.collections.new("Front"), bpy.data.collections.new("Back")
    sc.collection.children.link(front)
    sc.collection.children.link(back)
    for name, coll in (("wire", front), ("sphere", front), ("wall", back), ("wire", back)):
        coll.objects.link(bpy.data.objects[name])
    # far to near by median disparity; the wire, in both, goes to the first picked
    groups = blender_layers.groups_from_collections(sc, [front, back])
    assert [sorted(o.name for o in g) for g in groups] == [["wall"], ["sphere", "wire"]]
    assert blender_layers.setup_layers(sc, groups) == ["mpib_group_0", "mpib_group_1"]
    assert blender_layers.remove_layers(sc) == 2
    assert [vl.name for vl in sc.view_layers] == ["ViewLayer"]
    assert "Front" in bpy.data.collections and "mpib_group_0" not in bpy.data.collections


def test_one_object_falls_back_to_the_single_pass():
    import bpy

    sc = build(4, 0, dof=False, objects=("wall",))
    # an object in a collection the artist excluded from the view layer does not count
    hidden = bpy.data.collections.new("Hidden")
    sc.collection.children.link(hidden)
    hidden.objects.link(bpy.data.objects.new("ghost", bpy.data.meshes["Plane"]))
    sc.view_layers["ViewLayer"].layer_collection.children["Hidden"].exclude = True
    names, report = blender_layers.prepare(sc)
    assert names == [] and "single pass" in report and "1 visible object" in report
    assert [vl.name for vl in sc.view_layers] == ["ViewLayer"]
    assert sc.render.film_transparent is False


# --------------------------------------------------------------------------------------
# Pure numpy: the grouping and the MPI of group layers


def test_split_groups_at_the_largest_gaps_and_a_ground_plane_goes_farthest():
    # disparity intervals (1/m): a ground plane from 10 m to 1 m, a wall, two props
    ivs = [(0.1, 1.0), (0.1, 0.1), (0.48, 0.52), (0.9, 0.95), (0.5, 0.55)]
    assert blender_layers.split_groups(ivs, max_groups=3) == [[0, 1], [2, 4], [3]]
    # the largest gap (0.38 /m, wall to props) splits first
    assert blender_layers.split_groups(ivs, max_groups=2) == [[0, 1], [2, 4, 3]]
    # one object, or all overlapping in depth: one group
    assert blender_layers.split_groups([(0.2, 0.3)]) == [[0]]
    assert blender_layers.split_groups([(0.2, 0.3), (0.25, 0.4)]) == [[0, 1]]


def test_refine_intervals_shrinks_a_box_to_what_the_render_shows():
    # a 4x6 render: a wall at d = 0.2 everywhere, a ball whose visible front is at
    # d = 0.9 to 0.95 in columns 1-2 (its box reaches back to 0.58), a board seen in
    # columns 4-5 at 0.5 whose box spans 0.3 to 0.6, a prop hidden behind the board
    D = np.full((4, 6), 0.2)
    D[:, 1], D[:, 2] = 0.9, 0.95
    D[:, 4:] = 0.5
    boxes = [(0.2, 0.2), (0.58, 0.95), (0.3, 0.6), (0.4, 0.45)]
    rects = [(0, 0, 6, 4), (0, 0, 3, 4), (3, 0, 6, 4), (3, 0, 6, 4)]
    # the boxes overlap (ball and board): one group in front of the wall
    assert blender_layers.split_groups(boxes, max_groups=3) == [[0], [2, 3, 1]]
    got = blender_layers.refine_intervals(boxes, rects, D)
    # the prop: no pixel with its box's disparities shows (hidden): its box stays
    assert got == [(0.2, 0.2), (0.9, 0.95), (0.5, 0.5), (0.4, 0.45)]
    # with the render's values the ball's front stands apart from the board: a jump
    assert blender_layers.split_groups(got, max_groups=3) == [[0], [3, 2], [1]]
    # rectangles are clipped to the image; an empty one keeps the box
    assert blender_layers.refine_intervals([(0.1, 0.3)], [(7, 5, 9, 9)], D) == [(0.1, 0.3)]


def _pinhole(mpi):
    """The MPI composited with no blur: each additive group's layers summed, groups and
    plain layers laid "over", far to near (the compositor at zero aperture)."""
    acc = np.zeros((mpi.height, mpi.width, mpi.channels))
    keys = []
    for i, l in enumerate(mpi.layers):
        keys.append(("g", l.group) if l.group is not None else ("l", i))
    for key in dict.fromkeys(keys):
        part = np.zeros_like(acc)
        for l, k in zip(mpi.layers, keys):
            if k == key:
                y0, y1, x0, x1 = l.box
                part[y0:y1, x0:x1] += l.rgba
        acc = part + (1.0 - part[..., 3:4]) * acc
    return acc


@pytest.mark.parametrize("split", ["linear", "additive"])
@pytest.mark.parametrize("far_opaque", [True, False])
def test_layered_mpi_composites_back_to_the_group_layers(split, far_opaque):
    rng = np.random.default_rng(0)
    Hs, Ws = 24, 32
    # far: a textured wall at d = 0.3 (a hole to the world where not opaque); middle: a
    # disk at d = 0.8 with anti-aliased edges; near: a one-pixel wire at d = 1.5, half
    # covering its pixels
    a0 = np.ones((Hs, Ws))
    if not far_opaque:
        a0[:, :6] = 0.0
        a0[:, 6] = 0.5
    P0 = rng.uniform(0.1, 0.9, (Hs, Ws, 3)) * a0[..., None]
    yy, xx = np.mgrid[:Hs, :Ws]
    a1 = np.clip(6.5 - np.hypot(yy - 12, xx - 16), 0.0, 1.0)
    P1 = np.array([0.8, 0.2, 0.2]) * a1[..., None]
    a2 = np.zeros((Hs, Ws))
    a2[:, 20] = 0.5
    P2 = np.full((Hs, Ws, 3), 0.9) * a2[..., None]
    groups = [(P, a, np.where(a > 0, d, 0.0)) for P, a, d in
              ((P0, a0, 0.3), (P1, a1, 0.8), (P2, a2, 1.5))]
    mpi, info = layers_from_layered_passes(groups, 6.0, PassesSettings(split=split))
    assert info.extra["groups"] == 3 and mpi.channels == (4 if far_opaque else 5)
    colour, alpha = composite_over(groups)
    got = _pinhole(mpi)
    # the film channel (1 on content, 0 on the world) composites to the coverage; the
    # MPI itself is opaque (the world is its disparity-0 content)
    film = got[..., 4] if not far_opaque else got[..., 3]
    np.testing.assert_allclose(got[..., 3], 1.0, atol=1e-6)
    np.testing.assert_allclose(film, alpha, atol=1e-5)
    # float32 layers: rounding of a few "over" steps
    np.testing.assert_allclose(got[..., :3], colour, atol=1e-5)


def test_group_disparity_takes_the_nearest_finite_depth_where_the_centre_missed():
    z = np.array([[2.0, 1e10, 1e10, 1e10]])
    a = np.array([[1.0, 0.4, 0.0, 0.0]])
    np.testing.assert_allclose(group_disparity(z, a), [[0.5, 0.5, 0.0, 0.0]])


# --------------------------------------------------------------------------------------
# What the Indirect Only trick gets wrong: light through a nearer object's refraction


@pytest.fixture(scope="module")
def glass(tmp_path_factory):
    """Wall and a glass ball (8 glossy and transmission bounces), and the same ball
    diffuse: layered renders (same seed as their single pass), another seed of the
    single pass, and Cycles' depth of field of each (two seeds: its noise)."""
    tmp = tmp_path_factory.mktemp("glass")
    out = {}
    for kind in ("glass", "ball"):
        objs = ("wall", kind)
        sc = build(SHARP_SPP, SEED, dof=False, objects=objs, bounces=8)
        names, report = blender_layers.prepare(sc)
        out[kind] = {"names": names, "path": tmp / f"{kind}.exr",
                     "img": render(sc, tmp / f"{kind}.exr"),
                     "other": render(build(SHARP_SPP, SEED + 1, dof=False, objects=objs, bounces=8),
                                     tmp / f"{kind}-other.exr"),
                     "truth": render(build(TRUTH_SPP, 1, dof=True, objects=objs, bounces=8),
                                     tmp / f"{kind}-truth.exr"),
                     "truth2": render(build(TRUTH_SPP, 2, dof=True, objects=objs, bounces=8),
                                      tmp / f"{kind}-truth2.exr")}
    return out


def test_glass_group_layers_composited_over_give_back_the_single_pass(glass):
    """Where the glass ball covers a pixel its layer is the single pass (the refracted
    wall is traced in the ball's layer: the wall is Indirect Only there, so refraction
    rays see it); elsewhere the wall's layer is. Only partly covered pixels differ:
    "over" weights the wall's radiance over the whole pixel, not over its uncovered
    part. Measured at 64x48, 64 spp, same seed: rms 1.5e-3 (max 0.058, at the ball's
    silhouette), exactly 0 inside the ball; another seed's single pass differs by rms
    7.5e-3 (its noise)."""
    g = glass["glass"]
    assert g["names"] == ["mpib_group_0", "mpib_group_1"]
    single = rgba_from(g["img"], "ViewLayer.Combined.")[..., :3].astype(np.float64)
    lp = load_layered_passes(g["path"])
    colour, _ = composite_over(lp.groups)
    rms = float(np.sqrt(((colour - single) ** 2).mean()))
    other = rgba_from(g["other"], "ViewLayer.Combined.")[..., :3]
    noise = float(np.sqrt(((other - single) ** 2).mean()))
    print(f"glass: over-composite vs single pass rms {rms:.2e} (max "
          f"{np.abs(colour - single).max():.3f}); another seed rms {noise:.2e}")
    assert rms < 0.5 * noise
    inside = lp.groups[1][1] >= 1.0
    assert inside.sum() > 200  # the ball is 12 px in radius
    # the same samples: equal to float32 rounding
    np.testing.assert_allclose(colour[inside], single[inside], rtol=1e-5, atol=1e-6)


def _error_db(image, t1, t2, mask):
    """Error of ``image`` against the converged truth, in dB (PSNR, peak 1), inside
    ``mask``: the MSE against the mean of two truth seeds less that mean's own noise,
    ``mean((t1 - t2)^2) / 4`` (an unbiased estimate; values clipped to [0, 1])."""
    t1, t2, im = (np.clip(x, 0, 1) for x in (t1, t2, image))
    mse = (((im - (t1 + t2) / 2) ** 2)[mask]).mean()
    noise = (((t1 - t2) ** 2)[mask]).mean() / 4
    return -10 * math.log10(mse - noise), -10 * math.log10(noise)


def test_what_indirect_only_gets_wrong_refraction_is_blurred_at_the_glass(glass):
    """The ball's layer holds the wall as refracted through it, and the refocus blurs
    that at the ball's depth (1.12 to 1.2 m: about 5 px at this focus) where Cycles
    blurs the light that the ball lens bends (its image of the wall lies about 0.14 m
    behind the ball's centre: about 3.7 px). Inside the ball, against Cycles' depth of
    field (noise-corrected, :func:`_error_db`), measured at 64x48: layered 42.2 dB
    through glass against 44.0 dB for the same ball diffuse, so refraction costs 1.8
    dB there (error RMS 0.0078 against 0.0063; the two-seed truth's own noise is at
    43.5 dB inside the glass, 56.2 dB inside the diffuse ball, so this is known to a
    few tenths of a dB); the single pass is at 27.4 and 27.6 dB (its fill). The error
    is real but small next to what the layers remove."""
    res = {}
    for kind in ("glass", "ball"):
        g = glass[kind]
        lp = load_layered_passes(g["path"])
        t1 = rgba_from(g["truth"], "ViewLayer.Combined.")[..., :3]
        t2 = rgba_from(g["truth2"], "ViewLayer.Combined.")[..., :3]
        layered = refocus(RefocusRequest(lp, A, D_F, "default")).image[..., :3]
        single = refocus(RefocusRequest(single_pass(g["img"]), A, D_F, "default")).image[..., :3]
        inside = lp.groups[1][1] >= 1.0
        res[kind] = {"layered": _error_db(layered, t1, t2, inside),
                     "single": _error_db(single, t1, t2, inside)}
    print("inside the ball, error against Cycles' depth of field (dB, noise of the truth):", res)
    glass_, ball = res["glass"], res["ball"]
    assert glass_["layered"][0] < ball["layered"][0] - 1.0  # the refraction error is there
    assert glass_["layered"][0] > glass_["single"][0] + 10.0  # and far below the fill's


def _write_groups(path, groups, env=None, env_layer="mpib_group_0"):
    """A multilayer EXR of group layers ``(name, premultiplied colour, alpha, Z)``,
    and the world's Environment pass on ``env_layer``."""
    ch = {}
    for name, P, a, z in groups:
        for i, c in enumerate("RGB"):
            ch[f"{name}.Combined.{c}"] = P[..., i].astype(np.float32)
        ch[f"{name}.Combined.A"] = a.astype(np.float32)
        ch[f"{name}.Depth.Z"] = z.astype(np.float32)
    if env is not None:
        for i, c in enumerate("RGB"):
            ch[f"{env_layer}.Environment.{c}"] = env[..., i].astype(np.float32)
    write_exr(path, ch)


def test_the_world_behind_the_farthest_group_comes_from_its_environment_pass(tmp_path):
    """blender.layers gives the farthest layer an Environment pass where the artist's
    film is opaque: load_layered_passes adds it (the world where that layer's samples
    missed), the group is then opaque, and the world keeps disparity 0."""
    Hs, Ws = 8, 12
    sky = np.array([0.45, 0.6, 0.85])
    a0 = np.zeros((Hs, Ws), np.float32)
    a0[4:] = 1.0  # a ground in the lower half, the world above
    a0[3] = 0.25  # its horizon row partly covered
    P0 = (0.3 * a0)[..., None] * np.ones(3)
    env = (1.0 - a0)[..., None] * sky  # the samples that miss the ground see the sky
    z0 = np.where(a0 >= 0.5, 4.0, 1e10)
    a1 = np.zeros((Hs, Ws), np.float32)
    a1[5:7, 5:7] = 1.0  # a box in front
    P1 = a1[..., None] * np.array([0.9, 0.1, 0.1])
    z1 = np.where(a1 > 0, 1.5, 1e10)
    path = tmp_path / "world.exr"
    _write_groups(path, [("mpib_group_0", P0, a0, z0), ("mpib_group_1", P1, a1, z1)], env)
    lp = load_layered_passes(path)
    far = lp.groups[0]
    np.testing.assert_allclose(far[1], 1.0)  # opaque once the world is behind it
    np.testing.assert_allclose(far[0], P0 + env, atol=1e-6)
    np.testing.assert_allclose(far[3], a0)  # its own coverage rides along
    np.testing.assert_allclose(lp.alpha, 1.0)
    np.testing.assert_allclose(lp.colour[0, 0], sky, atol=1e-6)
    # the world is at disparity 0, the partly covered horizon takes the ground's
    D = group_disparity(far[2], far[3])
    assert np.all(D[:3] == 0.0) and np.allclose(D[3:], 0.25)
    res = refocus(RefocusRequest(lp, 4.0, 0.25, "default"))  # focus on the ground
    assert np.isfinite(res.image).all()
    np.testing.assert_allclose(res.image[..., 3], 1.0, atol=1e-6)  # opaque in, opaque out
    np.testing.assert_allclose(res.image[0, 0, :3], sky, atol=1e-4)  # the sky far from all


def test_a_ground_plane_group_stays_farthest_with_the_world(tmp_path):
    """blender.layers puts an object spanning the depth range (a ground plane) into
    mpib_group_0 with the world's Environment pass. Its median depth can be nearer than
    a farther group's (a ball standing far away on it): the groups must keep the
    renderer's order, or the world is added to no group and the sky turns black (a
    suite scene split into 4 groups scored 10 dB PSNR_ob so). Other view layers are
    ordered by median depth with the world's layer first."""
    Hs, Ws = 10, 12
    sky = np.array([0.45, 0.6, 0.85])
    a0 = np.zeros((Hs, Ws))
    a0[4:] = 1.0  # the ground in the lower part; the world above
    z0 = np.where(a0 > 0, np.linspace(6.0, 1.0, Hs)[:, None] * np.ones((1, Ws)), 1e10)
    P0 = 0.3 * a0[..., None] * np.ones(3)
    env = (1.0 - a0)[..., None] * sky
    a1 = np.zeros((Hs, Ws))
    a1[1:5, 2:5] = 1.0  # a ball far away (8 m), behind the ground's median (about 3 m)
    P1 = a1[..., None] * np.array([0.9, 0.6, 0.1])
    z1 = np.where(a1 > 0, 8.0, 1e10)
    # numbered out of median-depth order on purpose: group 0 is the ground
    _write_groups(tmp_path / "ground.exr", [("mpib_group_0", P0, a0, z0),
                                            ("mpib_group_1", P1, a1, z1)], env)
    lp = load_layered_passes(tmp_path / "ground.exr")
    assert len(lp.groups) == 2 and len(lp.groups[0]) == 4  # the world rides with group 0
    np.testing.assert_allclose(lp.colour[0, 0], sky, atol=1e-6)
    np.testing.assert_allclose(lp.alpha, 1.0)
    # any other names: by median depth, but the layer with the world goes first
    _write_groups(tmp_path / "named.exr", [("ground", P0, a0, z0), ("ball", P1, a1, z1)],
                  env, env_layer="ground")
    lp = load_layered_passes(tmp_path / "named.exr", layered=True)
    assert "ground, ball" in lp.colour_source
    np.testing.assert_allclose(lp.colour[0, 0], sky, atol=1e-6)
