"""mpib: layered bokeh (MPI) refocusing, checked against physically based renders.

The command line is a thin layer over the package's functions.

Subcommands:
  generate   make a seeded random card scene (JSON + EXR textures)
  render     render a scene (the Eq. 15 ray tracer) to EXR + PNG preview
  demo       the README's main job on an embedded default scene
  refocus    refocus a rendered picture (colour + depth) with the MPI compositor
  compare    image metrics between two EXRs
  bench      speed/error measurements, written to a report folder
  dataset    many generated scenes with references (local processes or Dask)
  backends   which compute backends run on this machine
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import textwrap
from pathlib import Path

from mpib_validate import __version__


class CliError(Exception):
    """A user error: printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (no usage block), exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(kind, low=None, strict=False, what=None):
    """An argparse type: an int or a finite float, at least ``low`` (above it if
    ``strict``)."""
    name = "an integer" if kind is int else "a finite number"
    bound = "" if low is None else f" {'>' if strict else '>='} {low:g}"
    why = f" ({what})" if what else ""

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {name}{bound}, got {text!r}") from None
        if kind is float and not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"must be {name}{bound}, got {text!r}{why}")
        if low is not None and (v <= low if strict else v < low):
            raise argparse.ArgumentTypeError(f"must be {name}{bound}, got {text!r}{why}")
        return v

    parse.__name__ = "int" if kind is int else "float"
    return parse


_POSITIVE_INT = _number(int, 1)
_COUNT = _number(int, 0)
_FINITE = _number(float)
_POSITIVE = _number(float, 0, strict=True)
_NON_NEGATIVE = _number(float, 0)


def _OVERSHOOT(text: str) -> int:
    """An argparse type: ``--map-overshoot``, an integer from 0 to
    :data:`mpib_validate.runtime.io.photo.MAX_OVERSHOOT_PX` (pixels of the photograph)."""
    from mpib_validate.runtime.io.photo import MAX_OVERSHOOT_PX

    v = _COUNT(text)
    if v > MAX_OVERSHOOT_PX:
        raise argparse.ArgumentTypeError(f"must be an integer from 0 to {MAX_OVERSHOOT_PX} "
                                         f"(pixels of the photograph), got {text!r}")
    return v


def _FRACTION(text: str) -> float:
    """An argparse type: a finite number or a fraction ``a/b`` of two finite numbers
    (``207/255``, the official demo's syntax), ``b != 0``."""
    num, sep, den = text.partition("/")
    why = f"must be a finite number or a fraction a/b (such as 207/255), got {text!r}"
    try:
        v = float(num) / float(den) if sep else float(num)
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(why) from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(why)
    return v


_FRACTION.__name__ = "fraction"


def _limit(args) -> int:
    from mpib_validate.runtime.budget import memory_limit

    return memory_limit(getattr(args, "max_memory_gb", None))


def _add_memory_option(parser) -> None:
    parser.add_argument("--max-memory-gb", type=_POSITIVE, default=None, metavar="GB",
                        help="refuse work estimated to need more memory than this (default: "
                             "half of this machine's memory)")


def _outputs(path, preview: bool) -> list[Path]:
    """The EXR and, with ``preview``, its PNG beside it."""
    out = Path(path)
    return [out, out.with_suffix(".png")] if preview else [out]


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 256x256, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return w, h


def _sample_set(args, aperture=None):
    """The tracer's samples over the camera's ``aperture`` (None: the disk); the
    official grid is of the disk only."""
    from mpib_validate.runtime import samples

    if args.aperture == "grid":
        if aperture is not None and not aperture.is_disk:
            raise CliError(f"--aperture grid is the official generator's grid over a disk; "
                           f"this scene's camera has {aperture.describe()}: use --aperture "
                           f"sobol")
        return samples.grid(args.grid_side, pixel=args.pixel)
    return samples.stratified(args.spp, seed=args.seed, pixel=args.pixel, aperture=aperture)


# --------------------------------------------------------------------------------------


def cmd_generate(args) -> int:
    from mpib_validate.runtime import budget
    from mpib_validate.runtime.io.atomic import check_outputs
    from mpib_validate.cards.generate import GeneratorSettings, generate
    from mpib_validate.cards.scene import save_scene

    w, h = args.size
    if args.case == "grazing" and args.family == "constant":
        raise CliError("--case grazing tilts a card to near-grazing incidence; use it with "
                       "--family varying (--family constant keeps every card fronto-parallel)")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out '{out}' is a file; give a folder for the scene")
    if (out / "scene.json").exists() and not args.force:
        raise CliError(f"--out '{out}' already holds a scene (scene.json); give --force to "
                       f"replace it, or another folder")
    check_outputs([out / "scene.json"], option="--out")
    budget.check_pixels(w, h, "--size")
    budget.check(budget.generate_estimate(w, h), _limit(args))
    scene = generate(args.seed, args.family, args.case, GeneratorSettings(width=w, height=h))
    given = _aperture_given(args)
    if any(v is not None for v in given.values()):
        from mpib_validate.runtime.io.camera_header import CameraHeaderError, resolve_aperture

        try:
            scene = scene.with_camera(aperture=resolve_aperture(given))
        except CameraHeaderError as exc:
            raise CliError(str(exc)) from None
    path = save_scene(scene, args.out)
    cam = scene.camera
    print(f"wrote {path}: {len(scene.cards)} cards, {cam.width}x{cam.height}, "
          f"A={cam.blur_parameter:.2f} px, d_f={cam.focus_disparity:.4f}, "
          f"largest blur radius {scene.max_blur_radius():.1f} px")
    return 0


def _apply_camera_overrides(scene, args):
    changes = {}
    if args.focus_disparity is not None:
        changes["focus_disparity"] = args.focus_disparity
    if args.blur_parameter is not None:
        changes["blur_parameter"] = args.blur_parameter
    if not changes:
        return scene
    flags = " and ".join(f"--{k.replace('_', '-')}" for k in changes)
    return scene.with_camera(**changes).validate(f"the command line's {flags}")


def _render_estimate(scene, args):
    from mpib_validate.runtime import budget

    cam = scene.camera
    texels = sum(int(c.rgba.shape[0]) * int(c.rgba.shape[1]) for c in scene.cards)
    budget.check_pixels(cam.width, cam.height, f"the scene's camera ({args.scene})")
    _, sample_bytes = budget.samples_estimate(args.aperture, args.spp, args.grid_side)
    return budget.trace_estimate(cam.width, cam.height, len(scene.cards), texels, sample_bytes,
                                 args.engine)


