#!/usr/bin/env python3
"""Check the extension's platform zips as Blender would install them.

Usage: python scripts/check_addon.py dist/mpib_refocus-*.zip

For each zip (one per platform, built by ``scripts/build_addon.py`` with Blender's
``extension build --split-platforms``):

- Blender's own ``extension validate`` accepts it (``blender_ext.py`` in the bpy wheel);
- its manifest names exactly the platform of its file name (``[build.generated]``);
- every wheel the manifest lists is in the zip, and every wheel in the zip is listed;
- the runtime's wheel holds only ``mpib_validate/__init__.py`` and ``mpib_validate/runtime``;
- every wheel is a wheel whose own ``WHEEL`` file carries the tags of its file name;
- every wheel's platform tag is the zip's platform (Blender's own mapping of wheel tags
  to platforms), its Python tag cp311 or cp313 (or pure ``py3-none-any``);
- for each Blender release of :data:`BLENDER` that runs on the platform, Blender's wheel
  filter (``bl_extension_ops._extensions_wheel_filter_for_this_system``, restated in
  :func:`installed`) picks exactly one wheel of each needed distribution, and no wheel
  is left that no release on that platform can use;
- the Python versions Blender reads from the zip's wheels (``python_versions_from_wheels``:
  it refuses the zip on any other) are those of the releases on the platform;
- a macOS wheel runs on the oldest macOS of every release that installs it (its
  ``macosx_X_Y`` tag at most that version), or of the platform's declared floor
  (:data:`MACOS_FLOOR`).

Prints one line per zip and one line per problem; exit status 1 if any problem.
Windows and macOS zips are checked here, not run: only Linux has a Blender to run them.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

#: Blender releases the extension supports (``blender_version_min = "4.2.0"`` up to the
#: newest): their Python, and per platform of an official build the oldest macOS it
#: runs on (None: not macOS). Sources: Blender 4.2 LTS requires macOS 11.2; the bpy
#: wheels on PyPI are tagged macosx_11_0 for 4.2 to 5.2 and macosx_13_0 for 5.3 (so
#: 11.2 is kept for 4.2 to 5.2, the documented figure); Intel Macs last get 4.5 (no
#: macosx x86_64 bpy wheel from 5.0 on); Windows on Arm builds start at 4.5.
BLENDER = {
    "4.2": ("3.11", {"linux-x64": None, "windows-x64": None,
                     "macos-x64": (11, 2), "macos-arm64": (11, 2)}),
    "4.5": ("3.11", {"linux-x64": None, "windows-x64": None, "windows-arm64": None,
                     "macos-x64": (11, 2), "macos-arm64": (11, 2)}),
    "5.0": ("3.11", {"linux-x64": None, "windows-x64": None, "windows-arm64": None,
                     "macos-arm64": (11, 2)}),
    "5.1": ("3.13", {"linux-x64": None, "windows-x64": None, "windows-arm64": None,
                     "macos-arm64": (11, 2)}),
    "5.2": ("3.13", {"linux-x64": None, "windows-x64": None, "windows-arm64": None,
                     "macos-arm64": (11, 2)}),
    "5.3": ("3.13", {"linux-x64": None, "windows-x64": None, "windows-arm64": None,
                     "macos-arm64": (13, 0)}),
}
#: The oldest macOS a platform's zip runs on where its dependencies need more than
#: Blender: SciPy publishes Apple-silicon wheels for macOS 12.0 and later only (1.15.3:
#: macosx_12_0_arm64, OpenBLAS; macosx_14_0_arm64, Accelerate), so the macos-arm64 zip
#: needs macOS 12 (Monterey), which every Apple-silicon Mac can run; Blender 4.2 to 5.2
#: themselves start at 11.2. Stated in the README.
MACOS_FLOOR = {"macos-arm64": (12, 0)}
#: What the add-on imports besides Blender's own numpy: one wheel of each per install.
NEEDED = ("mpib-validate", "openexr", "scipy")
#: The ``sysconfig.get_platform()`` of a Blender of each platform (what Blender's wheel
#: filter compares the wheel tags with; the macOS version in it is not compared).
SYSCONFIG = {"linux-x64": "linux_x86_64", "windows-x64": "win_amd64",
             "windows-arm64": "win_arm64", "macos-x64": "macosx_11_0_x86_64",
             "macos-arm64": "macosx_11_0_arm64"}
ZIP_RE = re.compile(r"^(?P<id>[a-z0-9_]+)-(?P<version>[^-]+)-(?P<platform>[a-z]+_[a-z0-9]+)\.zip$")
#: The files of the runtime's wheel: the package's ``__init__.py``, the runtime
#: subpackage's Python files and the wheel's metadata (no card scenes, tracer, benches or
#: Blender suite: the harness stays out of the extension).
RUNTIME_RE = re.compile(r"^(mpib_validate/__init__\.py|mpib_validate/runtime/.+\.py"
                        r"|mpib_validate-[^/]+\.dist-info/[^/]+)$")
MACOS_RE = re.compile(r"^macosx_(\d+)_(\d+)_(\w+)$")


def host_platform() -> str:
    """This machine's Blender platform, as in the zip names (``linux_x64``)."""
    import platform

    system = {"Linux": "linux", "Windows": "windows", "Darwin": "macos"}.get(
        platform.system(), platform.system().lower())
    machine = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64"}.get(
        platform.machine().lower(), platform.machine().lower())
    return f"{system}_{machine}"


