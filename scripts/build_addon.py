#!/usr/bin/env python3
"""Build the Blender extension zip: the project's wheel, the wheels it needs, validate, build.

Usage: python scripts/build_addon.py [--out dist]

The manifest (blender_addon/blender_manifest.toml) names every wheel. The project's own
wheel is built from this checkout; the others (OpenEXR, SciPy; Blender ships numpy) are
downloaded from PyPI for the Python version and platform in each file name (cp311 for
Blender 4.2 to 5.0, cp313 for 5.1+), pinned by those names. `--fetch-only` (run by
scripts/setup.sh) downloads them once; building afterwards needs no network. Then
Blender's own extension tool (inside the bpy wheel) validates and builds the zip, so
no Blender binary is needed. Nothing is downloaded at run time.
"""

from __future__ import annotations

import argparse
import importlib.util
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


def blender_ext() -> Path:
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("build_addon: the bpy module is needed for Blender's extension tool "
                 "(pip install mpib-validate[blender])")
    base = Path(list(spec.submodule_search_locations)[0])
    found = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        sys.exit(f"build_addon: blender_ext.py not found under {base}")
    return found[-1]


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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "dist"), help="output folder for the zip")
    ap.add_argument("--fetch-only", action="store_true",
                    help="only download the dependency wheels the manifest names (set-up step)")
    args = ap.parse_args()
    manifest = tomllib.loads((ADDON / "blender_manifest.toml").read_text())
    wheels_dir = ADDON / "wheels"
    wheels_dir.mkdir(exist_ok=True)
    wanted = [Path(w).name for w in manifest.get("wheels", [])]
    if not args.fetch_only:
        # the project's own wheel; offline when the environment has a recent setuptools
        flags = ["--no-build-isolation"] if _can_build_offline() else []
        with tempfile.TemporaryDirectory() as tmp:
            run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", *flags, "-w", tmp,
                 str(ROOT)])
            for whl in Path(tmp).glob("*.whl"):
                shutil.copy2(whl, wheels_dir / whl.name)
    for name in wanted:
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
    if args.fetch_only:
        print(f"build_addon: dependency wheels ready in {wheels_dir}")
        return 0
    missing = [n for n in wanted if not (wheels_dir / n).exists()]
    if missing:
        sys.exit(f"build_addon: wheels named in the manifest are missing: {missing}")
    for extra in wheels_dir.glob("*.whl"):
        if extra.name not in wanted:
            extra.unlink()  # an old build's wheel: keep the zip to what the manifest says
    tool = blender_ext()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    run([sys.executable, str(tool), "validate", str(ADDON)])
    run([sys.executable, str(tool), "build", "--source-dir", str(ADDON), "--output-dir", str(out)])
    zips = sorted(out.glob(f"{manifest['id']}-{manifest['version']}*.zip"))
    print(f"build_addon: wrote {', '.join(str(z) for z in zips)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