def cmd_render(args) -> int:
    from mpib_validate.runtime import budget
    from mpib_validate.runtime.io.atomic import check_outputs
    from mpib_validate.cards.render_io import write_render
    from mpib_validate.cards.scene import load_scene
    from mpib_validate.cards.trace import render

    scene = _apply_camera_overrides(load_scene(args.scene,
                                               allow_outside=args.allow_outside_textures,
                                               memory_limit=_limit(args)), args)
    check_outputs(_outputs(args.output, not args.no_preview), scene.sources)
    budget.check(_render_estimate(scene, args), _limit(args))
    if args.engine == "cycles":
        from mpib_validate.blender.cycles import render_result

        result = render_result(scene, args.spp, seed=args.seed)
    elif args.engine == "mitsuba":
        import mitsuba_scenes

        if not scene.camera.aperture.is_disk:
            raise CliError(f"--engine mitsuba: Mitsuba's thinlens sensor has a disk aperture "
                           f"only; this scene's camera has {scene.camera.aperture.describe()} "
                           f"(use --engine trace or cycles)")

        result = mitsuba_scenes.render_result(scene, args.spp, seed=args.seed,
                                              variant=args.variant)
    else:
        result = render(scene, _sample_set(args, scene.camera.aperture), backend=args.backend,
                        lookup=args.lookup,
                        order=args.order, progress=not args.quiet)
    written = write_render(args.output, result, scene, preview=not args.no_preview)
    m = result.meta
    print(f"rendered {scene.camera.width}x{scene.camera.height}, {len(scene.cards)} cards, "
          f"{m['sample_count']} samples ({m['samples']}) on {m['backend']} in {m['seconds']:.2f} s")
    for p in written:
        print(f"wrote {p}")
    return 0


def cmd_demo(args) -> int:
    from mpib_validate.demo import DemoSettings, check_hero_path, run_demo

    w, h = args.size
    settings = DemoSettings(card_size=args.card_size, trace_spp=args.trace_spp, width=w,
                            height=h, spp=args.spp, sharp_spp=args.sharp_spp,
                            backend=args.backend).validate()
    check_hero_path(args.hero)
    run_demo(Path(args.out), settings, hero=args.hero)
    return 0


def cmd_bench(args) -> int:
    from mpib_validate.bench import run_bench
    from mpib_validate.executor import make_executor

    run_bench(Path(args.out), suite=args.suite, quick=not args.full,
              executor=make_executor(args.workers, args.scheduler))
    return 0


def _read_mask(path: str, shape):
    import numpy as np

    from mpib_validate.runtime.io.atomic import check_input
    from mpib_validate.runtime.io.exr import read_exr

    check_input(path, "mask")
    if path.lower().endswith(".exr"):
        img = read_exr(path)
        name = next((n for n in ("Y", "A", "R", "mask.Y") if n in img.channels),
                    sorted(img.channels)[0])
        m = img.channels[name] > 0.5
    else:
        from PIL import Image

        try:
            m = np.asarray(Image.open(path).convert("L")) > 127
        except (OSError, ValueError) as exc:
            raise CliError(f"cannot read mask '{path}': {exc}") from None
    if m.shape != tuple(shape):
        raise CliError(f"mask '{path}' is {m.shape[1]}x{m.shape[0]} but the images are "
                       f"{shape[1]}x{shape[0]}")
    return m


def cmd_compare(args) -> int:
    from mpib_validate.runtime import budget
    from mpib_validate.runtime.io.exr import header_size
    from mpib_validate.runtime.io.photo import header_size as map_size
    from mpib_validate.metrics import COMPARE_BYTES_PER_PX, all_metrics
    from mpib_validate.runtime.refocus import read_colour

    parts, sizes = {}, []
    for label, path in (("reference", args.reference), ("test", args.test)):
        w, h, nch = header_size(path)
        parts[f"decoding the {label} ({w}x{h}, {nch} channels)"] = 4 * nch * w * h
        sizes.append((w, h))
    if args.mask:
        mw, mh = map_size(args.mask, "mask")
        parts[f"decoding the mask ({mw}x{mh})"] = 8 * mw * mh
    w, h = max(sizes, key=lambda s: s[0] * s[1])
    budget.check(budget.Estimate(f"comparing {w}x{h} images", {
        **parts, "metrics": COMPARE_BYTES_PER_PX * w * h}), _limit(args))
    a = read_colour(args.reference, all_in_focus=False)
    b = read_colour(args.test, all_in_focus=False)
    if a.shape != b.shape:
        raise CliError(f"image sizes differ: '{args.reference}' is {a.shape[1]}x{a.shape[0]}, "
                       f"'{args.test}' is {b.shape[1]}x{b.shape[0]}")
    mask = _read_mask(args.mask, a.shape[:2]) if args.mask else None
    if mask is not None and not mask.any():
        raise CliError(f"mask '{args.mask}' selects no pixel (no value above one half)")
    res = all_metrics(a[..., :3], b[..., :3], mask, peak=args.peak, with_flip=not args.no_flip)
    notes = _metric_notes(res, a.shape)
    if args.json:
        clean = {k: (v if math.isfinite(v) else None) for k, v in res.items()}
        print(json.dumps({**clean, "notes": notes} if notes else clean, indent=2))
    else:
        for k, v in res.items():
            text = f"{v:.6g}" if math.isfinite(v) else ("inf" if v > 0 else "n/a")
            print(f"{k:14s} {text}" + (f"  ({notes[k]})" if k in notes else ""))
    return 0


def _metric_notes(res: dict, shape) -> dict:
    """Why a figure is not a finite number (identical images, images too small)."""
    from mpib_validate.metrics import SSIM_WINDOW

    notes = {}
    for k, v in res.items():
        if math.isfinite(v):
            continue
        if k.startswith("psnr") and v > 0:
            notes[k] = "identical images"
        elif k.startswith("ssim"):
            notes[k] = (f"undefined on images smaller than {SSIM_WINDOW}x{SSIM_WINDOW}; "
                        f"these are {shape[1]}x{shape[0]}")
        else:
            notes[k] = "undefined"
    return notes


def _parse_pixel(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a pixel looks like X,Y (e.g. 120,80), got {text!r}") from None
    return x, y


def _refocus_camera(args, passes):
    """The camera of ``mpib refocus``: the input header's, each field overridden by the
    option that gives it (:func:`mpib_validate.runtime.io.camera_header.resolve`)."""
    from mpib_validate.runtime.io.camera_header import resolve
    from mpib_validate.runtime.refocus import focus_from_pixel

    H, W = passes.depth.shape
    given = {"lens_mm": args.focal_mm, "sensor_width_mm": args.sensor_mm,
             "sensor_height_mm": args.sensor_height_mm, "sensor_fit": args.sensor_fit,
             "fstop": args.fstop, "unit_scale": args.scene_unit_m,
             "blur_parameter": args.blur_parameter, "focus_distance": args.focus_depth,
             "focus_disparity": args.focus_disparity, **_aperture_given(args)}
    labels = {}
    if args.focus_pixel is not None:
        x, y = args.focus_pixel
        if not (0 <= x < W and 0 <= y < H):
            raise CliError(f"--focus-pixel {x},{y} is outside the {W}x{H} image")
        given["focus_disparity"] = focus_from_pixel(passes, x, y, far_limit=args.far_limit)
        labels["focus_disparity"] = "--focus-pixel {},{}".format(*args.focus_pixel)
    return resolve(passes.camera, given, W, H, args.input, labels)


def _aperture_given(args) -> dict:
    """The aperture options as camera fields (``--rotation`` degrees to radians), None
    where not given; a non-finite rotation is refused here, naming the option (the
    blades and the ratio are checked by ``camera_header.resolve``)."""
    rotation = args.rotation
    if rotation is not None:
        if not math.isfinite(rotation):
            raise CliError(f"--rotation must be a finite angle in degrees, got {rotation}")
        rotation = math.radians(rotation)
    return {"aperture_blades": args.blades, "aperture_rotation": rotation,
            "aperture_ratio": args.ratio}


def _cli_aperture(args):
    """The aperture of the options alone (a photograph with --K: no header), a disk where
    none is given."""
    from mpib_validate.runtime.io.camera_header import resolve_aperture

    return resolve_aperture(_aperture_given(args))


def _progress_bar(enabled: bool, desc: str, total: float, unit: str):
    """A tqdm bar on a terminal (none when not a terminal, or not ``enabled``)."""
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit=unit, leave=False, disable=None)