def blender_ext_path() -> Path:
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("check_addon: the bpy module is needed for Blender's extension tool")
    base = Path(list(spec.submodule_search_locations)[0])
    found = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        sys.exit(f"check_addon: blender_ext.py not found under {base}")
    return found[-1]


def blender_ext():
    """Blender's extension tool as a module (for its wheel-tag functions)."""
    spec = importlib.util.spec_from_file_location("_blender_ext", blender_ext_path())
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def wheel_tags(name: str) -> tuple[str, str, str, str]:
    """``(distribution, python, abi, platform)`` of a wheel file name (distribution
    normalised: lower case, ``_`` -> ``-``)."""
    parts = name[:-4].split("-")
    return parts[0].lower().replace("_", "-"), parts[-3], parts[-2], parts[-1]


def installed(wheels: list[str], platform: str, python: str) -> list[str]:
    """The wheels Blender installs on ``platform`` under CPython ``python`` ("3.11"):
    ``bl_extension_ops._extensions_wheel_filter_for_this_system`` with the system's
    platform and Python given (a ``macosx`` tag matches by architecture, its version is
    not compared; a ``manylinux`` tag by architecture; ``py3`` any Python 3)."""
    current = SYSCONFIG[platform]
    major, minor = python.split(".")
    out = []
    for w in wheels:
        _, py, _, plat = wheel_tags(Path(w).name)
        plats = plat.split(".")
        plat_ok = any(
            p in ("any", current)
            or (current.startswith("macosx_") and p.startswith("macosx_")
                and (p.endswith("_" + current.rpartition("_")[2]) or p.endswith("_universal2")))
            or (current.startswith("linux_") and p.startswith("manylinux")
                and p.endswith("_" + current.partition("_")[2]))
            for p in plats)
        py_ok = any(t in (f"py{major}", f"cp{major}{minor}", f"py{major}{minor}")
                    for t in py.split("."))
        if plat_ok and py_ok:
            out.append(w)
    return out


def wheel_file_tags(wheel: zipfile.ZipFile) -> set[str]:
    """The ``Tag:`` lines of a wheel's ``*.dist-info/WHEEL`` (what the wheel was built
    for, whatever its file is called)."""
    (meta,) = [n for n in wheel.namelist() if re.fullmatch(r"[^/]+\.dist-info/WHEEL", n)]
    return {line.split(":", 1)[1].strip() for line in wheel.read(meta).decode().splitlines()
            if line.startswith("Tag:")}


def macos_min(wheel: str) -> tuple[int, int] | None:
    """Oldest macOS of a wheel (the lowest of its ``macosx_X_Y`` tags), None if not macOS."""
    found = [MACOS_RE.match(p) for p in wheel_tags(Path(wheel).name)[3].split(".")]
    vs = [(int(m[1]), int(m[2])) for m in found if m]
    return min(vs) if vs else None


