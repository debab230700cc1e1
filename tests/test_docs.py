"""The documentation names only what exists, and every command's help fits a terminal.

- Every repository path that README.md, docs/*.md or a docstring names (backticked, or
  a Markdown link) exists in the checkout, and every link between pages lands on a
  file. CHANGELOG.md is left out: it names files as they were.
- Every dotted name of the package that a docstring cross-references (``:mod:``,
  ``:func:``, ``:class:``, ``:meth:``, ``:data:``, ``:attr:``, ``:exc:``) or that the
  Markdown backticks (`mpib_validate.x.y`) resolves: the module imports and the rest is
  found by getattr.
- Every ``mpib`` subcommand's ``--help`` fits a 100-column terminal, is at most
  :data:`HELP_MAX_LINES` lines, and ends with an example that parses with the current
  options.
"""

from __future__ import annotations

import ast
import importlib
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Top-level folders of the repository: a backticked path that starts with one of these
#: is a repository path and must exist. ``shared/`` is listed because docstrings used
#: to point into a ``shared/`` folder that the repository does not have.
REPO_DIRS = ("mpib_validate", "docs", "tests", "scripts", "blender_addon", "mitsuba_scenes",
             "shared")
#: Repository documents named without a folder.
REPO_DOCS = ("README.md", "CHANGELOG.md", "REFERENCE.md")
#: A terminal's width (columns), and a help page a reader can take in (lines: about
#: three screens; ``mpib refocus``, with its photograph, camera and cache options and the
#: paper/physical table, is the longest at about 130 at 80 columns).
HELP_MAX_COLUMNS = 100
HELP_MAX_LINES = 150

_PATH = re.compile(r"(?<![\w./-])((?:%s)/[A-Za-z0-9_./-]*[A-Za-z0-9_/])" % "|".join(REPO_DIRS))
_DOC = re.compile(r"(?<![\w./-])(%s)(?![\w])" % "|".join(re.escape(d) for d in REPO_DOCS))
_LINK = re.compile(r"\]\(([^)\s]+)\)")
_ROLE = re.compile(r":(?:mod|func|class|meth|data|attr|exc):`~?(mpib_validate(?:\.\w+)+)`")
_DOTTED = re.compile(r"`(mpib_validate(?:\.\w+)+)(?:\([^`]*\))?`")
_PLACEHOLDER = re.compile(r"[<>*{}]")


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def python_files() -> list[Path]:
    files = []
    for top in ("mpib_validate", "mitsuba_scenes", "blender_addon", "scripts", "tests"):
        files += sorted((ROOT / top).rglob("*.py"))
    return [f for f in files if "wheels" not in f.parts]


