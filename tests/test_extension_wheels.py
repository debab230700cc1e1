"""The extension's platform zips, checked as Blender would install them.

`make addon` (scripts/build_addon.py) builds one zip per platform of the manifest with
Blender's own ``extension build --split-platforms``; scripts/check_addon.py checks each:
Blender's validate, the manifest's wheels present and nothing else, each wheel's
platform and Python tags (in its name and its WHEEL file), one wheel of each dependency for every Blender release on the
platform (4.2 to 5.0: Python 3.11, 5.1 and later: 3.13), macOS wheels within the macOS
versions those releases run on, and the runtime's wheel holding only the runtime.

Only the Linux zip is installed and run here (tests/test_addon.py); the Windows and
macOS zips are built and checked, not run.
"""

from __future__ import annotations

import io
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
pytest.importorskip("bpy")  # Blender's extension tool lives in the bpy wheel
sys.path.insert(0, str(ROOT / "scripts"))
import check_addon  # noqa: E402

pytestmark = pytest.mark.blender
MANIFEST = tomllib.loads((ROOT / "blender_addon" / "blender_manifest.toml").read_text())
#: The issue's bound on each platform's download.
MAX_ZIP_BYTES = 100e6


@pytest.fixture(scope="module")
def zips(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "build_addon.py"), "--out",
                        str(out)], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    return {z.name.rsplit("-", 1)[1][:-4]: z for z in sorted(out.glob("mpib_refocus-*.zip"))}


def _problems(path):
    return check_addon.check_zip(path)[1]


def _rewrite(src: Path, dst: Path, drop=(), add=None, wheels=None) -> Path:
    """A copy of the zip ``src`` without the members ``drop``, with the members ``add``
    ({name: bytes}), and (if given) the generated manifest's wheel list ``wheels``."""
    add = add or {}
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            if info.filename in drop or info.filename in add:
                continue
            data = zin.read(info.filename)
            if info.filename == "blender_manifest.toml" and wheels is not None:
                text = data.decode()
                head, _, tail = text.partition("[build.generated]")
                lines = [("wheels = [" + ", ".join(f'"{w}"' for w in wheels) + "]")
                         if ln.startswith("wheels = [") else ln for ln in tail.splitlines()]
                data = (head + "[build.generated]" + "\n".join(lines) + "\n").encode()
            zout.writestr(info, data)
        for name, data in add.items():
            zout.writestr(name, data)
    return dst


def _wheels_of(path: Path) -> list[str]:
    with zipfile.ZipFile(path) as zf:
        return sorted(n for n in zf.namelist() if n.endswith(".whl"))


def test_one_zip_per_platform_each_passing_the_checks(zips):
    assert sorted(zips) == sorted(p.replace("-", "_") for p in MANIFEST["platforms"])
    for platform, path in zips.items():
        assert _problems(path) == [], platform
        assert path.stat().st_size <= MAX_ZIP_BYTES, (platform, path.stat().st_size)


def test_each_zip_holds_its_platform_only(zips):
    tags = {"linux_x64": "manylinux", "windows_x64": "win_amd64",
            "macos_arm64": "_arm64", "macos_x64": "_x86_64"}
    for platform, path in zips.items():
        deps = [w for w in _wheels_of(path) if "mpib_validate" not in w]
        assert deps and all(tags[platform] in w for w in deps), (platform, deps)
    # the Intel-Mac zip serves Blender 4.2 and 4.5 only (Python 3.11)
    assert all("cp311" in w for w in _wheels_of(zips["macos_x64"]) if "mpib_validate" not in w)


def test_the_runtime_wheel_holds_the_runtime_only(zips):
    with zipfile.ZipFile(zips["linux_x64"]) as zf:
        (name,) = [n for n in zf.namelist() if "mpib_validate" in n]
        names = zipfile.ZipFile(io.BytesIO(zf.read(name))).namelist()
    code = sorted(n for n in names if n.endswith(".py"))
    assert "mpib_validate/__init__.py" in code and "mpib_validate/runtime/refocus.py" in code
    assert all(n == "mpib_validate/__init__.py" or n.startswith("mpib_validate/runtime/")
               for n in code), code
    # every module the add-on imports from the package is in the wheel
    imported = set()
    for f in (ROOT / "blender_addon").glob("*.py"):
        for line in f.read_text().splitlines():
            words = line.split()
            if len(words) >= 2 and words[0] in ("from", "import") and \
                    words[1].startswith("mpib_validate"):
                imported.add(words[1])
    assert imported
    for mod in imported:
        rel = mod.replace(".", "/")
        assert f"{rel}.py" in names or f"{rel}/__init__.py" in names, mod


# -- the checker refuses what Blender would install wrongly ---------------------------


def test_checker_refuses_a_stray_or_missing_wheel(zips, tmp_path):
    src = zips["macos_x64"]
    win = next(w for w in _wheels_of(zips["windows_x64"]) if "openexr" in w)
    stray = _rewrite(src, tmp_path / src.name, add={win: b"stray"})
    assert any("in the zip but not in the manifest" in p for p in _problems(stray))
    scipy = next(w for w in _wheels_of(src) if "scipy" in w)
    (tmp_path / "b").mkdir()
    gone = _rewrite(src, tmp_path / "b" / src.name, drop={scipy})
    probs = _problems(gone)
    assert any("listed in the manifest but not in the zip" in p for p in probs), probs