def check_zip(path: Path, ext=None, tool: Path | None = None) -> tuple[dict, list[str]]:
    """``(summary, problems)`` of one platform zip."""
    ext = ext or blender_ext()
    problems: list[str] = []
    m = ZIP_RE.match(path.name)
    if m is None:
        return {}, [f"{path.name}: not an <id>-<version>-<platform>.zip name"]
    platform = m["platform"].replace("_", "-", 1)
    r = subprocess.run([sys.executable, str(tool or blender_ext_path()), "validate", str(path)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        problems.append(f"{path.name}: Blender's validate refuses it: "
                        f"{(r.stdout + r.stderr).strip().splitlines()[-1:]}")
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    generated = manifest.get("build", {}).get("generated", {})
    if generated.get("platforms") != [platform]:
        problems.append(f"{path.name}: manifest [build.generated] platforms "
                        f"{generated.get('platforms')} != [{platform!r}]")
    wheels = generated.get("wheels", manifest.get("wheels", []))
    listed = {w.removeprefix("./") for w in wheels}
    in_zip = {n for n in names if n.endswith(".whl")}
    for w in sorted(listed - in_zip):
        problems.append(f"{path.name}: wheel listed in the manifest but not in the zip: {w}")
    for w in sorted(in_zip - listed):
        problems.append(f"{path.name}: wheel in the zip but not in the manifest: {w}")
    for w in sorted(listed & in_zip):
        name = Path(w).name
        try:
            with zipfile.ZipFile(path) as zf, zf.open(w) as fh, zipfile.ZipFile(fh) as inner:
                names = inner.namelist()
                tags = wheel_file_tags(inner)
        except (zipfile.BadZipFile, KeyError, ValueError) as exc:
            problems.append(f"{path.name}: {name} is not a readable wheel ({exc})")
            continue
        _, py, abi, plat = wheel_tags(name)
        named = {f"{p}-{a}-{pl}" for p in py.split(".") for a in abi.split(".")
                 for pl in plat.split(".")}
        if not named <= tags:
            problems.append(f"{path.name}: {name}: its file name's tags {sorted(named - tags)} "
                            f"are not in its WHEEL file ({sorted(tags)})")
        if wheel_tags(name)[0] == "mpib-validate":
            extra = [n for n in names if not RUNTIME_RE.match(n)]
            if extra:
                problems.append(f"{path.name}: the runtime wheel holds more than the runtime: "
                                f"{extra[:3]}{' ...' if len(extra) > 3 else ''} ({len(extra)} files)")
    used: set[str] = set()
    served = {}
    for w in sorted(listed):
        dist, py, abi, plat = wheel_tags(Path(w).name)
        if not any(ext.blender_platform_compatible_with_wheel_platform(platform, p)
                   for p in plat.split(".")):
            problems.append(f"{path.name}: {Path(w).name} is not for {platform}")
        if (py, abi, plat) != ("py3", "none", "any") and not (
                py in ("cp311", "cp313") and abi == py):
            problems.append(f"{path.name}: {Path(w).name}: Python/ABI tags {py}-{abi} are "
                            f"neither cp311/cp313 nor py3-none")
    for blender, (python, platforms) in BLENDER.items():
        if platform not in platforms:
            continue
        chosen = installed(sorted(listed), platform, python)
        used.update(chosen)
        served[blender] = python
        by_dist: dict[str, list[str]] = {}
        for w in chosen:
            by_dist.setdefault(wheel_tags(Path(w).name)[0], []).append(Path(w).name)
        for dist in NEEDED:
            if len(by_dist.get(dist, [])) != 1:
                problems.append(f"{path.name}: Blender {blender} (Python {python}) would install "
                                f"{len(by_dist.get(dist, []))} wheels of {dist}: {by_dist.get(dist, [])}")
        oldest = max(platforms[platform], MACOS_FLOOR.get(platform, (0, 0))) \
            if platforms[platform] else None
        for w in chosen:
            need = macos_min(w)
            if need is not None and oldest is not None and need > oldest:
                problems.append(f"{path.name}: {Path(w).name} needs macOS {need[0]}.{need[1]}; "
                                f"Blender {blender} on {platform} runs from "
                                f"{oldest[0]}.{oldest[1]}")
    # the Pythons Blender reads from the zip's wheels (it refuses the zip on any other)
    read = ext.python_versions_from_wheels(sorted(listed)) if listed else set()
    want = {tuple(int(x) for x in py.split(".")) for py in served.values()}
    if isinstance(read, str) or {v for v in read if len(v) == 2} != want:
        problems.append(f"{path.name}: Blender reads Python versions {read} from the wheels; "
                        f"the releases on {platform} run {sorted(want)}")
    for w in sorted(listed - used):
        problems.append(f"{path.name}: {Path(w).name}: no Blender release on {platform} installs it")
    if not served:
        problems.append(f"{path.name}: no Blender release of the supported range runs on {platform}")
    summary = {"zip": path.name, "platform": platform, "bytes": path.stat().st_size,
               "wheels": len(listed), "blender": served,
               "macos_floor": MACOS_FLOOR.get(platform)}
    return summary, problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("zips", nargs="+", type=Path)
    args = ap.parse_args(argv)
    ext, tool = blender_ext(), blender_ext_path()
    bad = 0
    for z in args.zips:
        if not z.is_file():
            print(f"check_addon: {z}: no such file", file=sys.stderr)
            return 2
        s, problems = check_zip(z, ext, tool)
        if s:
            pythons = sorted(set(s["blender"].values()))
            floor = f", macOS >= {s['macos_floor'][0]}.{s['macos_floor'][1]}" \
                if s["macos_floor"] else ""
            print(f"{s['zip']}: {s['bytes'] / 1e6:.1f} MB, {s['wheels']} wheels, Blender "
                  f"{', '.join(s['blender'])} (Python {', '.join(pythons)}){floor}: "
                  f"{'ok' if not problems else f'{len(problems)} problems'}")
        for p in problems:
            print("  " + p)
        bad += bool(problems)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