def docstrings(path: Path):
    """``(where, text)`` of every module, class and function docstring in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            text = ast.get_docstring(node)
            if text:
                yield f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 1)}", text


def named_paths(text: str) -> set[str]:
    """Repository paths and documents named in ``text`` (placeholders left out)."""
    found = {m.rstrip("./") for m in _PATH.findall(text)} | set(_DOC.findall(text))
    return {p for p in found if p and not _PLACEHOLDER.search(p)}


def exists(name: str) -> bool:
    if "/" in name:
        return (ROOT / name).exists()
    return (ROOT / name).exists() or (ROOT / "docs" / name).exists()


def anchors(text: str) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation but ``-`` dropped,
    spaces to ``-`` (code fences skipped)."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
            for h in re.findall(r"^#{1,6} (.+)$", text, re.M)}


def missing_paths() -> list[str]:
    bad = []
    for md in markdown_files():
        text = md.read_text(encoding="utf-8")
        for name in named_paths(text):
            if not exists(name):
                bad.append(f"{md.relative_to(ROOT)} names `{name}`, which does not exist")
        for link in _LINK.findall(text):
            target = link.split("#")[0]
            if re.match(r"[a-z]+:", target) or _PLACEHOLDER.search(target):
                continue
            page = md.parent / target if target else md
            if not page.exists():
                bad.append(f"{md.relative_to(ROOT)} links to {link}, which does not exist")
            elif "#" in link and page.suffix == ".md" and \
                    link.split("#", 1)[1] not in anchors(page.read_text(encoding="utf-8")):
                bad.append(f"{md.relative_to(ROOT)} links to {link}: no such heading there")
    for py in python_files():
        for where, text in docstrings(py):
            for name in named_paths(text):
                if not exists(name):
                    bad.append(f"the docstring at {where} names `{name}`, which does not exist")
    return sorted(set(bad))


def resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError as exc:
            if exc.name and not ".".join(parts[:i]).startswith(exc.name):
                raise  # a dependency is missing, not the module: say so
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def unresolved_names() -> list[str]:
    bad = []
    for md in markdown_files():
        for name in set(_DOTTED.findall(md.read_text(encoding="utf-8"))):
            if not resolves(name):
                bad.append(f"{md.relative_to(ROOT)} names `{name}`, which does not resolve")
    for py in python_files():
        for where, text in docstrings(py):
            for name in set(_ROLE.findall(text)):
                if not resolves(name):
                    bad.append(f"the docstring at {where} names {name}, which does not resolve")
    return sorted(set(bad))


def test_named_paths_exist():
    bad = missing_paths()
    assert not bad, "\n".join(bad)


def test_named_python_objects_resolve():
    bad = unresolved_names()
    assert not bad, "\n".join(bad)


def test_the_checks_see_what_they_check():
    """The extractors find the kinds of names they are meant to (so a passing run means
    the names were checked, not missed)."""
    text = ("see ``docs/camera.md`` and `mpib_validate/runtime/camera.py`, [a](docs/x.md), "
            "``shared/REFERENCE.md`` and REFERENCE.md; `out/bench/<suite>.md` is output")
    assert named_paths(text) == {"docs/camera.md", "mpib_validate/runtime/camera.py",
                                 "docs/x.md", "shared/REFERENCE.md", "REFERENCE.md"}
    assert not exists("shared/REFERENCE.md") and not exists("REFERENCE.md")
    assert anchors("## Presets (`--preset`)\n```\n# not a heading\n```\n### The camera's K") == {
        "presets---preset", "the-cameras-k"}
    assert resolves("mpib_validate.runtime.camera.Camera.thin_lens")
    assert not resolves("mpib_validate.runtime.camera.NoSuchThing")
    assert not resolves("mpib_validate.no_such_module")
    assert _ROLE.findall(":func:`~mpib_validate.runtime.refocus.refocus` :class:`Camera`") == [
        "mpib_validate.runtime.refocus.refocus"]
    docs = {p.name for p in markdown_files()}
    assert {"README.md", "camera.md", "compositor.md", "pipeline.md", "photos.md",
            "blender.md", "validation.md", "benchmark.md"} <= docs


# --------------------------------------------------------------------------------------
# --help


def subparsers():
    from mpib_validate import cli

    parser = cli.build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return parser, dict(action.choices)


def help_text(monkeypatch, parser, columns: int) -> str:
    monkeypatch.setenv("COLUMNS", str(columns))
    return parser.format_help()


def examples(text: str) -> list[str]:
    """The ``mpib ...`` command lines under the help's ``example:``/``examples:``."""
    lines = text.splitlines()
    out = []
    for i, line in enumerate(lines):
        if re.match(r"\s*examples?:", line):
            rest = line.split(":", 1)[1].strip()
            block = [rest] if rest else []
            for more in lines[i + 1:]:
                if not more.strip():
                    break
                block.append(more.strip())
            out += [b.split("  #")[0].strip() for b in block if b.startswith("mpib ")]
    return out


@pytest.mark.parametrize("name", sorted(subparsers()[1]) + ["(top level)"])
def test_help_fits_a_terminal_and_shows_an_example(name, monkeypatch):
    top, subs = subparsers()
    parser = top if name == "(top level)" else subs[name]
    for columns in (80, HELP_MAX_COLUMNS):
        text = help_text(monkeypatch, parser, columns)
        wide = [l for l in text.splitlines() if len(l) > HELP_MAX_COLUMNS]
        assert not wide, (f"mpib {name} --help at COLUMNS={columns} has lines over "
                          f"{HELP_MAX_COLUMNS} columns:\n" + "\n".join(wide))
        assert len(text.splitlines()) <= HELP_MAX_LINES, (
            f"mpib {name} --help is {len(text.splitlines())} lines (at most {HELP_MAX_LINES})")
    shown = examples(text)
    assert shown, f"mpib {name} --help shows no example (an 'example:' line with an mpib command)"
    for line in shown:
        argv = shlex.split(line)[1:]
        try:
            top.parse_args(argv)
        except SystemExit:
            pytest.fail(f"the example of mpib {name} --help does not parse: {line}")
        if name != "(top level)":
            assert argv[0] == name, f"mpib {name} --help shows an example of another command: {line}"
