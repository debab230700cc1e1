"""The ``mpib`` command line: a thin layer over the package's functions.

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
import sys
from pathlib import Path

from . import __version__


class CliError(Exception):
    """A user error: printed as one line, exit status 2."""


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 256x256, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return w, h


def _sample_set(args):
    from . import samples

    if args.aperture == "grid":
        return samples.grid(args.grid_side, pixel=args.pixel)
    return samples.stratified(args.spp, seed=args.seed, pixel=args.pixel)


# --------------------------------------------------------------------------------------


def cmd_generate(args) -> int:
    from .generate import GeneratorSettings, generate
    from .scene import save_scene

    w, h = args.size
    scene = generate(args.seed, args.family, args.case, GeneratorSettings(width=w, height=h))
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
    return scene.with_camera(**changes).validate("command line") if changes else scene


def cmd_render(args) -> int:
    from .atomic import refuse_overwrite
    from .render_io import write_render
    from .scene import load_scene
    from .trace import render

    scene = _apply_camera_overrides(load_scene(args.scene), args)
    src = Path(args.scene)
    json_path = src / "scene.json" if src.is_dir() else src
    refuse_overwrite(args.output, [json_path] + [json_path.parent / "cards" / f"{c.name}.exr"
                                                 for c in scene.cards])
    refuse_overwrite(Path(args.output).with_suffix(".png"), [json_path])
    if args.engine == "cycles":
        from .cycles import render_result

        result = render_result(scene, args.spp, seed=args.seed)
    elif args.engine == "mitsuba":
        import mitsuba_scenes

        result = mitsuba_scenes.render_result(scene, args.spp, seed=args.seed,
                                              variant=args.variant)
    else:
        result = render(scene, _sample_set(args), backend=args.backend, lookup=args.lookup,
                        order=args.order, progress=not args.quiet)
    written = write_render(args.output, result, scene, preview=not args.no_preview)
    m = result.meta
    print(f"rendered {scene.camera.width}x{scene.camera.height}, {len(scene.cards)} cards, "
          f"{m['sample_count']} samples ({m['samples']}) on {m['backend']} in {m['seconds']:.2f} s")
    for p in written:
        print(f"wrote {p}")
    return 0


def cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(Path(args.out), size=args.size, spp=args.spp, backend=args.backend)
    return 0


def cmd_bench(args) -> int:
    from .bench import run_bench
    from .executor import make_executor

    run_bench(Path(args.out), suite=args.suite, quick=not args.full,
              executor=make_executor(args.workers, args.scheduler))
    return 0


def _read_mask(path: str, shape):
    import numpy as np

    from .exr import read_exr

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
    from .metrics import all_metrics
    from .refocus import read_colour

    a = read_colour(args.reference, all_in_focus=False)
    b = read_colour(args.test, all_in_focus=False)
    if a.shape != b.shape:
        raise CliError(f"image sizes differ: '{args.reference}' is {a.shape[1]}x{a.shape[0]}, "
                       f"'{args.test}' is {b.shape[1]}x{b.shape[0]}")
    mask = _read_mask(args.mask, a.shape[:2]) if args.mask else None
    res = all_metrics(a[..., :3], b[..., :3], mask, peak=args.peak, with_flip=not args.no_flip)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        for k, v in res.items():
            print(f"{k:14s} {v:.6g}")
    return 0


def _parse_pixel(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a pixel looks like X,Y (e.g. 120,80), got {text!r}") from None
    return x, y


def _refocus_camera(args, passes):
    """The camera of ``mpib refocus``: the input header's, each field overridden by the
    option that gives it (:func:`mpib_validate.camera_header.resolve`)."""
    from .camera_header import resolve
    from .refocus import focus_from_pixel

    H, W = passes.depth.shape
    given = {"lens_mm": args.focal_mm, "sensor_width_mm": args.sensor_mm,
             "sensor_height_mm": args.sensor_height_mm, "sensor_fit": args.sensor_fit,
             "fstop": args.fstop, "unit_scale": args.scene_unit_m,
             "blur_parameter": args.blur_parameter, "focus_distance": args.focus_depth,
             "focus_disparity": args.focus_disparity}
    labels = {}
    if args.focus_pixel is not None:
        given["focus_disparity"] = focus_from_pixel(passes, *args.focus_pixel, far_limit=args.far_limit)
        labels["focus_disparity"] = "--focus-pixel {},{}".format(*args.focus_pixel)
    return resolve(passes.camera, given, W, H, args.input, labels)


def cmd_refocus(args) -> int:
    from .atomic import refuse_overwrite
    from .refocus import load_layered_passes, load_passes, read_background, refocus, write_result

    inputs = [args.input] + [p for p in (args.depth, args.background) if p]
    refuse_overwrite(args.output, inputs)
    refuse_overwrite(Path(args.output).with_suffix(".png"), inputs)
    if args.layered and (args.depth or args.background):
        raise CliError("--layered takes colour and depth from the input's view layers: "
                       "drop --depth and --background")
    # layered input: with --layered, or view layers named mpib_group_<k> (automatic)
    passes = None if args.depth else load_layered_passes(
        args.input, True if args.layered else None, args.far_limit)
    if passes is not None and args.background:
        raise CliError(f"'{args.input}' is a layered render (mpib_group_ view layers): the "
                       f"groups hold what lies behind the foreground; drop --background")
    if passes is None:
        passes = load_passes(args.input, args.depth)
    H, W = passes.depth.shape
    used = _refocus_camera(args, passes)
    A, d_f = used.camera.blur_parameter, used.camera.focus_disparity
    background = read_background(args.background, (H, W)) if args.background else None
    result = refocus(passes, A, d_f, args.preset, args.far_limit, background=background)
    result.info["camera"] = used.header()  # which camera fields were used, and from where
    written = write_result(args.output, result, preview=not args.no_preview)
    i = result.info
    layered = f", {i['groups']} depth groups" if i["groups"] > 1 else ""
    print(f"refocused {W}x{H} ({args.preset}{layered}): {i['planes']} planes, largest blur radius "
          f"{i['largest_radius_px']:.1f} px, fill {100 * i['fill_fraction']:.1f} % of pixels, "
          f"edge pixels {100 * i['edge_fraction']:.1f} %, A = {A:.3f} px, d_f = {d_f:.5g}, "
          f"{i['seconds']:.2f} s")
    for p in written:
        print(f"wrote {p}")
    return 0


def cmd_dataset(args) -> int:
    import time

    from .dataset import build_dataset
    from .executor import make_executor

    ex = make_executor(args.workers, args.scheduler)
    t0 = time.perf_counter()
    summary = build_dataset(args.out, args.count, args.family, args.size, args.spp, args.start, ex)
    print(f"dataset {args.out}: {summary['count']} complete samples; built {summary['built']}, "
          f"skipped {summary['skipped']} already done ({ex.kind}, {time.perf_counter() - t0:.1f} s)")
    return 0


def cmd_backends(args) -> int:
    from . import backend

    report = {}
    for name in ("numpy", "llvm", "cuda"):
        be = backend.resolve(name)
        report[name] = {"runs_as": be.name, "notice": be.notice, "llvm_library": be.llvm_library}
    print(json.dumps(report, indent=2))
    return 0


# --------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    from .camera import SENSOR_FITS
    from .generate import FAMILIES, HARD_CASES
    from .presets import PRESETS

    p = argparse.ArgumentParser(prog="mpib", description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"mpib {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    g = sub.add_parser("generate", help="make a seeded random card scene",
                       description="Write a random card scene (scene.json + cards/*.exr). "
                                   "The same seed gives the same files, byte for byte.")
    g.add_argument("--seed", type=int, default=0, help="non-negative integer (default 0)")
    g.add_argument("--family", choices=FAMILIES, default="constant",
                   help="constant: fronto-parallel cards; varying: tilted planes")
    g.add_argument("--case", choices=HARD_CASES, default=None, help="force one named hard case")
    g.add_argument("--size", type=_parse_size, default=(256, 256), help="WxH (default 256x256)")
    g.add_argument("--out", required=True, help="output scene directory")
    g.set_defaults(func=cmd_generate)

    r = sub.add_parser("render", help="render a scene to EXR + PNG",
                       description="Render a card scene. --engine trace is the paper's "
                                   "image-space thin-lens ray tracer (Eq. 15).")
    r.add_argument("scene", help="scene directory or scene.json")
    r.add_argument("-o", "--output", required=True, help="output EXR path (a PNG is written beside it)")
    r.add_argument("--engine", default="trace", choices=["trace", "mitsuba", "cycles"])
    r.add_argument("--aperture", choices=["sobol", "grid"], default="sobol",
                   help="sobol: scrambled 4-D Sobol (default); grid: the official square grid")
    r.add_argument("--spp", type=int, default=1024,
                   help="samples per pixel (trace with --aperture sobol, cycles, mitsuba)")
    r.add_argument("--variant", default=None,
                   help="Mitsuba variant (default: probed: cuda_ad_rgb, llvm_ad_rgb, scalar_rgb)")
    r.add_argument("--grid-side", type=int, default=51,
                   help="grid points per side for --aperture grid (51 = 1,957 samples)")
    r.add_argument("--pixel", choices=["box", "centre"], default="box",
                   help="box: average over the pixel area (canonical); centre: pixel centres")
    r.add_argument("--seed", type=int, default=0, help="sample set seed")
    r.add_argument("--backend", choices=["auto", "numpy", "llvm", "cuda"], default="auto")
    r.add_argument("--lookup", choices=["nearest", "bilinear"], default="nearest")
    r.add_argument("--order", choices=["depth", "fixed"], default="depth",
                   help="depth: per-ray depth sort; fixed: the official generator's order")
    r.add_argument("--focus-disparity", type=float, default=None, help="override d_f (1/scene-unit)")
    r.add_argument("--blur-parameter", type=float, default=None, help="override A (px per unit disparity)")
    r.add_argument("--no-preview", action="store_true", help="do not write the PNG preview")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=cmd_render)

    d = sub.add_parser("demo", help="the main job on an embedded default scene",
                       description="Generate the default scenes (both families), render them "
                                   "and write a short report.")
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--size", type=int, default=256, help="image side in pixels (default 256)")
    d.add_argument("--spp", type=int, default=1024, help="ray tracer samples per pixel")
    d.add_argument("--backend", choices=["auto", "numpy", "llvm", "cuda"], default="auto")
    d.set_defaults(func=cmd_demo)

    b = sub.add_parser("bench", help="measure speed and error; write a report",
                       description="Run a benchmark suite and write a report folder "
                                   "(Markdown + JSON).")
    b.add_argument("--out", default="out/bench", help="report folder (default out/bench)")
    from .bench import SUITES

    b.add_argument("--suite", choices=["all", *SUITES], default="all")
    mode = b.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true",
                      help="small scenes, a few minutes on 2 cores (the default)")
    mode.add_argument("--full", action="store_true", help="larger scenes and more samples (slow)")
    b.add_argument("--workers", type=int, default=0,
                   help="spread per-scene work over local processes (times then share the machine)")
    b.add_argument("--scheduler", default=None,
                   help="Dask scheduler address, or 'local' for a LocalCluster")
    b.set_defaults(func=cmd_bench)

    c = sub.add_parser("compare", help="PSNR, SSIM, FLIP (and _ob variants) of two EXRs",
                       description="Compare a test image with a reference: PSNR, SSIM and FLIP "
                                   "on [0, 1]-clipped values and on linear HDR values; with "
                                   "--mask also PSNR_ob and SSIM_ob inside the mask.")
    c.add_argument("reference", help="reference EXR")
    c.add_argument("test", help="test EXR")
    c.add_argument("--mask", help="mask (EXR channel Y/A/R > 0.5, or a PNG > 127)")
    c.add_argument("--peak", type=float, default=None,
                   help="HDR data range (default: the reference's largest value, at least 1)")
    c.add_argument("--no-flip", action="store_true", help="skip FLIP")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.set_defaults(func=cmd_compare)

    f = sub.add_parser("refocus", help="refocus a rendered picture (colour + depth EXR)",
                       description="Refocus a picture from its colour and depth passes with the "
                                   "MPI compositor. Input: a Blender multilayer EXR (Combined + "
                                   "Depth), an mpib render, or colour plus --depth.")
    f.add_argument("input", help="EXR with colour (and depth, unless --depth)")
    f.add_argument("-o", "--output", required=True, help="output EXR (a PNG is written beside it)")
    f.add_argument("--depth", help="separate EXR holding the depth (Z, Depth.Z, Y or R)")
    f.add_argument("--background",
                   help="EXR of the scene rendered without the foreground: used in place of "
                        "the hidden-background fill where its alpha > 0.5")
    g2 = f.add_mutually_exclusive_group()
    g2.add_argument("--focus-depth", type=float, help="focus distance (scene units)")
    g2.add_argument("--focus-disparity", type=float, help="focus disparity (1/scene-unit)")
    g2.add_argument("--focus-pixel", type=_parse_pixel, help="focus on pixel X,Y")
    lens = f.add_argument_group(
        "camera", "By default focus and aperture come from the input's header (a render made "
        "with the MPIB extension enabled, or an mpib render). Each option below replaces "
        "that one field; without a header, give --blur-parameter, or --fstop and --focal-mm.")
    lens.add_argument("--blur-parameter", type=float,
                      help="A, pixels per unit disparity (not with the lens options)")
    lens.add_argument("--fstop", type=float, help="f-number N")
    lens.add_argument("--focal-mm", type=float, help="focal length in mm")
    lens.add_argument("--sensor-mm", type=float,
                      help="sensor width in mm (default: the header's, else 36)")
    lens.add_argument("--sensor-height-mm", type=float,
                      help="sensor height in mm, used by VERTICAL fit (default: the header's, else 24)")
    lens.add_argument("--sensor-fit", type=str.upper, choices=list(SENSOR_FITS),
                      help="how the sensor maps to the image, as Blender: AUTO puts the sensor "
                           "width across the larger image side (default: the header's, else AUTO)")
    lens.add_argument("--scene-unit-m", type=float,
                      help="metres per depth unit for the lens (default: the header's, else 1; "
                           "Blender renders need 1 whatever their Unit Scale)")
    f.add_argument("--layered", action="store_true",
                   help="the input's view layers are depth groups (each with Combined and "
                        "Depth; ordered far to near by median depth); view layers named "
                        "mpib_group_<k> are read so without this option")
    f.add_argument("--preset", choices=list(PRESETS), default="default")
    f.add_argument("--far-limit", type=float, default=1e9,
                   help="depth at or beyond this is infinitely far (Cycles writes 1e10)")
    f.add_argument("--no-preview", action="store_true")
    f.set_defaults(func=cmd_refocus)

    ds = sub.add_parser("dataset", help="many generated scenes with their ray-traced references",
                        description="Build a dataset of generated card scenes and their renders "
                                    "(one folder per seed, written atomically; a rerun resumes).")
    ds.add_argument("--out", required=True, help="dataset folder")
    ds.add_argument("--count", type=int, required=True, help="number of samples")
    ds.add_argument("--start", type=int, default=0, help="first seed (default 0)")
    ds.add_argument("--family", choices=["constant", "varying", "mixed"], default="mixed")
    ds.add_argument("--size", type=_parse_size, default=(256, 256), help="WxH (default 256x256)")
    ds.add_argument("--spp", type=int, default=1024, help="ray tracer samples per pixel")
    ds.add_argument("--workers", type=int, default=0, help="local worker processes (0: in process)")
    ds.add_argument("--scheduler", default=None,
                    help="Dask scheduler address (tcp://host:8786), or 'local' for a LocalCluster")
    ds.set_defaults(func=cmd_dataset)

    k = sub.add_parser("backends", help="which compute backends run here",
                       description="Probe numpy, Dr.Jit LLVM and Dr.Jit CUDA (in subprocesses).")
    k.set_defaults(func=cmd_backends)
    return p


def main(argv: list[str] | None = None) -> int:
    from .atomic import OutputError
    from .exr import ExrError
    from .passes import PassError
    from .scene import SceneError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (CliError, SceneError, ExrError, OutputError, PassError, ValueError) as exc:
        print(f"mpib {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mpib {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
