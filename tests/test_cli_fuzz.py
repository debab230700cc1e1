"""Property-based test of the command line (Hypothesis): `refocus`, `render` and
`generate` driven in this process with random malformed inputs: EXR channel sets,
NaN/Inf/negative values, sizes, option values and scene.json mutations.

Whatever the input, the command either succeeds (exit 0) with finite outputs, or
refuses it (exit 2) with one line naming a file or an option; never a traceback, never
a changed input, never a partial output. Small images and bounded example counts keep
the default run well under a minute.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import sys
import tempfile
from pathlib import Path

import numpy as np
from clirun import run
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from mpib_validate.runtime.io.exr import ExrError, read_exr, write_exr
from mpib_validate.cards.generate import GeneratorSettings, generate
from mpib_validate.cards.scene import save_scene

# MPIB_FUZZ_EXAMPLES raises the counts for a deeper run (the default keeps the suite fast)
EXAMPLES = int(os.environ.get("MPIB_FUZZ_EXAMPLES", "30"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
# a limit that lets every small job through and refuses the large ones the strategies
# can ask for (a 1e9 px wide camera, a billion samples, a huge blur)
MEMORY = ["--max-memory-gb", "2"]


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _check(rc: int, out: str, err: str, command: str, names, outputs, before: dict,
           folder: Path, replaced: Path | None = None) -> None:
    """The property: see the module docstring. Files under ``replaced`` (relative to
    ``folder``) may change when the command succeeds (generate --force)."""
    assert "Traceback" not in err, err
    assert rc in (0, 2), (rc, err)
    after = _snapshot(folder)
    for rel, data in before.items():  # no input changed or removed
        if rc == 0 and replaced is not None and rel.is_relative_to(replaced):
            continue
        assert after.get(rel) == data, f"input {rel} changed"
    new = sorted(str(p) for p in set(after) - set(before))
    if rc == 0:
        for o in outputs:
            assert o.exists(), (o, out, err)
            if o.suffix == ".exr":
                for name, ch in read_exr(o).channels.items():
                    assert np.isfinite(ch).all(), f"{o}: channel {name} is not finite"
        return
    lines = [l for l in err.splitlines() if l.strip() and ": notice: " not in l]
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith(f"mpib {command}: error: "), line
    assert "--" in line or any(n in line for n in names), line  # names an option or a file
    assert new == [], f"partial output {new} after: {line}"


# -- refocus ---------------------------------------------------------------------------

colour_layouts = st.sampled_from(["RGB", "RGBA", "AllInFocus", "ViewLayer", "two-layers",
                                  "G-only", "none"])
depth_layouts = st.sampled_from(["Depth.Z", "Z", "ViewLayer.Depth.Z", "separate", "none",
                                 "separate-wrong-size"])
def mostly(good, bad):
    """A good value seven times in eight (so that the deep code runs too), else a
    malformed one."""
    return st.integers(0, 7).flatmap(
        lambda i: st.sampled_from(list(bad) if i == 0 else list(good)))


BAD_NUMBERS = ["0", "-1", "nan", "inf", "-inf", "abc", "", "1e308"]
bad_values = mostly([None], [np.nan, np.inf, -np.inf, -0.5, 1e30])
depth_kinds = mostly(["ok", "constant"], ["zero", "negative", "nan", "inf", "far", "tiny",
                                          "colour-like"])


def _depth(kind: str, rng, shape):
    d = rng.uniform(1, 10, shape)
    d[: shape[0] // 2] = 1.5
    if kind == "zero":
        d.flat[rng.integers(d.size)] = 0
    elif kind == "negative":
        d.flat[rng.integers(d.size)] = -2
    elif kind == "nan":
        d.flat[rng.integers(d.size)] = np.nan
    elif kind == "inf":
        d.flat[rng.integers(d.size)] = np.inf
    elif kind == "far":
        d[:] = 1e10
    elif kind == "tiny":
        d.flat[rng.integers(d.size)] = 1e-6
    elif kind == "colour-like":
        d = rng.uniform(0.001, 1.0, shape)
    elif kind == "constant":
        d[:] = 3.0
    return d.astype(np.float32)


@st.composite
def refocus_cases(draw):
    h, w = draw(st.integers(1, 10)), draw(st.integers(1, 12))
    seed = draw(st.integers(0, 2 ** 16))
    options = []
    aperture = draw(mostly(["A", "lens"], ["both", "none", "fstop-only"]))
    if aperture in ("A", "both"):
        options += ["--blur-parameter", draw(mostly(["2", "25", "1e-3"], BAD_NUMBERS + ["1e5"]))]
    if aperture in ("lens", "both", "fstop-only"):
        options += ["--fstop", draw(mostly(["2", "0.5", "16"], BAD_NUMBERS + ["0.001"]))]
    if aperture in ("lens", "both"):
        options += ["--focal-mm", draw(mostly(["50", "200"], BAD_NUMBERS))]
    for flag, good in (("--scene-unit-m", ["1", "0.01"]), ("--far-limit", ["1e9", "5"]),
                       ("--sensor-mm", ["36", "24"])):
        if draw(st.integers(0, 3)) == 0:
            options += [flag, draw(mostly(good, BAD_NUMBERS))]
    focus = draw(mostly(["depth", "disparity", "pixel"], ["none"]))
    if focus == "pixel":
        options += ["--focus-pixel", draw(mostly(["0,0", "3,2"], ["-1,10", "100,1", "1", "a,b"]))]
    elif focus != "none":
        options += [f"--focus-{focus}", draw(mostly(["2.5", "0.3"], BAD_NUMBERS))]
    options += ["--preset", draw(st.sampled_from(["draft", "default", "best"]))]
    if draw(st.integers(0, 3)) == 0:
        options += ["--view-layer", draw(st.sampled_from(["ViewLayer", "Other", "x"]))]
    if draw(st.booleans()):
        options.append("--no-preview")
    return dict(h=h, w=w, seed=seed,
                colour=draw(mostly(["RGB", "RGBA", "AllInFocus", "ViewLayer"],
                                   ["two-layers", "G-only", "none"])),
                depth=draw(mostly(["Depth.Z", "Z", "ViewLayer.Depth.Z", "separate"],
                                  ["none", "separate-wrong-size"])),
                bad=draw(bad_values), depth_kind=draw(depth_kinds), options=options,
                output=draw(mostly(["out.exr", "sub/out.exr"],
                                   ["in.exr", "out.png", "dir-png", "depth.exr"])))


def _write_refocus_inputs(folder: Path, case) -> list[str]:
    rng = np.random.default_rng(case["seed"])
    h, w = case["h"], case["w"]
    rgba = rng.uniform(0, 2, (h, w, 4)).astype(np.float32)
    rgba[..., 3] = 1
    if case["bad"] is not None:
        rgba[rng.integers(h), rng.integers(w), rng.integers(3)] = case["bad"]
    depth = _depth(case["depth_kind"], rng, (h, w))
    ch = {}
    layout = case["colour"]
    if layout in ("RGB", "RGBA"):
        ch.update({c: rgba[..., i] for i, c in enumerate(layout)})
    elif layout == "AllInFocus":
        ch.update({f"AllInFocus.{c}": rgba[..., i] for i, c in enumerate("RGBA")})
    elif layout in ("ViewLayer", "two-layers"):
        ch.update({f"ViewLayer.Combined.{c}": rgba[..., i] for i, c in enumerate("RGBA")})
        if layout == "two-layers":
            ch.update({f"Other.Combined.{c}": rgba[..., i] for i, c in enumerate("RGB")})
            ch["Other.Depth.Z"] = depth
    elif layout == "G-only":
        ch["G"] = rgba[..., 1]
    if case["depth"] in ("Depth.Z", "Z", "ViewLayer.Depth.Z"):
        ch[case["depth"]] = depth
    if not ch:
        ch["Y"] = rgba[..., 0]
    write_exr(folder / "in.exr", {k: np.ascontiguousarray(v) for k, v in ch.items()})
    extra = []
    if case["depth"].startswith("separate"):
        d = depth if case["depth"] == "separate" else np.ones((h + 1, w), np.float32)
        write_exr(folder / "depth.exr", {"Z": d})
        extra = ["--depth", str(folder / "depth.exr")]
    if case["output"] == "dir-png":
        (folder / "res.png").mkdir()
    return extra


@FUZZ
@given(refocus_cases())
def test_refocus_never_crashes_or_corrupts(case):
    folder = Path(tempfile.mkdtemp(prefix="mpib-fuzz-"))
    try:
        extra = _write_refocus_inputs(folder, case)
        out = folder / ("res.exr" if case["output"] == "dir-png" else case["output"])
        outputs = [out] + ([] if "--no-preview" in case["options"] else [out.with_suffix(".png")])
        before = _snapshot(folder)
        rc, stdout, err = run("refocus", folder / "in.exr", "-o", out, *extra, *case["options"],
                              *MEMORY, "-q")
        _check(rc, stdout, err, "refocus", ["in.exr", "depth.exr", out.name, "res.png"],
               outputs, before, folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- render ----------------------------------------------------------------------------

_SCENE = {}


def _base_scene() -> Path:
    if "dir" not in _SCENE:
        d = Path(tempfile.mkdtemp(prefix="mpib-fuzz-scene-")) / "s"
        save_scene(generate(4, "varying", settings=GeneratorSettings(width=12, height=10)), d)
        _SCENE["dir"] = d
    return _SCENE["dir"]


json_values = st.sampled_from([None, 0, -3, 1, 7, 2.5, -0.5, 1e9, 10 ** 9, "24", "", "cards/x.exr",
                               [1, 2], [1], {}, {"a": 0, "b": 0, "c": 2}, True, float("nan")])
card_fields = st.sampled_from(["name", "texture", "size", "offset", "disparity", "plane", "ofset",
                               "plane.c", "plane.a"])
camera_fields = st.sampled_from(["width", "height", "blur_parameter", "focus_disparity",
                                 "focal_length_px", "widht"])


@st.composite
def scene_mutations(draw):
    muts = []
    for _ in range(draw(st.sampled_from([0, 0, 1, 1, 2]))):
        where = draw(st.sampled_from(["camera", "card", "top", "delete-card-field", "texture-file"]))
        if where == "camera":
            muts.append(("camera", draw(camera_fields), draw(json_values)))
        elif where == "card":
            muts.append(("card", draw(st.integers(0, 3)), draw(card_fields), draw(json_values)))
        elif where == "top":
            muts.append(("top", draw(st.sampled_from(["format", "version", "metadata", "cards",
                                                     "camera", "extra"])), draw(json_values)))
        elif where == "delete-card-field":
            muts.append(("delete", draw(st.integers(0, 3)),
                         draw(st.sampled_from(["name", "texture", "plane", "disparity"]))))
        else:
            muts.append(("texture-file", draw(st.integers(0, 3)),
                         draw(st.sampled_from(["nan", "negative", "alpha", "garbage", "empty"]))))
    return muts


def _apply(doc: dict, d: Path, muts) -> None:
    for m in muts:
        cards = doc.get("cards") if isinstance(doc.get("cards"), list) else []
        if m[0] == "camera" and isinstance(doc.get("camera"), dict):
            doc["camera"][m[1]] = m[2]
        elif m[0] == "card" and cards and isinstance(cards[m[1] % len(cards)], dict):
            card = cards[m[1] % len(cards)]
            key = m[2]
            if key.startswith("plane.") and isinstance(card.get("plane"), dict):
                card["plane"][key[6:]] = m[3]
            else:
                card[key] = m[3]
        elif m[0] == "top":
            doc[m[1]] = m[2]
        elif m[0] == "delete" and cards and isinstance(cards[m[1] % len(cards)], dict):
            cards[m[1] % len(cards)].pop(m[2], None)
        elif m[0] == "texture-file" and cards and isinstance(cards[m[1] % len(cards)], dict):
            tex = cards[m[1] % len(cards)].get("texture")
            if not isinstance(tex, str) or not (d / tex).is_file():
                continue
            path = d / tex
            if m[2] in ("garbage", "empty"):
                path.write_bytes(b"" if m[2] == "empty" else b"not an exr" * 10)
                continue
            try:
                img = read_exr(path)
            except ExrError:  # already garbage
                continue
            ch = {k: v.astype(np.float32).copy() for k, v in img.channels.items()}
            key = {"nan": "R", "negative": "G", "alpha": "A"}[m[2]]
            if key in ch:
                ch[key].flat[0] = {"nan": np.nan, "negative": -1.0, "alpha": 1.5}[m[2]]
            write_exr(path, ch)


@st.composite
def render_cases(draw):
    options = []
    if draw(st.integers(0, 3)) == 0:
        options += ["--aperture", "grid", "--grid-side",
                    draw(mostly(["1", "3"], ["0", "100000", "-2", "x"]))]
    options += ["--spp", draw(mostly(["1", "2", "4"], ["0", "1000000000", "-1", "2.5"]))]
    for flag in ("--focus-disparity", "--blur-parameter"):
        if draw(st.integers(0, 3)) == 0:
            options += [flag, draw(mostly(["0.3", "5"], ["0", "-1", "nan", "inf", "1e9"]))]
    for flag in ("--pixel", "--lookup", "--order"):
        if draw(st.booleans()):
            options += [flag, draw(st.sampled_from({"--pixel": ["box", "centre"],
                                                    "--lookup": ["nearest", "bilinear"],
                                                    "--order": ["depth", "fixed"]}[flag]))]
    if draw(st.booleans()):
        options.append("--no-preview")
    return dict(muts=draw(scene_mutations()), options=options,
                output=draw(mostly(["r.exr", "deep/er/r.exr"],
                                   ["s/cards/background.exr", "s/scene.json", "r.png", "dir-png"])))


@FUZZ
@given(render_cases())
def test_render_never_crashes_or_corrupts(case):
    folder = Path(tempfile.mkdtemp(prefix="mpib-fuzz-"))
    try:
        d = folder / "s"
        shutil.copytree(_base_scene(), d)
        doc = json.loads((d / "scene.json").read_text())
        _apply(doc, d, case["muts"])
        (d / "scene.json").write_text(json.dumps(doc))
        if case["output"] == "dir-png":
            (folder / "r2.png").mkdir()
            out = folder / "r2.exr"
        else:
            out = folder / case["output"]
        outputs = [out] + ([] if "--no-preview" in case["options"] else [out.with_suffix(".png")])
        before = _snapshot(folder)
        rc, stdout, err = run("render", d, "-o", out, *case["options"], *MEMORY, "-q",
                              "--backend", "numpy")
        _check(rc, stdout, err, "render", ["scene.json", ".exr", out.name, "r2.png"], outputs,
               before, folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- generate --------------------------------------------------------------------------


@st.composite
def generate_cases(draw):
    size = draw(mostly(["16x12", "40x8", "12x2", "1x1", "2x3"],
                       ["0x5", "5x-1", "abc", "8", "100000000x100000000"]))
    args = ["--size", size, "--family", draw(mostly(["constant", "varying"], ["tilted"]))]
    if draw(st.booleans()):
        args += ["--case", draw(st.sampled_from(["thin", "hair", "soft", "hdr", "near-focus",
                                                 "grazing", "large-blur", "focus-fg", "focus-bg",
                                                 "wobbly"]))]
    args += ["--seed", draw(mostly(["0", "3", "99999"], ["-1", "1.5"]))]
    if draw(st.booleans()):
        args.append("--force")
    return dict(args=args, out=draw(mostly(["new", "nested/new"], ["existing-scene", "file"])))


@FUZZ
@given(generate_cases())
def test_generate_never_crashes_or_corrupts(case):
    folder = Path(tempfile.mkdtemp(prefix="mpib-fuzz-"))
    try:
        out = folder / case["out"]
        if case["out"] == "existing-scene":
            shutil.copytree(_base_scene(), out)
        elif case["out"] == "file":
            out.write_text("not a folder")
        before = _snapshot(folder)
        rc, stdout, err = run("generate", *case["args"], "--out", out, *MEMORY)
        _check(rc, stdout, err, "generate", [out.name], [out / "scene.json"], before, folder,
               replaced=out.relative_to(folder))
        if rc == 0:  # what was written loads back
            from mpib_validate.cards.scene import load_scene

            load_scene(out)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- hostile files: special files, hostile headers, NaN side inputs, interrupted writes --
#
# Each case is one `mpib refocus` (or `compare`) on a small picture with one hostile
# element drawn from HOSTILE. Besides the property above: no special file (FIFO,
# device) is replaced, nothing hangs (a SIGALRM after HANG_S seconds fails the case),
# a run cut short by a full disk (a file-size limit at a drawn byte count) or a SIGTERM
# (after a drawn delay) leaves no file at all, and an image-space A taken from a header
# belongs to an image of the input's size.

HOSTILE = ["fifo-input", "fifo-depth", "fifo-background", "fifo-mask", "chardev-input",
           "fifo-output", "fifo-preview", "chardev-output", "fifo-exr",
           "layered-nan", "layered-world-nan", "background-nan",
           "header-deep", "header-note-deep", "header-huge-number", "header-other-size",
           "full-disk", "sigterm", "cache-damaged", "none"]
HANG_S = 20
CHARDEV = os.geteuid() == 0  # only root may make a device node (1, 3 as /dev/null)


@st.composite
def hostile_cases(draw):
    kind = draw(st.sampled_from(HOSTILE))
    if kind.startswith("chardev") and not CHARDEV:
        kind = kind.replace("chardev", "fifo")
    return dict(kind=kind, h=draw(st.integers(2, 10)), w=draw(st.integers(2, 12)),
                seed=draw(st.integers(0, 2 ** 16)), value=draw(st.sampled_from(
                    [np.nan, np.inf, -np.inf])), group=draw(st.integers(0, 1)),
                limit=draw(st.integers(0, 6000)), delay=draw(st.floats(0.0, 0.03)),
                preview=draw(st.booleans()), photo=draw(st.booleans()),
                damage=draw(st.sampled_from(["truncate", "flip", "json", "nan"])))


def _special(path: Path, kind: str) -> None:
    if kind.startswith("chardev"):
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    else:
        os.mkfifo(path)


def _kinds(folder: Path) -> dict:
    """Every special file (not regular, not a folder) and its type."""
    return {p.relative_to(folder): stat.S_IFMT(os.lstat(p).st_mode)
            for p in folder.rglob("*") if not p.is_symlink()
            and not stat.S_ISREG(os.lstat(p).st_mode) and not p.is_dir()}


def _write_hostile_inputs(folder: Path, case) -> tuple[list, list]:
    """The input files of ``case`` and the command line; returns ``(args, outputs)``."""
    rng = np.random.default_rng(case["seed"])
    h, w, kind = case["h"], case["w"], case["kind"]
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = rng.uniform(0.05, 1.0, (h, w, 3))
    depth = np.full((h, w), 4.0, np.float32)
    depth[: h // 2, : w // 2] = 1.5
    attributes = {}
    header = {"deep": '{"camera": ' + "[" * 5000 + "]" * 5000 + "}",
              "huge": '{"camera": {"blur_parameter": 1%s, "focus_disparity": 0.4}}' % ("0" * 400),
              "other": json.dumps({"camera": {"width": w * 40, "height": h * 40,
                                              "blur_parameter": 150.0, "focus_disparity": 0.4}})}
    if kind == "header-deep":
        attributes["mpib"] = header["deep"]
    elif kind == "header-note-deep":
        attributes["Note"] = "mpib:" + header["deep"]
    elif kind == "header-huge-number":
        attributes["mpib"] = header["huge"]
    elif kind == "header-other-size":
        attributes["mpib"] = header["other"]
    if kind.startswith("layered"):
        ch = {}
        for k, z in enumerate((8.0, 2.0)):
            layer = rgba.copy()
            if k == 1:
                layer[h // 2:] = 0
            if kind == "layered-nan" and case["group"] == k:
                layer[rng.integers(h), rng.integers(w), rng.integers(3)] = case["value"]
            ch.update({f"mpib_group_{k}.Combined.{c}": layer[..., i] for i, c in enumerate("RGBA")})
            ch[f"mpib_group_{k}.Depth.Z"] = np.full((h, w), z, np.float32)
        if kind == "layered-world-nan":
            env = np.full((h, w), 0.1, np.float32)
            env.flat[rng.integers(env.size)] = case["value"]
            ch.update({f"mpib_group_0.Environment.{c}": env for c in "RGB"})
        write_exr(folder / "in.exr", {k: np.ascontiguousarray(v) for k, v in ch.items()},
                  attributes=attributes)
    else:
        write_exr(folder / "in.exr", {**{c: np.ascontiguousarray(rgba[..., i])
                                         for i, c in enumerate("RGBA")}, "Depth.Z": depth},
                  attributes=attributes)
    lens = [] if kind.startswith("header") else ["--blur-parameter", "6", "--focus-depth", "2"]
    out = folder / "out.exr"
    args = ["refocus", folder / "in.exr", "-o", out, *lens, "-q"]
    if kind == "background-nan":
        bg = rgba.copy()
        bg[rng.integers(h), rng.integers(w), rng.integers(3)] = case["value"]
        write_exr(folder / "bg.exr", {**{c: np.ascontiguousarray(bg[..., i])
                                         for i, c in enumerate("RGBA")},
                                      "Depth.Z": np.full((h, w), 4.0, np.float32)})
        args += ["--background", folder / "bg.exr"]
    if kind in ("fifo-input", "chardev-input"):
        (folder / "in.exr").unlink()
        _special(folder / "in.exr", kind)
    elif kind in ("fifo-depth", "fifo-background"):
        _special(folder / "x.exr", kind)
        args += [f"--{kind[5:]}", folder / "x.exr"]
    elif kind == "fifo-mask":
        _special(folder / "m.png", kind)
        args = ["compare", folder / "in.exr", folder / "in.exr", "--mask", folder / "m.png"]
    elif kind in ("fifo-output", "chardev-output"):
        _special(out, kind)
    elif kind == "fifo-preview":
        _special(out.with_suffix(".png"), kind)
    elif kind == "fifo-exr":  # a photograph's --exr beside its JPEG
        from PIL import Image

        Image.fromarray((rgba[..., :3] * 255).astype(np.uint8)).save(folder / "p.png")
        Image.fromarray(np.full((h, w), 100, np.uint8)).save(folder / "d.png")
        _special(folder / "x.exr", kind)
        out = folder / "out.jpg"
        args = ["refocus", folder / "p.png", "--disparity", folder / "d.png", "--K", "5",
                "--disp-focus", "0.5", "-o", out, "--exr", folder / "x.exr", "-q"]
    if kind == "cache-damaged":
        args += ["--mpi-cache", folder / "cache"]
    if not case["preview"] and args[0] == "refocus" and kind != "fifo-preview":
        args.append("--no-preview")
    outputs = [] if args[0] == "compare" else [out] + (
        [out.with_suffix(".png")] if "--no-preview" not in args and out.suffix == ".exr" else [])
    return args, outputs


def _damage_cache(folder: Path, case) -> None:
    """Damage the entry an earlier run left in ``folder / "cache"``."""
    for p in sorted((folder / "cache").glob("*")):
        data = bytearray(p.read_bytes())
        if case["damage"] == "truncate":
            data = data[: len(data) // 2]
        elif case["damage"] == "flip" and data:
            data[case["seed"] % len(data)] ^= 0xFF
        elif case["damage"] == "json" and p.suffix == ".json":
            data = bytearray(b'{"a": ' * 3000 + b"1" + b"}" * 3000)
        elif case["damage"] == "nan" and p.suffix == ".npz":
            from mpib_validate.runtime.layers.mpi import load_mpi, save_mpi

            try:
                mpi = load_mpi(p)
            except Exception:  # noqa: BLE001 - already unreadable
                continue
            for layer in mpi.layers:
                if layer.rgba is not None and layer.rgba.size:
                    layer.rgba.flat[0] = np.nan
                    break
            save_mpi(mpi, p)
            continue
        p.write_bytes(bytes(data))


def _in_a_child(args, limit: int | None, delay: float | None) -> tuple[int, str, str]:
    """``mpib ARGS`` in a forked child (the modules already imported) under a file-size
    limit of ``limit`` bytes (a full disk: writes past it fail) or a SIGTERM after
    ``delay`` seconds; ``(status, stdout, stderr)``."""
    import resource
    import signal
    import time

    out_fd, out_path = tempfile.mkstemp()
    err_fd, err_path = tempfile.mkstemp()
    pid = os.fork()
    if pid == 0:  # the child: never returns to pytest
        rc = 99
        try:
            # a SIGTERM after the command's own handler is gone (it ended) is ignored
            signal.signal(signal.SIGTERM, lambda *a: None)
            hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
            if limit is not None:
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
            if delay is not None:
                signal.signal(signal.SIGALRM, lambda *a: os.kill(os.getpid(), signal.SIGTERM))
                signal.setitimer(signal.ITIMER_REAL, max(delay, 1e-3))
            rc, out, err = run(*args)  # a traceback comes back as status -1 in err
            signal.setitimer(signal.ITIMER_REAL, 0)
            resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
            os.write(out_fd, out.encode())
            os.write(err_fd, err.encode())
        finally:
            os._exit(rc & 0xFF)
    os.close(out_fd)
    os.close(err_fd)
    t0 = time.monotonic()
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() - t0 > HANG_S:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise AssertionError(f"hung: {args}")
        time.sleep(0.01)
    rc = os.waitstatus_to_exitcode(status)
    rc = -1 if rc == 255 else rc
    text = Path(out_path).read_text(), Path(err_path).read_text()
    os.unlink(out_path)
    os.unlink(err_path)
    return rc, *text


def _run_with_alarm(args) -> tuple[int, str, str]:
    """``mpib ARGS`` in this process; a hang (a FIFO opened for reading) fails after
    HANG_S seconds."""
    import signal

    def hang(*a):
        raise AssertionError(f"hung: {args}")

    previous = signal.signal(signal.SIGALRM, hang)
    signal.alarm(HANG_S)
    try:
        return run(*args)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _every_kind(test):
    """One explicit example of each kind of hostile file (the drawn ones add more)."""
    for i, kind in enumerate(HOSTILE):
        if kind.startswith("chardev") and not CHARDEV:
            continue
        test = example(dict(kind=kind, h=4, w=5, seed=i, value=np.nan, group=i % 2,
                            limit=100 * i, delay=0.002 * i, preview=True, photo=False,
                            damage=["truncate", "flip", "json", "nan"][i % 4]))(test)
    return test


@settings(FUZZ, max_examples=2 * EXAMPLES)  # twenty kinds of hostile file
@given(hostile_cases())
@_every_kind
def test_hostile_files_never_hang_replace_or_corrupt(case):
    folder = Path(tempfile.mkdtemp(prefix="mpib-fuzz-"))
    try:
        args, outputs = _write_hostile_inputs(folder, case)
        kind = case["kind"]
        if kind == "cache-damaged":  # a first run leaves an entry, which is then damaged
            rc, _, err = run(*args)
            assert rc == 0, err
            for o in outputs:
                o.unlink(missing_ok=True)
            _damage_cache(folder, case)
        specials, before = _kinds(folder), _snapshot(folder)
        if kind == "full-disk":
            rc, out, err = _in_a_child(args, case["limit"], None)
        elif kind == "sigterm":
            rc, out, err = _in_a_child(args, None, case["delay"])
        else:
            rc, out, err = _run_with_alarm(args)
        event(f"{kind}: exit {rc}")  # shown by --hypothesis-show-statistics
        assert _kinds(folder) == specials, f"a special file was replaced: {err}"
        if kind == "sigterm" and rc == 143:  # stopped: nothing written, the line says so
            assert "terminated" in err and "Traceback" not in err, err
            after = _snapshot(folder)
            assert sorted(set(after) - set(before)) == [], "partial output after SIGTERM"
            return
        if kind == "cache-damaged":  # the cache may be rebuilt in place
            before = {k: v for k, v in before.items() if k.parts[0] != "cache"}
            names = ["in.exr", "cache", "out"]
        else:
            names = ["in.exr", "x.exr", "bg.exr", "m.png", "out", "p.png", "d.png"]
        _check(rc, out, err, args[0], names, outputs, before, folder,
               replaced=Path("cache") if kind == "cache-damaged" else None)
        if rc == 0 and args[0] == "refocus" and outputs[0].suffix == ".exr":
            used = json.loads(read_exr(outputs[0]).header["mpib"])["camera"]
            if used.get("from", {}).get("blur_parameter", "").startswith("'"):  # a header's A
                assert (used["width"], used["height"]) == (case["w"], case["h"])
                assert used["blur_parameter"] != 150.0, "another image's A was used"
        if kind == "full-disk" and rc != 0:  # every temporary removed too
            assert not [p for p in folder.rglob(".*tmp-*")], "temporary files left"
    finally:
        shutil.rmtree(folder, ignore_errors=True)