def _check_cache_dir(path: str, inputs) -> None:
    """``--mpi-cache DIR``: a folder (made if missing) that is writable and not an input."""
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise CliError(f"--mpi-cache '{path}' is not a directory")
    for p in inputs:
        if Path(p).resolve() == d.resolve():
            raise CliError(f"--mpi-cache '{path}' is an input file")
    parent = d
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise CliError(f"--mpi-cache '{path}': cannot write in '{parent}'")


class _TableFormatter(argparse.HelpFormatter):
    """Help text wrapped as usual, except text with line breaks (a table), kept as is."""

    def _fill_text(self, text, width, indent):
        if "\n" in text:
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


_REFOCUS_EPILOG = """\
parameters, paper and physical (blur radius r in pixels, disparity d):
  paper (photographs)       physical (renders)                  the model
  --K K                     --fstop N --focal-mm F [--sensor-mm] A = K = R f_px
                            or --blur-parameter A
  --disp-focus D in [0, 1]  --focus-depth Z | --focus-disparity  d_f = D = 1/Z
  --focus-pixel X,Y         --focus-pixel X,Y                    d_f = d at (X, Y)
  map d in [0, 1], 0 = far  --depth FILE (d = 1/Z)               r = A |d - d_f|
  --gamma 2.2, else sRGB    EXR: linear                          Eq. 1 on linear colour

examples:
  mpib refocus render.exr -o refocused.exr                  # lens and focus from the EXR header
  mpib refocus render.exr -o near.exr --fstop 2 --focus-pixel 40,60 --mpi-cache mpi-cache/
  mpib refocus photo.jpg --disparity disp.png --K 60 --disp-focus 207/255 -o out.jpg
"""

_MAIN_EPILOG = """\
examples:
  mpib generate --seed 3 --family varying --out scenes/s3
  mpib render scenes/s3 --engine trace -o renders/s3.exr
  mpib refocus renders/s3.exr -o renders/s3-mpib.exr

Each command has its own --help. Documentation: README.md and docs/ in the repository.
"""

_GENERATE_EPILOG = """\
examples:
  mpib generate --seed 3 --family varying --out scenes/s3
  mpib generate --seed 3 --family constant --case hair --size 320x240 --out scenes/hair
"""

_RENDER_EPILOG = """\
examples:
  mpib render scenes/s3 --engine trace -o renders/s3.exr       # + renders/s3.png
  mpib render scenes/s3 -o renders/s3-grid.exr --aperture grid --grid-side 51 --pixel centre
  mpib render scenes/s3 --engine cycles --spp 256 -o renders/s3-cycles.exr
"""

_DEMO_EPILOG = """\
examples:
  mpib demo --out out/demo
  mpib demo --out out/demo --hero docs/images/hero.jpg   # also the README's picture
"""

_BENCH_EPILOG = """\
suites: %s (default: all)

examples:
  mpib bench --out out/bench                       # every suite, quick mode
  mpib bench --suite refocus --out out/bench       # one suite
  mpib bench --suite official --full               # needs make official (CPU torch)
"""

_COMPARE_EPILOG = """\
example:
  mpib compare renders/s3.exr renders/s3-mpib.exr --mask mask.exr --json
"""

_DATASET_EPILOG = """\
examples:
  mpib dataset --out data --count 1000 --workers 2
  mpib dataset --out data --count 1000 --scheduler tcp://host:8786    # a Dask cluster
"""

_BACKENDS_EPILOG = """\
example:
  mpib backends
"""


def _plan_and_refocus(args, request, notices=()):
    """Estimate the memory of the request (refused past --max-memory-gb), print
    ``notices`` (on stderr, once the input is accepted) and the plan, and refocus with a
    progress bar on a terminal (with --mpi-cache: through the disk cache)."""
    from mpib_validate.runtime import budget
    from mpib_validate.runtime.layers.cache import DiskCache
    from mpib_validate.runtime.refocus import refocus

    H, W = request.passes.depth.shape
    est = budget.estimate_request(request)
    budget.check(est, _limit(args))
    for notice in notices:
        print(f"mpib refocus: notice: {notice}", file=sys.stderr, flush=True)
    print(f"refocusing {W}x{H} ({request.preset.name}): {est.describe()}", flush=True)
    bar = _progress_bar(not args.quiet, "refocus", 100, "%")

    def progress(fraction):
        if bar is not None:
            bar.update(max(0, int(round(100 * fraction)) - bar.n))

    try:
        cache = None if args.mpi_cache is None else DiskCache(args.mpi_cache)
        from mpib_validate.runtime.io.atomic import apart

        # the cache is kept as it is built: not an output of the run, written at once
        with apart():
            result = refocus(request, progress, cache)
        if args.mpi_cache is not None:
            cached = result.info["mpi_cache"]
            if cached.get("notice"):
                print(f"mpib refocus: {cached['notice']}", file=sys.stderr, flush=True)
            reused, entry = cached["reused"], cached["entry"]
            print(f"{'reused the cached MPI' if reused else 'built the MPI and cached it as'} "
                  f"{entry}" + (" (same inputs, preset, far limit and aperture)" if reused
                                else ""), flush=True)
        if bar is not None:
            bar.refresh()
    finally:
        if bar is not None:
            bar.close()
    return result


_PHOTO_ONLY = ("disparity", "K", "disp_focus", "gamma", "encoding", "exr", "official_focus_range",
               "refine", "map_overshoot")


def _photo_input(args) -> bool:
    """Whether ``mpib refocus`` reads a photograph (JPEG/PNG/TIFF colour, or any colour
    with ``--disparity``) rather than rendered EXR passes."""
    from mpib_validate.runtime.io.photo import image_format

    return args.disparity is not None or image_format(args.input) in ("JPEG", "PNG", "TIFF")


def _photo_encoding(args):
    from mpib_validate.runtime.io.photo import Encoding

    if args.gamma is not None:
        if args.encoding not in (None, "gamma"):
            raise CliError(f"--gamma {args.gamma:g} is the paper's encoding; do not combine it "
                           f"with --encoding {args.encoding}")
        return Encoding("gamma", args.gamma)
    if args.encoding == "gamma":
        raise CliError("--encoding gamma needs --gamma G (the paper uses 2.2)")
    return Encoding(args.encoding) if args.encoding else None


