"""Blender's extension conventions, read from the source (no Blender needed).

- Every Blender version quirk lives in ``mpib_validate/runtime/blender/compat.py``: no
  other file of the project reads ``bpy.app.version``, and the extension and the
  runtime do not ask compat for the version number either (they ask for the feature).
- The extension registers its classes with ``bpy.utils.register_classes_factory``.
- Neither the extension nor the runtime it bundles imports a network module.

Where the extension writes files (the kept passes in its user directory) is checked in
real Blender by tests/test_addon.py.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COMPAT = ROOT / "mpib_validate" / "runtime" / "blender" / "compat.py"
#: What the extension zip ships: the add-on's modules and the runtime's wheel.
SHIPPED = [*sorted((ROOT / "blender_addon").glob("*.py")),
           *sorted((ROOT / "mpib_validate" / "runtime").rglob("*.py"))]
#: ``bpy.app.version`` (not ``version_string``, which only reports), however imported.
VERSION_READ = re.compile(r"\bapp\s*\.\s*version\b(?!_)|from\s+bpy\.app\s+import\s+.*\bversion\b(?!_)")
#: A call of compat's ``version()``.
VERSION_CALL = re.compile(r"(\bcompat|\bbc)\s*\.\s*version\s*\(|import\s+.*\bversion\b(?!_)")
NETWORK = {"socket", "ssl", "urllib", "http", "ftplib", "smtplib", "xmlrpc", "requests",
           "aiohttp", "httpx", "websocket", "websockets"}


def _python_files():
    """The project's Python files, but this one (which names the pattern it refuses)."""
    for top in ("mpib_validate", "blender_addon", "tests", "scripts", "mitsuba_scenes"):
        yield from (f for f in sorted((ROOT / top).rglob("*.py"))
                    if f.resolve() != Path(__file__).resolve())


def test_only_compat_reads_the_blender_version():
    found = {}
    for f in _python_files():
        for n, line in enumerate(f.read_text().splitlines(), 1):
            if VERSION_READ.search(line.split("#")[0]):
                found.setdefault(f.relative_to(ROOT).as_posix(), []).append(n)
    # the scan sees compat's own read, so it would see one elsewhere
    assert COMPAT.relative_to(ROOT).as_posix() in found
    others = {k: v for k, v in found.items() if k != COMPAT.relative_to(ROOT).as_posix()}
    assert others == {}, f"bpy.app.version read outside compat.py (lines): {others}"


def test_the_extension_and_runtime_ask_for_features_not_versions():
    calls = {}
    for f in SHIPPED:
        if f == COMPAT:
            continue
        for n, line in enumerate(f.read_text().splitlines(), 1):
            if VERSION_CALL.search(line.split("#")[0]):
                calls.setdefault(f.relative_to(ROOT).as_posix(), []).append(n)
    assert calls == {}, f"compat.version() called from shipped code (lines): {calls}"
    # the pattern does match such a call
    assert VERSION_CALL.search("if compat.version() < (5, 0):")


def _registered_classes(tree: ast.Module) -> tuple[set[str], set[str], bool, list[int]]:
    """(Blender classes defined, names in ``classes``, factory used, direct
    register_class / unregister_class calls) of a module."""
    bl_bases = {"Operator", "Panel", "PropertyGroup", "Menu", "UIList", "AddonPreferences",
                "Header", "Gizmo", "GizmoGroup", "Macro", "KeyingSetInfo", "RenderEngine"}
    defined, listed, factory, direct = set(), set(), False, []
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef):
            for b in node.bases:
                name = b.attr if isinstance(b, ast.Attribute) else getattr(b, "id", "")
                if name in bl_bases:
                    defined.add(node.name)
        elif isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "classes" for t in node.targets):
            if isinstance(node.value, (ast.Tuple, ast.List)):
                listed |= {e.id for e in node.value.elts if isinstance(e, ast.Name)}
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr == "register_classes_factory":
                factory = True
            elif node.func.attr in ("register_class", "unregister_class"):
                direct.append(node.lineno)
    return defined, listed, factory, direct


def test_the_extension_registers_its_classes_with_the_factory():
    seen = 0
    for f in sorted((ROOT / "blender_addon").glob("*.py")):
        defined, listed, factory, direct = _registered_classes(ast.parse(f.read_text()))
        assert direct == [], f"{f.name}: register_class/unregister_class called directly, lines {direct}"
        if defined:
            seen += len(defined)
            assert factory and defined <= listed, (f.name, defined, listed, factory)
    assert seen >= 8  # operators, panels and the settings: the scan finds them


def test_the_extension_and_runtime_import_no_network_module():
    found = {}
    for f in SHIPPED:
        for node in ast.walk(ast.parse(f.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            hits = [n for n in names if n.split(".")[0] in NETWORK]
            if hits:
                found.setdefault(f.relative_to(ROOT).as_posix(), []).extend(hits)
    assert found == {}, found
