#!/usr/bin/env python3
"""Build the Blender extension: one zip per platform, each with the runtime's wheel and
its platform's dependency wheels; validate and check them.

Usage: python scripts/build_addon.py [--out dist] [--fetch-only]

The manifest (blender_addon/blender_manifest.toml) lists the platforms and every wheel.
The runtime's wheel (``mpib_validate/__init__.py`` and ``mpib_validate/runtime/``: what
refocusing needs, none of the validation harness) is built from this checkout; the
others (OpenEXR, SciPy; Blender ships numpy) are downloaded from PyPI for the Python
version and platform in each file name, pinned by those names. ``--fetch-only`` (run by
scripts/setup.sh) downloads them once; building afterwards needs no network. Blender's
own extension tool (inside the bpy wheel, no Blender binary needed) validates the source
and builds with ``--split-platforms``: one zip per platform, holding only the wheels of
that platform (``mpib_refocus-<version>-<platform>.zip``). scripts/check_addon.py then
checks each zip as Blender would install it. Nothing is downloaded at run time.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ADDON = ROOT / "blender_addon"
WHEEL_RE = re.compile(r"^(?P<name>[^-]+)-(?P<version>[^-]+)-(?P<py>[^-]+)-(?P<abi>[^-]+)-(?P<plat>.+)\.whl$")
#: What the runtime's wheel holds, relative to the checkout: the package's
#: ``__init__.py`` (units and version) and the runtime subpackage, Python files only.
RUNTIME_FILES = ("mpib_validate/__init__.py", "mpib_validate/runtime")
#: The runtime wheel's project file: no dependencies (Blender bundles numpy; the
#: extension bundles OpenEXR and SciPy beside it and installs no dependency itself).
RUNTIME_PYPROJECT = """\
[build-system]
requires = ["setuptools>=68", "wheel"]
build-backend = "setuptools.build_meta"

[project]
name = "mpib-validate"
version = "{version}"
description = "MPIB refocusing runtime (the MPIB Refocus Blender extension's compositor)"
requires-python = ">=3.11,<3.14"
license = {{ text = "MIT" }}

[tool.setuptools.packages.find]
include = ["mpib_validate*"]
"""

sys.path.insert(0, str(Path(__file__).resolve().parent))
import check_addon  # noqa: E402


def _can_build_offline() -> bool:
    """True when setuptools >= 68 and wheel are installed (no isolated build env needed)."""
    try:
        import setuptools
        import wheel  # noqa: F401
    except ImportError:
        return False
    return int(setuptools.__version__.split(".")[0]) >= 68


def python_version(tag: str, name: str) -> str:
    """``cp313`` -> ``3.13``: the Python version a manifest wheel is for."""
    m = re.fullmatch(r"cp(\d)(\d+)", tag)
    if m is None:
        sys.exit(f"build_addon: wheel {name!r} is not for one CPython version ({tag!r})")
    return f"{m[1]}.{m[2]}"


def run(cmd, **kw):
    print("+", " ".join(map(str, cmd)), flush=True)
    subprocess.run(cmd, check=True, **kw)


def runtime_wheel(dest: Path) -> Path:
    """Build the runtime's wheel into ``dest`` from a staging copy of :data:`RUNTIME_FILES`."""
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    flags = ["--no-build-isolation"] if _can_build_offline() else []
    with tempfile.TemporaryDirectory() as tmp:
        stage = Path(tmp) / "stage"
        for rel in RUNTIME_FILES:
            src = ROOT / rel
            files = [src] if src.is_file() else sorted(src.rglob("*.py"))
            for f in files:
                dst = stage / f.relative_to(ROOT)
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(f, dst)
        (stage / "pyproject.toml").write_text(RUNTIME_PYPROJECT.format(version=version))
        out = Path(tmp) / "out"
        run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", *flags, "-w", str(out),
             str(stage)])
        (whl,) = out.glob("*.whl")
        shutil.copy2(whl, dest / whl.name)
        return dest / whl.name


def fetch(names: list[str], wheels_dir: Path) -> None:
    """Download the dependency wheels named in the manifest that are not here yet."""
    for name in names:
        if (wheels_dir / name).exists() or name.startswith("mpib_validate-"):
            continue
        m = WHEEL_RE.match(name)
        if m is None:
            sys.exit(f"build_addon: cannot parse wheel file name {name!r} in the manifest")
        plats = []
        for p in m["plat"].split("."):
            plats += ["--platform", p]
        run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
             "--python-version", python_version(m["py"], name), "--implementation", "cp",
             "--abi", m["abi"], *plats, "-d", str(wheels_dir), f"{m['name']}=={m['version']}"])
        if not (wheels_dir / name).exists():
            sys.exit(f"build_addon: pip did not download {name} (check the name in the manifest)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "dist"), help="output folder for the zips")
    ap.add_argument("--fetch-only", action="store_true",
                    help="only download the dependency wheels the manifest names (set-up step)")
    args = ap.parse_args()
    manifest = tomllib.loads((ADDON / "blender_manifest.toml").read_text())
    wheels_dir = ADDON / "wheels"
    wheels_dir.mkdir(exist_ok=True)
    wanted = [Path(w).name for w in manifest.get("wheels", [])]
    fetch(wanted, wheels_dir)
    if args.fetch_only:
        print(f"build_addon: dependency wheels ready in {wheels_dir}")
        return 0
    runtime_wheel(wheels_dir)
    missing = [n for n in wanted if not (wheels_dir / n).exists()]
    if missing:
        sys.exit(f"build_addon: wheels named in the manifest are missing: {missing}")
    for extra in wheels_dir.glob("*.whl"):
        if extra.name not in wanted:
            # not in the manifest (an old build's wheel): Blender's build would copy it
            # into every zip as a plain file
            extra.unlink()
    tool = check_addon.blender_ext_path()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob(f"{manifest['id']}-*.zip"):
        old.unlink()  # an earlier build's zips (another version, or the one-platform zip)
    run([sys.executable, str(tool), "validate", str(ADDON)])
    run([sys.executable, str(tool), "build", "--split-platforms", "--source-dir", str(ADDON),
         "--output-dir", str(out)])
    zips = sorted(out.glob(f"{manifest['id']}-{manifest['version']}-*.zip"))
    if len(zips) != len(manifest["platforms"]):
        sys.exit(f"build_addon: expected {len(manifest['platforms'])} zips, got {zips}")
    if check_addon.main([str(z) for z in zips]) != 0:
        sys.exit("build_addon: the zips fail the checks above")
    print(f"build_addon: wrote {', '.join(str(z) for z in zips)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