def _photo_outputs(args) -> list[Path]:
    from mpib_validate.runtime.io.photo import image_format

    fmt = image_format(args.output)
    if fmt is None:
        raise CliError(f"-o '{args.output}': give a .jpg, .png, .tif or .exr name")
    outs = _outputs(args.output, not args.no_preview) if fmt == "EXR" else [Path(args.output)]
    if args.exr:
        if image_format(args.exr) != "EXR":
            raise CliError(f"--exr '{args.exr}': give a .exr name")
        outs.append(Path(args.exr))
    return outs


def _refocus_photo(args) -> int:
    """``mpib refocus`` of a photograph with a disparity map (or a depth EXR): the MPI is
    built from the linearised colour and the disparity by the same
    :func:`~mpib_validate.runtime.refocus.refocus` as rendered passes; the output is written in
    the input's encoding (see :mod:`mpib_validate.runtime.io.photo`)."""
    import numpy as np

    from mpib_validate.runtime.camera import OFFICIAL_BINS, from_paper, widen_focus
    from mpib_validate.runtime.io.atomic import check_outputs
    from mpib_validate.runtime.io.photo import (Encoding, image_format, output_bits,
                                                read_disparity, read_photo, shrink_overshoot,
                                                upsample_disparity, write_photo)
    from mpib_validate.runtime.layers.passes import depth_to_disparity
    from mpib_validate.runtime.refocus import _depth_channel, focus_from_pixel, passes_from_photo, write_result
    from mpib_validate.runtime.request import RefocusRequest
    from mpib_validate.runtime.io.exr import read_exr

    for opt, given in (("--layered", args.layered), ("--background", args.background),
                       ("--view-layer", args.view_layer)):
        if given:
            raise CliError(f"{opt} is for rendered EXR passes, not a photograph with a "
                           f"disparity map")
    if (args.disparity is None) == (args.depth is None):
        raise CliError(f"'{args.input}' is a photograph: give its disparity map with "
                       f"--disparity FILE (or a depth EXR with --depth FILE), one of them")
    inputs = [args.input] + [p for p in (args.disparity, args.depth) if p]
    outputs = _photo_outputs(args)
    check_outputs(outputs, inputs)
    if args.mpi_cache is not None:
        _check_cache_dir(args.mpi_cache, inputs)
    if args.K is not None and args.blur_parameter is not None:
        raise CliError("--K and --blur-parameter both give the blur: give one")
    lens = [o for o, v in (("--fstop", args.fstop), ("--focal-mm", args.focal_mm),
                           ("--sensor-mm", args.sensor_mm),
                           ("--sensor-height-mm", args.sensor_height_mm),
                           ("--sensor-fit", args.sensor_fit),
                           ("--scene-unit-m", args.scene_unit_m)) if v is not None]
    if args.K is not None and lens:
        raise CliError(f"--K gives the blur directly: do not combine it with {', '.join(lens)}")
    if args.K is None and args.blur_parameter is None and not lens:
        raise CliError("no blur: give --K (the paper's blur parameter, pixels per unit of the "
                       "[0, 1] disparity), --blur-parameter, or --fstop and --focal-mm")
    if args.K is None:
        for opt, given in (("--disp-focus", args.disp_focus is not None),
                           ("--official-focus-range", args.official_focus_range)):
            if given:
                raise CliError(f"{opt} is in the paper's convention on the [0, 1] disparity: "
                               f"use it with --K")
    elif args.focus_depth is not None:
        raise CliError("--focus-depth is a distance, which a normalised disparity map has no "
                       "scale for: give --disp-focus (in [0, 1]) or --focus-pixel X,Y")
    _check_reading(args, [(args.input, "photo")] + [(p, kind) for p, kind in (
        (args.disparity, "map"), (args.depth, "exr")) if p])
    photo = read_photo(args.input, _photo_encoding(args))
    H, W = photo.rgb.shape[:2]
    notices = []  # printed once the input is accepted (a refusal is one line)
    if args.disparity is not None:
        dmap = read_disparity(args.disparity, (H, W), normalised=args.K is not None,
                              any_size=True)
        if dmap.normalised and lens:
            raise CliError(f"'{args.disparity}' is a normalised {dmap.kind} map, which has no "
                           f"physical scale: give --K instead of {', '.join(lens)}")
        D, dsrc = dmap.values, f"{args.disparity} ({dmap.kind} disparity)"
        if D.shape != (H, W):
            notices.append(f"disparity map '{args.disparity}' is {D.shape[1]}x{D.shape[0]}: "
                           f"upsampled to {W}x{H} (bilinear; the refinement moves its edges "
                           f"onto the photograph's)")
            D = upsample_disparity(D, (H, W))
            dsrc = f"{dsrc}, upsampled from {dmap.values.shape[1]}x{dmap.values.shape[0]}"
        if args.map_overshoot:
            D = shrink_overshoot(D, args.map_overshoot)
            dsrc = f"{dsrc}, near side shrunk by {args.map_overshoot} px"
            notices.append(f"disparity map '{args.disparity}': near side shrunk by "
                           f"{args.map_overshoot} px (--map-overshoot)")
    else:
        if args.map_overshoot is not None:
            raise CliError("--map-overshoot is for a predicted map (--disparity FILE); a depth "
                           "EXR is taken as exact")
        if args.K is not None:
            raise CliError("--K is per unit of a [0, 1] normalised disparity: give "
                           "--disparity, or --blur-parameter with --depth")
        z = _depth_channel(read_exr(args.depth), args.depth)
        if z.shape != (H, W):
            raise CliError(f"depth '{args.depth}' is {z.shape[1]}x{z.shape[0]} but the "
                           f"photograph is {W}x{H}")
        dsrc = str(args.depth)
        D = depth_to_disparity(z, args.far_limit, source=dsrc)
    passes = passes_from_photo(photo, D, dsrc)
    _set_pixel_model(args, passes)
    if args.K is not None:
        # on a normalised map --focus-disparity is the same number as --disp-focus
        focus = args.disp_focus if args.disp_focus is not None else args.focus_disparity
        if args.focus_pixel is not None:
            x, y = args.focus_pixel
            if not (0 <= x < W and 0 <= y < H):
                raise CliError(f"--focus-pixel {x},{y} is outside the {W}x{H} image")
            focus = focus_from_pixel(passes, x, y)
        if focus is None:
            raise CliError("no focus: give --disp-focus (in [0, 1]) or --focus-pixel X,Y")
        try:
            A, d_f = from_paper(args.K, focus)
        except ValueError as exc:  # names the option
            raise CliError(str(exc)) from None
        sources = {"blur_parameter": "--K", "focus_disparity": "--focus-pixel {},{}".format(
            *args.focus_pixel) if args.focus_pixel else (
            "--disp-focus" if args.disp_focus is not None else "--focus-disparity")}
        aperture = _cli_aperture(args)
        camera_info = {"K": A, "disp_focus": d_f, "from": sources}
        if not aperture.is_disk:
            camera_info["aperture"] = aperture.to_dict()
    else:
        used = _refocus_camera(args, passes)
        A, d_f = used.camera.blur_parameter, used.camera.focus_disparity
        aperture = used.camera.aperture
        camera_info = used.header()
    if args.official_focus_range:
        passes.disparity = widen_focus(D, d_f, 0.5 / OFFICIAL_BINS)
    # a predicted disparity map is refined onto the colour edges unless told otherwise; a
    # depth EXR is taken as a renderer's exact depth
    refine = args.refine or ("guided" if args.disparity is not None else "off")
    result = _plan_and_refocus(args, RefocusRequest(passes, A, d_f, args.preset, args.far_limit,
                                                    refine=refine, aperture=aperture),
                               notices=notices)
    result.info["refine"] = refine
    result.info["camera"] = camera_info
    result.info["encoding"] = photo.encoding.describe()
    img = result.image
    if not np.isfinite(img).all():  # never a NaN image with exit 0
        raise CliError("the refocused image holds NaN or infinite values (a bug; please "
                       "report it with the inputs)")
    alpha = None if photo.alpha is None else img[..., 3]
    written = []
    if image_format(args.output) == "EXR":
        written += write_result(args.output, result, preview=not args.no_preview)
    else:
        # a linear input written to an integer file is encoded as sRGB unless told
        enc = photo.encoding if photo.encoding.name != "linear" else (
            _photo_encoding(args) or Encoding("srgb"))
        write_photo(args.output, img[..., :3], alpha, enc, output_bits(photo, args.output),
                    photo.icc_profile)
        written.append(Path(args.output))
    if args.exr:
        written += write_result(args.exr, result, preview=False)
    i = result.info
    return _report(f"refocused {W}x{H} ({args.preset})", i, written,
                   f"{'A = K' if args.K is not None else 'A'} = {A:.4g} px, d_f = {d_f:.5g}, "
                   f"{photo.encoding.describe()}, disparity refinement {refine}")


