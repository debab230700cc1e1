"""The extension manifest bundles wheels for every Python of the Blender range.

Blender 4.2 to 5.0 run CPython 3.11, Blender 5.1 and later 3.13. Blender installs the
wheels whose Python and platform tags match it, and derives the Pythons an extension
supports from its wheels: with cp311 wheels only, Blender 5.3 refused the zip ("This
Python version (3.13) isn't compatible with (3.11)").
"""

from __future__ import annotations

import importlib.util
import tomllib
from pathlib import Path

import pytest
from packaging.utils import parse_wheel_filename

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = tomllib.loads((ROOT / "blender_addon" / "blender_manifest.toml").read_text())
#: The Pythons of the supported Blender range and the platform tags of the manifest's
#: platforms (Blender matches any manylinux tag of the same architecture).
PYTHONS = ("cp311", "cp313")
PLATFORMS = {"linux-x64": "x86_64"}
#: What the add-on needs besides Blender's own numpy.
NEEDED = {"mpib-validate", "openexr", "scipy"}


def _wheels():
    return [parse_wheel_filename(Path(w).name) for w in MANIFEST["wheels"]]


@pytest.mark.parametrize("python", PYTHONS)
@pytest.mark.parametrize("platform", sorted(MANIFEST["platforms"]))
def test_each_python_and_platform_gets_each_dependency_once(python, platform):
    arch = PLATFORMS[platform]
    chosen = {}
    for name, _, _, tags in _wheels():
        for tag in tags:
            py_ok = tag.interpreter in (python, "py3")
            plat_ok = tag.platform == "any" or (tag.platform.startswith("manylinux")
                                                and tag.platform.endswith("_" + arch))
            if py_ok and plat_ok:
                chosen.setdefault(str(name), set()).add(tag.interpreter)
                break
    assert set(chosen) == NEEDED, (python, platform, chosen)


def test_pure_wheel_is_the_only_one_without_a_python_version():
    for name, _, _, tags in _wheels():
        interps = {t.interpreter for t in tags}
        if str(name) == "mpib-validate":
            assert interps == {"py3"} and {t.platform for t in tags} == {"any"}
        else:
            assert interps <= set(PYTHONS), (name, interps)


@pytest.mark.blender
def test_blender_reads_both_python_versions_from_the_manifest():
    """Blender's own extension tool (bl_pkg/cli/blender_ext.py in the bpy wheel) gives
    the Python versions it will accept the zip on."""
    spec = importlib.util.find_spec("bpy")
    if spec is None:
        pytest.skip("bpy is not installed")
    base = Path(list(spec.submodule_search_locations)[0])
    tool = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))[-1]
    mod_spec = importlib.util.spec_from_file_location("blender_ext_for_test", tool)
    mod = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(mod)
    versions = mod.python_versions_from_wheels(MANIFEST["wheels"])
    assert not isinstance(versions, str), versions
    assert {v for v in versions if len(v) == 2} == {(3, 11), (3, 13)}
