"""The package's import graph: the runtime stands alone, and no module imports itself back.

The runtime (``mpib_validate.runtime``: what the Blender extension ships) must import
nothing of the validation harness (cards, tracer, references, baselines, metrics,
benches, CLI) nor of the add-on or the Mitsuba adapter; and no two modules may import
each other, directly or through others (a strongly connected component of more than one
module). Imports are read from the source (every ``import`` statement, also those inside
functions), so a lazy import counts as an arrow too.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("mpib_validate", "mitsuba_scenes", "blender_addon")
RUNTIME = "mpib_validate.runtime"


def modules(root: Path = ROOT) -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            name = ".".join(path.relative_to(root).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """``{module: modules it imports}`` among the project's own modules.

    ``from P import X`` is an arrow to ``P.X`` when that is a module, else to ``P``;
    importing a submodule does not count as importing its package's ``__init__``
    (Python runs it, but the package cannot depend on it that way)."""
    mods = modules(root)
    graph: dict[str, set[str]] = {m: set() for m in mods}

    def known(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    for m, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = m.split(".") if is_pkg else m.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                for a in node.names:
                    full = f"{mod}.{a.name}"
                    targets.append(full if full in mods else mod)
            for t in targets:
                k = known(t)
                if k is not None and k != m:
                    graph[m].add(k)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def upward(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Arrows from the runtime to anything of the project outside it (the package's
    ``__init__`` holds only the version and is allowed)."""
    return sorted((a, b) for a, bs in graph.items() if a.startswith(RUNTIME)
                  for b in bs if not b.startswith(RUNTIME) and b != "mpib_validate")


def test_runtime_imports_nothing_of_the_harness():
    assert upward(import_graph()) == []


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_the_checks_see_a_cycle_and_an_upward_arrow(tmp_path):
    """The checks themselves fail on a tree that has both defects."""
    for rel, text in {
        "mpib_validate/__init__.py": "",
        "mpib_validate/runtime/__init__.py": "",
        "mpib_validate/runtime/a.py": "from mpib_validate.runtime import b\n",
        "mpib_validate/runtime/b.py": "def f():\n    from mpib_validate.runtime.a import x\n"
                                      "    from mpib_validate.cards import trace\n",
        "mpib_validate/cards/__init__.py": "",
        "mpib_validate/cards/trace.py": "from mpib_validate.runtime import a\n",
    }.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    g = import_graph(tmp_path)
    assert upward(g) == [("mpib_validate.runtime.b", "mpib_validate.cards.trace")]
    assert cycles(g) == [["mpib_validate.cards.trace", "mpib_validate.runtime.a",
                          "mpib_validate.runtime.b"]]