#: Peak bytes per pixel of reading an EXR's passes (``refocus.load_passes`` or
#: ``load_layered_passes``), per channel the file holds and fixed: measured 60 B/px for
#: colour and depth (5 channels), 276 and 480 B/px for layered renders of 2 and 5 groups
#: (14 and 29 channels), 2000x1500, fresh processes.
EXR_READ_BYTES_PER_CHANNEL = 14
EXR_READ_BYTES = 86


def _check_reading(args, inputs) -> None:
    """Refuse, from the files' headers and before any pixel is decoded, a refocus whose
    inputs alone would take more memory than --max-memory-gb: decoding each input
    (``inputs``: ``(path, kind)``, kind ``photo``, ``map`` or ``exr``) and the least any
    refocus of that size needs (``budget.reading_estimate``)."""
    from mpib_validate.runtime import budget
    from mpib_validate.runtime.io.exr import header_size as exr_size
    from mpib_validate.runtime.io.photo import READ_BYTES_PER_PX, header_size, image_format

    parts, size = {}, None
    for path, kind in inputs:
        if kind == "exr" or (kind == "photo" and image_format(path) == "EXR"):
            w, h, nch = exr_size(path)
            per = (EXR_READ_BYTES + EXR_READ_BYTES_PER_CHANNEL * nch if kind == "exr"
                   else READ_BYTES_PER_PX["float"])
        else:
            w, h = header_size(path, "disparity map" if kind == "map" else "photograph")
            per = READ_BYTES_PER_PX["integer" if kind == "photo" else "map"]
        parts[f"reading '{Path(path).name}' ({w}x{h})"] = per * w * h
        size = size or (w, h)
    budget.check(budget.reading_estimate(f"refocusing {size[0]}x{size[1]}", parts,
                                         size[0] * size[1]), _limit(args))


def _set_pixel_model(args, passes) -> None:
    """``--pixel-model`` over what the input says (``refocus.pixel_model_of``)."""
    if getattr(args, "pixel_model", "auto") != "auto":
        passes.pixel_model = args.pixel_model


def cmd_refocus(args) -> int:
    from mpib_validate.runtime.io.atomic import check_outputs
    from mpib_validate.runtime.refocus import load_layered_passes, load_passes, read_background, write_result
    from mpib_validate.runtime.request import RefocusRequest

    if _photo_input(args):
        return _refocus_photo(args)
    for name in _PHOTO_ONLY:
        if getattr(args, name) not in (None, False):
            opt = "--" + name.replace("_", "-")
            raise CliError(f"{opt} is for a photograph with a disparity map (--disparity "
                           f"FILE); '{args.input}' is read as rendered EXR passes")
    inputs = [args.input] + [p for p in (args.depth, args.background) if p]
    check_outputs(_outputs(args.output, not args.no_preview), inputs)
    if args.mpi_cache is not None:
        _check_cache_dir(args.mpi_cache, inputs)
    if args.layered and (args.depth or args.background or args.view_layer):
        raise CliError("--layered takes colour and depth from the input's view layers: "
                       "drop --depth, --background and --view-layer")
    _check_reading(args, [(args.input, "exr")] + [(p, "exr") for p in (args.depth,
                                                                        args.background) if p])
    # layered input: with --layered, or view layers named mpib_group_<k> (automatic)
    layered = not (args.depth or args.view_layer)
    passes = load_layered_passes(args.input, True if args.layered else None,
                                 args.far_limit) if layered else None
    if passes is not None and args.background:
        raise CliError(f"'{args.input}' is a layered render (mpib_group_ view layers): the "
                       f"groups hold what lies behind the foreground; drop --background")
    if passes is None:
        passes = load_passes(args.input, args.depth, view_layer=args.view_layer)
    _set_pixel_model(args, passes)
    for notice in passes.notices:
        print(f"mpib refocus: notice: {notice}", file=sys.stderr)
    H, W = passes.depth.shape
    used = _refocus_camera(args, passes)
    A, d_f = used.camera.blur_parameter, used.camera.focus_disparity
    background = read_background(args.background, (H, W)) if args.background else None
    result = _plan_and_refocus(args, RefocusRequest(passes, A, d_f, args.preset, args.far_limit,
                                                    background,
                                                    aperture=used.camera.aperture))
    result.info["camera"] = used.header()  # which camera fields were used, and from where
    written = write_result(args.output, result, preview=not args.no_preview)
    i = result.info
    layered = f", {i['groups']} depth groups" if i["groups"] > 1 else ""
    return _report(f"refocused {W}x{H} ({args.preset}{layered})", i, written,
                   f"edge pixels {100 * i['edge_fraction']:.1f} %, A = {A:.3f} px, "
                   f"d_f = {d_f:.5g}" + ("" if used.camera.aperture.is_disk else
                                         f", aperture {used.camera.aperture.describe()}"))


