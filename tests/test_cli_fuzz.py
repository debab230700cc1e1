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
import shutil
import tempfile
from pathlib import Path

import numpy as np
from clirun import run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpib_validate.runtime.io.exr import ExrError, read_exr, write_exr
from mpib_validate.cards.generate import GeneratorSettings, generate
from mpib_validate.cards.scene import save_scene

FUZZ = settings(max_examples=30, deadline=None, database=None,
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
