"""Writing a card scene as Mitsuba 3 XML, for users outside Python.

``to_xml(scene, directory)`` writes::

    directory/scene.xml              radiance (RGB) with the stock path tracer
    directory/coverage.xml           the same scene with radiance = alpha (white):
                                     its image is the coverage 1 - T
    directory/cards/<name>.ply       the card's mesh (one quad, or one per texel if tilted)
    directory/cards/<name>_rgb.exr   premultiplied RGB radiance (float32)
    directory/cards/<name>_alpha.exr alpha (float32, one channel 'Y')

and renders with the ``mitsuba`` command (``-D spp=256`` sets the sample count)::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        mitsuba -m llvm_ad_rgb -D spp=256 -o bokeh.exr directory/scene.xml

The Python-only compositing integrator cannot be used there, so the files use the
stock ``path`` integrator with a ``mask`` BSDF per card (see
:mod:`mitsuba_scenes.build`); it agrees with the compositing integrator to Monte Carlo
noise but is noisier. No Mitsuba import is needed to write the files.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from mpib_validate.runtime.io.atomic import write_text
from mpib_validate.runtime.io.exr import write_exr
from mpib_validate.cards.scene import Scene

from . import build as _build
from . import geometry


def _f(v: float) -> str:
    return repr(float(v))


def _sensor_xml(scene: Scene, sampler: str) -> str:
    cam = scene.camera
    s = cam.mitsuba_settings()
    z_near, z_far = geometry.depth_range(scene)
    focus = s["focus_distance"]
    if not math.isfinite(focus):
        focus = _build.FAR_FOCUS_FACTOR * z_far
    return f"""    <sensor type="thinlens">
        <transform name="to_world">
            <lookat origin="0, 0, 0" target="0, 0, 1" up="0, -1, 0"/>
        </transform>
        <float name="fov" value="{_f(s['fov'])}"/>
        <string name="fov_axis" value="x"/>
        <float name="aperture_radius" value="{_f(s['aperture_radius'])}"/>
        <float name="focus_distance" value="{_f(focus)}"/>
        <float name="near_clip" value="{_f(min(1e-2, 1e-3 * z_near))}"/>
        <float name="far_clip" value="{_f(100.0 * z_far)}"/>
        <sampler type="{sampler}">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{int(cam.width)}"/>
            <integer name="height" value="{int(cam.height)}"/>
            <string name="pixel_format" value="rgb"/>
            <string name="component_format" value="float32"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


def _bitmap_xml(name: str, filename: str, indent: str) -> str:
    return (f'{indent}<texture type="bitmap" name="{name}">\n'
            f'{indent}    <string name="filename" value={quoteattr(filename)}/>\n'
            f'{indent}    <boolean name="raw" value="true"/>\n'
            f'{indent}    <string name="filter_type" value="nearest"/>\n'
            f'{indent}    <string name="wrap_mode" value="clamp"/>\n'
            f'{indent}</texture>\n')


def _card_xml(card, coverage: bool) -> str:
    ind = " " * 12
    name = f"cards/{card.name}_alpha.exr" if coverage else f"cards/{card.name}_rgb.exr"
    radiance = _bitmap_xml("radiance", name, ind)
    return (f'    <shape type="ply" id={quoteattr("card_" + card.name)}>\n'
            f'        <string name="filename" value={quoteattr(f"cards/{card.name}.ply")}/>\n'
            f'        <emitter type="area">\n{radiance}        </emitter>\n'
            f'        <bsdf type="mask">\n'
            + _bitmap_xml("opacity", f"cards/{card.name}_alpha.exr", " " * 12)
            + '            <bsdf type="diffuse">\n'
              '                <rgb name="reflectance" value="0"/>\n'
              '            </bsdf>\n'
              '        </bsdf>\n'
              '    </shape>\n')


def _backstop_xml(scene: Scene) -> str:
    """A black opaque rectangle behind every card, covering the whole view.

    Mitsuba 3.9.1's ``path`` integrator discards a sample (returns 0) whose path meets
    only null interactions (the pass-through lobe of a ``mask``) and then escapes, even
    if it collected emission on the way (measured: one card of opacity 0.5 and radiance 2
    renders as 1.0, and 2.0 once an opaque card is behind it). Behind the backstop no
    path escapes, so every sample is the front-to-back composite of the emitted
    (premultiplied) radiance; being black, the backstop adds nothing.
    """
    cam = scene.camera
    _z_near, z_far = geometry.depth_range(scene)
    z = 2.0 * z_far
    # half-size: the frustum's half-width at z plus the lens radius, doubled
    half = 2.0 * (0.5 * max(cam.width, cam.height) / float(cam.focal_length_px) * z
                  + cam.thin_lens().aperture_radius)
    return (f'    <shape type="rectangle" id="backstop">\n'
            f'        <transform name="to_world">\n'
            f'            <scale x="{_f(half)}" y="{_f(half)}" z="1"/>\n'
            f'            <translate x="0" y="0" z="{_f(z)}"/>\n'
            f'        </transform>\n'
            f'        <bsdf type="diffuse">\n'
            f'            <rgb name="reflectance" value="0"/>\n'
            f'        </bsdf>\n'
            f'    </shape>\n')


def scene_xml(scene: Scene, spp: int = 64, sampler: str = "independent",
              coverage: bool = False) -> str:
    """The XML text (files referenced relative to the XML's directory)."""
    integ = _build.stock_integrator_dict(len(scene.cards))
    head = (f'<?xml version="1.0" encoding="utf-8"?>\n'
            f'<!-- mpib card scene, {"coverage (1 - T)" if coverage else "radiance"}: '
            f'stock path tracer, mask BSDF per card. -->\n'
            f'<scene version="3.0.0">\n'
            f'    <default name="spp" value="{int(spp)}"/>\n'
            f'    <integrator type="path">\n'
            f'        <integer name="max_depth" value="{integ["max_depth"]}"/>\n'
            f'        <integer name="rr_depth" value="{integ["rr_depth"]}"/>\n'
            f'        <boolean name="hide_emitters" value="false"/>\n'
            f'    </integrator>\n')
    return (head + _sensor_xml(scene, sampler)
            + "".join(_card_xml(c, coverage) for c in scene.cards) + _backstop_xml(scene)
            + "</scene>\n")


def to_xml(scene: Scene, directory: str | os.PathLike, spp: int = 64,
           sampler: str = "independent") -> Path:
    """Write ``scene.xml``, ``coverage.xml`` and the card files under ``directory``.

    Returns the path of ``scene.xml``. See the module docstring for the layout and the
    command line. ``spp`` is the default sample count (``-D spp=N`` overrides it).
    """
    _build._check_sampler(sampler, spp)
    scene.validate()
    directory = Path(directory)
    for card in scene.cards:
        v, uv, faces = _build.card_mesh_arrays(card, scene.camera)
        geometry.write_ply(directory / "cards" / f"{card.name}.ply", v, faces, uv)
        rgb, alpha = _build.stock_card_textures(card)
        write_exr(directory / "cards" / f"{card.name}_rgb.exr",
                  {c: rgb[..., i] for i, c in enumerate("RGB")})
        write_exr(directory / "cards" / f"{card.name}_alpha.exr",
                  {"Y": np.ascontiguousarray(alpha[..., 0])})
    write_text(directory / "coverage.xml", scene_xml(scene, spp, sampler, coverage=True))
    path = directory / "scene.xml"
    write_text(path, scene_xml(scene, spp, sampler))
    return path