def _report(head: str, info: dict, written, details: str) -> int:
    """The one summary line of ``mpib refocus`` (planes, largest blur, fill, then the
    path's own ``details`` and the time) and the files written; exit status 0."""
    print(f"{head}: {info['planes']} planes, largest blur radius "
          f"{info['largest_radius_px']:.1f} px, fill {100 * info['fill_fraction']:.1f} % of "
          f"pixels, {details}, {info['seconds']:.2f} s")
    for p in written:
        print(f"wrote {p}")
    return 0


def cmd_dataset(args) -> int:
    import time

    from mpib_validate.runtime import budget
    from mpib_validate.cards.dataset import build_dataset
    from mpib_validate.executor import make_executor

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out '{out}' is a file; give a folder for the dataset")
    w, h = args.size
    budget.check_pixels(w, h, "--size")
    one = budget.generate_estimate(w, h).bytes + budget.trace_estimate(
        w, h, 4, 4 * w * h, budget.samples_estimate("sobol", args.spp, 0)[1]).bytes
    per = budget.Estimate(f"building {w}x{h} samples on {max(args.workers, 1)} worker(s)",
                          {"one sample per worker": one * max(args.workers, 1)})
    budget.check(per, _limit(args))
    ex = make_executor(args.workers, args.scheduler)
    ex.check()
    bar = _progress_bar(True, "dataset", args.count, "sample")

    def progress(result):
        bar.update(1)
        bar.refresh()  # samples are slow: show each one

    t0 = time.perf_counter()
    try:
        summary = build_dataset(args.out, args.count, args.family, args.size, args.spp,
                                args.start, ex, progress=progress if bar is not None else None)
    finally:
        if bar is not None:
            bar.close()
    print(f"dataset {args.out}: {summary['count']} complete samples; built {summary['built']}, "
          f"skipped {summary['skipped']} already done ({ex.kind}, {time.perf_counter() - t0:.1f} s)")
    return 0


def cmd_backends(args) -> int:
    from mpib_validate.runtime.compositor import backend

    report = {}
    for name in ("numpy", "llvm", "cuda"):
        be = backend.resolve(name)
        report[name] = {"runs_as": be.name, "notice": be.notice, "llvm_library": be.llvm_library}
    print(json.dumps(report, indent=2))
    return 0


