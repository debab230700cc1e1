"""Layered rendering from Blender: one view layer per depth group (real Cycles renders).

A tiny scene (64x48): a checkered diffuse wall at z = 3 filling the view, a small
sphere at z = 1.2 whose shadow falls on the wall, and a thin wire (about one pixel
wide) at z = 1; a sun with no angle (one deterministic shadow ray) and no bounces, so
the only noise is the anti-aliasing and lens sampling. One F12 render gives the
artist's view layer (the single pass) and the ``mpib_group_<k>`` layers of
:mod:`mpib_validate.blender_layers`, with the same seed; Cycles' depth of field of the
same scene (focus on the wall) is the truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("bpy")

from mpib_validate import blender_layers, metrics  # noqa: E402
from mpib_validate.exr import read_exr, rgba_from  # noqa: E402
from mpib_validate.layered import composite_over, group_disparity  # noqa: E402
from mpib_validate.passes import depth_to_disparity  # noqa: E402
from mpib_validate.refocus import Passes, load_layered_passes, refocus  # noqa: E402

W, H = 64, 48
LENS_MM, SENSOR_MM, FSTOP, Z_WALL = 100.0, 36.0, 1.0, 3.0
F_PX = LENS_MM / SENSOR_MM * W
A = LENS_MM * 1e-3 / (2.0 * FSTOP) * F_PX  # A = R f_px (px per 1/m), R = lens / (2 N)
D_F = 1.0 / Z_WALL
SHARP_SPP, TRUTH_SPP, SEED = 64, 512, 3


def _material(bpy, name, colour=None, checker=False):
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
    return m


def build(spp, seed, dof, objects=("wall", "sphere", "wire")):
    """Reset Blender and build the scene (objects in an artist's collection)."""
    import bpy

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
    c.max_bounces = 0
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
               rotation=(math.pi / 2, 0.0, 0.3))}
    mats = {"wall": lambda: _material(bpy, "wall", checker=True),
            "sphere": lambda: _material(bpy, "sphere", (0.8, 0.2, 0.2)),
            "wire": lambda: _material(bpy, "wire", (0.95, 0.95, 0.95))}
    for name in objects:
        add[name]()
        obj = bpy.context.object
        obj.name = name
        obj.data.materials.append(mats[name]())
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
    removed = blender_layers.remove_layers(sc)
    after = [vl.name for vl in sc.view_layers]
    film_after = sc.render.film_transparent
    # the same scene, another seed (the single pass's own noise) and the truth
    other = render(build(SHARP_SPP, SEED + 1, dof=False), tmp / "other.exr")
    truth = render(build(TRUTH_SPP, 1, dof=True), tmp / "truth.exr")
    return {"path": tmp / "layers.exr", "img": layered, "names": names, "report": report,
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
    # the sphere's shadow is in the wall's layer (Indirect Only keeps it): without it the
    # shadowed wall would be brighter than the single pass there
    shadow = np.abs(colour - single).max(axis=-1)
    assert np.percentile(shadow, 99) < 3 * noise


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
    single = refocus(sp, A, D_F, "default")
    layered = refocus(lp, A, D_F, "default")
    assert layered.info["groups"] == 3 and np.isfinite(layered.image).all()
    p_single, mask = _psnr_ob(truth, single.image[..., :3] * single.image[..., 3:], sp.depth)
    p_layered, _ = _psnr_ob(truth, layered.image[..., :3] * layered.image[..., 3:], sp.depth, mask)
    print(f"PSNR_ob single pass {p_single:.2f} dB, layered {p_layered:.2f} dB, "
          f"mask {100 * mask.mean():.0f} %")
    assert p_layered > p_single + 1.0


def test_one_object_falls_back_to_the_single_pass():
    sc = build(4, 0, dof=False, objects=("wall",))
    names, report = blender_layers.prepare(sc)
    assert names == [] and "single pass" in report and "1 visible object" in report
    assert [vl.name for vl in sc.view_layers] == ["ViewLayer"]
    assert sc.render.film_transparent is False