def test_checker_refuses_a_wheel_of_another_platform(zips, tmp_path):
    src = zips["macos_x64"]
    win = next(w for w in _wheels_of(zips["windows_x64"]) if "openexr" in w and "cp311" in w)
    listed = ["./" + w for w in _wheels_of(src)] + ["./" + win]
    with zipfile.ZipFile(zips["windows_x64"]) as zf:
        data = zf.read(win)
    bad = _rewrite(src, tmp_path / src.name, add={win: data}, wheels=listed)
    probs = _problems(bad)
    assert any(f"{Path(win).name} is not for macos-x64" in p for p in probs), probs


def test_checker_refuses_a_renamed_wheel(zips, tmp_path):
    """The Linux OpenEXR wheel under the Windows wheel's name: the file names pass, the
    wheel's own WHEEL file does not."""
    src = zips["windows_x64"]
    win = next(w for w in _wheels_of(src) if "openexr" in w and "cp311" in w)
    with zipfile.ZipFile(zips["linux_x64"]) as zf:
        linux = zf.read(next(w for w in zf.namelist() if "openexr" in w and "cp311" in w))
    bad = _rewrite(src, tmp_path / src.name, add={win: linux})
    probs = _problems(bad)
    assert len(probs) == 1 and "['cp311-cp311-win_amd64'] are not in its WHEEL file" in probs[0], probs


def test_checker_refuses_a_zip_without_the_newer_python(zips, tmp_path):
    """cp311 wheels only: Blender 5.1+ (Python 3.13) would find no OpenEXR or SciPy."""
    src = zips["linux_x64"]
    cp313 = {w for w in _wheels_of(src) if "cp313" in w}
    keep = ["./" + w for w in _wheels_of(src) if w not in cp313]
    bad = _rewrite(src, tmp_path / src.name, drop=cp313, wheels=keep)
    probs = _problems(bad)
    for blender in ("5.1", "5.2", "5.3"):
        assert any(f"Blender {blender} (Python 3.13) would install 0 wheels of scipy" in p
                   for p in probs), probs
    assert not any("Blender 4.2" in p for p in probs), probs
    # Blender itself would refuse it on 5.1+: it reads only 3.11 from the wheels
    assert any("Blender reads Python versions {(3, 11)}" in p for p in probs), probs


def test_checker_refuses_a_wheel_no_release_on_the_platform_installs(zips, tmp_path):
    """A cp313 wheel in the Intel-Mac zip: no Blender with Python 3.13 runs there."""
    src = zips["macos_x64"]
    with zipfile.ZipFile(zips["macos_arm64"]) as zf:
        arm = next(w for w in zf.namelist() if "openexr" in w and "cp313" in w)
    name = arm.replace("macosx_11_0_arm64", "macosx_10_15_x86_64")
    bad = _rewrite(src, tmp_path / src.name, add={name: b"x"},
                   wheels=["./" + w for w in _wheels_of(src)] + ["./" + name])
    probs = _problems(bad)
    assert any("no Blender release on macos-x64 installs it" in p for p in probs), probs


def test_checker_refuses_a_macos_wheel_newer_than_blender(zips, monkeypatch):
    """SciPy's Apple-silicon wheels need macOS 12.0; Blender 4.2 to 5.2 run from 11.2.
    The zip passes only with the macos-arm64 floor the checker declares (and the README
    states); without it the checker names the wheel and the releases."""
    assert _problems(zips["macos_arm64"]) == []
    monkeypatch.setattr(check_addon, "MACOS_FLOOR", {})
    probs = _problems(zips["macos_arm64"])
    assert probs and all("needs macOS 12.0" in p and "scipy" in p for p in probs), probs
    assert any("Blender 4.2 on macos-arm64 runs from 11.2" in p for p in probs)
    # 5.3 starts at macOS 13.0 (its bpy wheel's tag): SciPy's 12.0 is fine there
    assert not any("Blender 5.3" in p for p in probs)


def test_checker_refuses_the_harness_in_the_runtime_wheel(zips, tmp_path):
    src = zips["linux_x64"]
    with zipfile.ZipFile(src) as zf:
        (name,) = [n for n in zf.namelist() if "mpib_validate" in n]
        buf = io.BytesIO()
        with zipfile.ZipFile(io.BytesIO(zf.read(name))) as inner, \
                zipfile.ZipFile(buf, "w") as out:
            for info in inner.infolist():
                out.writestr(info, inner.read(info.filename))
            out.writestr("mpib_validate/cards/trace.py", "")
    bad = _rewrite(src, tmp_path / src.name, add={name: buf.getvalue()})
    probs = _problems(bad)
    assert any("the runtime wheel holds more than the runtime" in p
               and "mpib_validate/cards/trace.py" in p for p in probs), probs


def test_checker_exits_1_on_a_problem_and_2_on_a_missing_file(zips, tmp_path):
    script = ROOT / "scripts" / "check_addon.py"
    ok = subprocess.run([sys.executable, str(script), str(zips["linux_x64"])],
                        capture_output=True, text=True)
    assert ok.returncode == 0 and ": ok" in ok.stdout, ok.stdout + ok.stderr
    src = zips["macos_x64"]
    bad = _rewrite(src, tmp_path / src.name, drop={_wheels_of(src)[-1]})
    r = subprocess.run([sys.executable, str(script), str(bad)], capture_output=True, text=True)
    assert r.returncode == 1 and "1 problems" in r.stdout, r.stdout + r.stderr
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "none.zip")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 \
        and "none.zip" in r.stderr, r.stderr