# --------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    from mpib_validate.runtime.camera import SENSOR_FITS
    from mpib_validate.cards.generate import FAMILIES, HARD_CASES
    from mpib_validate.runtime.presets import PRESETS

    p = _Parser(prog="mpib", description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=_MAIN_EPILOG)
    p.add_argument("--version", action="version", version=f"mpib {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    g = sub.add_parser("generate", help="make a seeded random card scene",
                       description="Write a random card scene (scene.json + cards/*.exr). "
                                   "The same seed gives the same files, byte for byte.",
                       formatter_class=_TableFormatter, epilog=_GENERATE_EPILOG)
    g.add_argument("--seed", type=_COUNT, default=0, help="non-negative integer (default 0)")
    g.add_argument("--family", choices=FAMILIES, default="constant",
                   help="constant: fronto-parallel cards; varying: tilted planes")
    g.add_argument("--case", choices=HARD_CASES, default=None, help="force one named hard case")
    g.add_argument("--size", type=_parse_size, default=(256, 256), help="WxH (default 256x256)")
    g.add_argument("--out", required=True, help="output scene directory")
    g.add_argument("--force", action="store_true", help="replace a scene already in --out")
    g.add_argument("--blades", type=int, metavar="N",
                   help="the camera's aperture blades: 0 (a disk, default) or 3 to 16")
    g.add_argument("--rotation", type=float, metavar="DEG",
                   help="the blades' rotation in degrees, counter-clockwise on screen")
    g.add_argument("--ratio", type=float,
                   help="anamorphic ratio: the aperture's width is divided by it (default 1)")
    _add_memory_option(g)
    g.set_defaults(func=cmd_generate)

    r = sub.add_parser("render", help="render a scene to EXR + PNG",
                       description="Render a card scene. --engine trace is the paper's "
                                   "image-space thin-lens ray tracer (Eq. 15).",
                       formatter_class=_TableFormatter, epilog=_RENDER_EPILOG)
    r.add_argument("scene", help="scene directory or scene.json")
    r.add_argument("-o", "--output", required=True, help="output EXR path (a PNG is written beside it)")
    r.add_argument("--engine", default="trace", choices=["trace", "mitsuba", "cycles"])
    r.add_argument("--aperture", choices=["sobol", "grid"], default="sobol",
                   help="sobol: scrambled 4-D Sobol (default); grid: the official square grid")
    r.add_argument("--spp", type=_POSITIVE_INT, default=1024,
                   help="samples per pixel (trace with --aperture sobol, cycles, mitsuba)")
    r.add_argument("--variant", default=None,
                   help="Mitsuba variant (default: probed: cuda_ad_rgb, llvm_ad_rgb, scalar_rgb)")
    r.add_argument("--grid-side", type=_POSITIVE_INT, default=51,
                   help="grid points per side for --aperture grid (51 = 1,957 samples)")
    r.add_argument("--pixel", choices=["box", "centre"], default="box",
                   help="box: average over the pixel area (canonical); centre: pixel centres")
    r.add_argument("--seed", type=_COUNT, default=0, help="sample set seed")
    r.add_argument("--backend", choices=["auto", "numpy", "llvm", "cuda"], default="auto")
    r.add_argument("--lookup", choices=["nearest", "bilinear"], default="nearest")
    r.add_argument("--order", choices=["depth", "fixed"], default="depth",
                   help="depth: per-ray depth sort; fixed: the official generator's order")
    r.add_argument("--focus-disparity", type=_FINITE, default=None, help="override d_f (1/scene-unit)")
    r.add_argument("--blur-parameter", type=_FINITE, default=None, help="override A (px per unit disparity)")
    r.add_argument("--no-preview", action="store_true", help="do not write the PNG preview")
    r.add_argument("--allow-outside-textures", action="store_true",
                   help="read texture paths that lead outside the scene folder ('..', "
                        "absolute paths, links pointing out); refused by default, see "
                        "docs/scene-format.md")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_memory_option(r)
    r.set_defaults(func=cmd_render)

    d = sub.add_parser("demo", help="render the default scenes, refocus them, write a picture gallery",
                       description="Render a card scene (ray tracer) and a Blender scene "
                                   "(Cycles, CPU), refocus each at two foci with mpib and "
                                   "Blender's Defocus node, score them against the references "
                                   "and write a gallery (index.html, index.md): inputs, results, "
                                   "boundary crops, error maps, a speed-against-error plot. A "
                                   "few minutes on 2 cores; the Cycles renders are cached in "
                                   "OUT/blender-cache.",
                       formatter_class=_TableFormatter, epilog=_DEMO_EPILOG)
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--hero", default=None, metavar="FILE",
                   help="also write the sharp | Defocus node | mpib | Cycles picture here "
                        "(.jpg or .png) and its figures beside it (.json)")
    d.add_argument("--size", type=_parse_size, default=(320, 240),
                   help="WxH of the Blender scene (default 320x240)")
    d.add_argument("--spp", type=_POSITIVE_INT, default=128,
                   help="Cycles samples per seed of the depth-of-field truth (default 128, "
                        "2 seeds)")
    d.add_argument("--sharp-spp", type=_POSITIVE_INT, default=32,
                   help="Cycles samples of the sharp input (default 32)")
    d.add_argument("--card-size", type=_POSITIVE_INT, default=256,
                   help="side of the card scene in pixels (default 256)")
    d.add_argument("--trace-spp", type=_POSITIVE_INT, default=16384,
                   help="aperture samples of the ray-traced reference (default 16384)")
    d.add_argument("--backend", choices=["auto", "numpy", "llvm", "cuda"], default="auto",
                   help="the ray tracer's backend (default auto)")
    d.set_defaults(func=cmd_demo)

    b = sub.add_parser("bench", help="measure speed and error; write a report",
                       description="Run a benchmark suite and write a report folder "
                                   "(Markdown + JSON).",
                       formatter_class=_TableFormatter)
    b.add_argument("--out", default="out/bench", help="report folder (default out/bench)")
    from mpib_validate.bench import SUITES

    b.epilog = _BENCH_EPILOG % textwrap.fill(", ".join(SUITES), 70, subsequent_indent="  ")
    b.add_argument("--suite", choices=["all", *SUITES], default="all", metavar="NAME",
                   help="one suite, or all (the suites are listed below)")
    mode = b.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true",
                      help="small scenes, a few minutes on 2 cores (the default)")
    mode.add_argument("--full", action="store_true", help="larger scenes and more samples (slow)")
    b.add_argument("--workers", type=_COUNT, default=0,
                   help="spread per-scene work over local processes (times then share the machine)")
    b.add_argument("--scheduler", default=None,
                   help="Dask scheduler address, or 'local' for a LocalCluster")
    b.set_defaults(func=cmd_bench)

    c = sub.add_parser("compare", help="PSNR, SSIM, FLIP (and _ob variants) of two EXRs",
                       description="Compare a test image with a reference: PSNR, SSIM and FLIP "
                                   "on [0, 1]-clipped values and on linear HDR values; with "
                                   "--mask also PSNR_ob and SSIM_ob inside the mask.",
                       formatter_class=_TableFormatter, epilog=_COMPARE_EPILOG)
    c.add_argument("reference", help="reference EXR")
    c.add_argument("test", help="test EXR")
    c.add_argument("--mask", help="mask (EXR channel Y/A/R > 0.5, or a PNG > 127)")
    c.add_argument("--peak", type=_POSITIVE, default=None,
                   help="HDR data range (default: the reference's largest value, at least 1)")
    c.add_argument("--no-flip", action="store_true", help="skip FLIP")
    c.add_argument("--json", action="store_true", help="print JSON")
    _add_memory_option(c)
    c.set_defaults(func=cmd_compare)

    f = sub.add_parser("refocus", help="refocus a rendered picture (colour + depth EXR) or a "
                                       "photograph with a disparity map",
                       formatter_class=_TableFormatter,
                       description="Refocus a picture from its colour and depth passes with the "
                                   "MPI compositor. Input: a Blender multilayer EXR (Combined + "
                                   "Depth), an mpib render, or colour plus --depth; or a "
                                   "photograph (JPEG, PNG, TIFF or EXR) with --disparity.",
                       epilog=_REFOCUS_EPILOG)
    f.add_argument("input", help="EXR with colour (and depth, unless --depth), or a photograph "
                                 "(.jpg, .png, .tif) with --disparity")
    f.add_argument("-o", "--output", required=True,
                   help="output EXR (a PNG is written beside it); for a photograph also .jpg, "
                        ".png or .tif, written in the input's encoding")
    f.add_argument("--depth", help="separate EXR holding the depth (Z, Depth.Z, Y or R)")
    photo = f.add_argument_group(
        "photographs", "A photograph with a disparity map, in the MPIB paper's convention: "
        "--K and --disp-focus (or --focus-pixel). See the table below.")
    photo.add_argument("--disparity", metavar="FILE",
                       help="disparity map: 8/16-bit grey PNG/JPEG/TIFF (scaled to [0, 1]: "
                            "v/255, v/65535) or float EXR/TIFF/.npy; 0 = infinitely far; "
                            "a map at a network's resolution (same aspect ratio) is "
                            "upsampled")
    photo.add_argument("--K", type=_POSITIVE, metavar="K",
                       help="the paper's blur parameter: blur radius in pixels per unit of the "
                            "[0, 1] disparity, r = K |d - disp_focus| (A = K)")
    photo.add_argument("--gamma", type=_POSITIVE, metavar="G",
                       help="the paper's encoding: linear = value ** G (the paper uses 2.2); "
                            "the output is written with ** (1/G)")
    photo.add_argument("--encoding", choices=["srgb", "linear"],
                       help="colour encoding of an 8/16-bit photograph (default srgb, the exact "
                            "IEC 61966-2-1 curve; EXR and float TIFF are linear)")
    photo.add_argument("--exr", metavar="PATH",
                       help="also write the refocused linear EXR here")
    photo.add_argument("--refine", choices=["off", "guided", "guided-thin"], default=None,
                       help="move a predicted disparity's edges onto the colour edges before "
                            "the split (layers/refine.py): guided (the default with "
                            "--disparity), guided-thin (also thin structures; about 1.4 "
                            "times the cost), off (the default with --depth)")
    photo.add_argument("--map-overshoot", type=_OVERSHOOT, metavar="PX",
                       help="the map's near side overshoots the outlines by PX photograph "
                            "pixels (a halo of sharp background around an in-focus object): "
                            "shrink it first, a grey erosion over a (2 PX + 1)^2 square "
                            "(default 0; at most 64)")
    photo.add_argument("--official-focus-range", action="store_true",
                       help="as the official renderer's demo (increase_focus_range): subtract "
                            "half a 1/32 bin from every defocus, r = K max(|d - d_f| - 1/64, 0)")
    f.add_argument("--background",
                   help="EXR of the scene rendered without the foreground: used in place of "
                        "the hidden-background fill where its alpha > 0.5")
    g2 = f.add_mutually_exclusive_group()
    g2.add_argument("--focus-depth", type=float, metavar="Z", help="focus distance (scene units)")
    g2.add_argument("--focus-disparity", type=float, metavar="D",
                    help="focus disparity (1/scene-unit)")
    g2.add_argument("--focus-pixel", type=_parse_pixel, metavar="X,Y", help="focus on pixel X,Y")
    g2.add_argument("--disp-focus", type=_FRACTION, metavar="D",
                    help="the paper's focus: the normalised disparity in focus, in [0, 1], "
                         "a number or a fraction a/b such as 207/255 (with --K)")
    lens = f.add_argument_group(
        "camera", "By default focus and aperture come from the input's header (a render made "
        "with the MPIB extension enabled, or an mpib render). Each option below replaces "
        "that one field; without a header, give --blur-parameter, or --fstop and --focal-mm.")
    lens.add_argument("--blur-parameter", type=float,
                      help="A, pixels per unit disparity (not with the lens options)")
    lens.add_argument("--fstop", type=float, help="f-number N")
    # checked by camera_header.resolve, whose messages name the option and the bound
    lens.add_argument("--focal-mm", type=float, help="focal length in mm")
    lens.add_argument("--sensor-mm", type=float,
                      help="sensor width in mm (default: the header's, else 36)")
    lens.add_argument("--sensor-height-mm", type=float,
                      help="sensor height in mm, used by VERTICAL fit (default: the header's, else 24)")
    lens.add_argument("--sensor-fit", type=str.upper, choices=list(SENSOR_FITS),
                      help="how the sensor maps to the image, as Blender: AUTO puts the sensor "
                           "width across the larger image side (default: the header's, else AUTO)")
    lens.add_argument("--blades", type=int, metavar="N",
                      help="aperture blades: 0 (a disk) or 3 to 16, as Blender's Camera > "
                           "Aperture > Blades (default: the header's, else 0)")
    lens.add_argument("--rotation", type=float, metavar="DEG",
                      help="the blades' rotation in degrees, counter-clockwise on screen, as "
                           "Blender's Rotation (default: the header's, else 0)")
    lens.add_argument("--ratio", type=float,
                      help="anamorphic ratio, as Blender's Ratio: the aperture's width is "
                           "divided by it (1.5: oval bokeh 1.5 times taller than wide); "
                           "finite and > 0 (default: the header's, else 1)")
    lens.add_argument("--scene-unit-m", type=float,
                      help="metres per depth unit for the lens (default: the header's, else 1; "
                           "Blender renders need 1 whatever their Unit Scale)")
    f.add_argument("--layered", action="store_true",
                   help="the input's view layers are depth groups (each with Combined and "
                        "Depth; ordered far to near by median depth); view layers named "
                        "mpib_group_<k> are read so without this option")
    f.add_argument("--preset", choices=list(PRESETS), default="default")
    f.add_argument("--far-limit", type=_POSITIVE, default=1e9,
                   help="depth (scene units) at or beyond which a pixel is infinitely far "
                        "(default 1e9; Cycles writes 1e10 for the sky)")
    f.add_argument("--view-layer", metavar="NAME",
                   help="the Blender view layer to refocus, when the EXR holds several")
    f.add_argument("--no-preview", action="store_true", help="do not write the PNG preview")
    f.add_argument("--pixel-model", choices=["auto", "continuous", "texel"], default="auto",
                   help="how the colour samples the scene, which sets the blur kernel: "
                        "continuous (a render of geometry, a photograph), texel (this "
                        "project's card scenes, nearest-texel textures); auto (default): "
                        "texel for an mpib card-scene render, else continuous")
    f.add_argument("--mpi-cache", metavar="DIR",
                   help="keep the MPI in DIR and reuse it when the input pixels, preset, far "
                        "limit, background and aperture are unchanged (a new focus then only "
                        "re-composites; the output is the same as without the cache)")
    f.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_memory_option(f)
    f.set_defaults(func=cmd_refocus)

    ds = sub.add_parser("dataset", help="many generated scenes with their ray-traced references",
                        description="Build a dataset of generated card scenes and their renders "
                                    "(one folder per seed, written atomically; a rerun resumes).",
                        formatter_class=_TableFormatter, epilog=_DATASET_EPILOG)
    ds.add_argument("--out", required=True, help="dataset folder")
    ds.add_argument("--count", type=_POSITIVE_INT, required=True, help="number of samples")
    ds.add_argument("--start", type=_COUNT, default=0, help="first seed (default 0)")
    ds.add_argument("--family", choices=["constant", "varying", "mixed"], default="mixed")
    ds.add_argument("--size", type=_parse_size, default=(256, 256), help="WxH (default 256x256)")
    ds.add_argument("--spp", type=_POSITIVE_INT, default=1024, help="ray tracer samples per pixel")
    ds.add_argument("--workers", type=_COUNT, default=0, help="local worker processes (0: in process)")
    ds.add_argument("--scheduler", default=None,
                    help="Dask scheduler address (tcp://host:8786), or 'local' for a LocalCluster")
    _add_memory_option(ds)
    ds.set_defaults(func=cmd_dataset)

    k = sub.add_parser("backends", help="which compute backends run here",
                       description="Probe numpy, Dr.Jit LLVM and Dr.Jit CUDA (in subprocesses).",
                       formatter_class=_TableFormatter, epilog=_BACKENDS_EPILOG)
    k.set_defaults(func=cmd_backends)
    return p


#: Options whose value may start with "-" (a pixel outside the image, e.g. -1,10):
#: argparse would take it for an option.
_NEGATIVE_VALUE_OPTIONS = ("--focus-pixel",)


def _join_option_values(argv: list[str]) -> list[str]:
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a in _NEGATIVE_VALUE_OPTIONS and i + 1 < len(argv) and argv[i + 1].startswith("-") \
                and argv[i + 1][1:2].isdigit():
            out.append(f"{a}={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def _named(exc: BaseException) -> bool:
    """Whether ``exc`` is a refusal whose message names the file, field or option: the
    project's own error classes (every one a ``ValueError`` defined in this package),
    :class:`CliError`, and file-system errors (``OSError`` names the path)."""
    kind = type(exc)
    return isinstance(exc, (CliError, OSError)) or (
        isinstance(exc, ValueError) and kind.__module__.startswith("mpib_validate."))


#: Commands whose outputs appear together or not at all (``io.atomic.together``);
#: ``dataset``, ``bench`` and ``demo`` write many results, each atomically, and keep
#: the finished ones when a later one fails.
_TOGETHER = ("generate", "render", "refocus", "compare")


def main(argv: list[str] | None = None) -> int:
    import contextlib

    from mpib_validate.runtime.io.atomic import together
    from mpib_validate.executor import Terminated, raise_on_sigterm, restore_sigterm

    argv = _join_option_values(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(argv)
    previous = raise_on_sigterm()
    try:
        with together() if args.command in _TOGETHER else contextlib.nullcontext():
            return args.func(args)
    except MemoryError:
        print(f"mpib {args.command}: error: out of memory; give smaller inputs or fewer "
              f"samples (the estimate before the work was under --max-memory-gb)", file=sys.stderr)
        return 2
    except (Terminated, KeyboardInterrupt) as exc:
        what = "terminated" if isinstance(exc, Terminated) else "interrupted"
        note = "; nothing was written" if args.command in _TOGETHER else ""
        print(f"mpib {args.command}: {what}{note}", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
    except Exception as exc:  # noqa: BLE001 - every error is one line, never a traceback
        text = " ".join(str(exc).split()) or type(exc).__name__
        if _named(exc):
            print(f"mpib {args.command}: error: {text}", file=sys.stderr)
            return 2
        if os.environ.get("MPIB_TRACEBACK"):
            raise
        print(f"mpib {args.command}: internal error: {type(exc).__name__}: {text[:300]} (a "
              f"bug: please report it with the command line; MPIB_TRACEBACK=1 shows where)",
              file=sys.stderr)
        return 70
    finally:
        restore_sigterm(previous)


if __name__ == "__main__":
    sys.exit(main())
