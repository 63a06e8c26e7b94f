"""The import graph of the package runs one way: no cycle (imports inside functions included), and no library
module imports a command-line module. Read from the source (AST), so nothing is imported to check it.

Importing `pkg.sub` runs `pkg/__init__.py` first (and whatever that imports), so an import of a submodule counts
as an import of each package above it too, except the importer's own packages (already being imported)."""

from __future__ import annotations

import ast
import os

import pytest

PACKAGE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bridge_jax")
# Modules with a `main()` behind a console command; `demo` is the one command that composes two others (it
# trains, then evaluates), like a `main.py` calling `train`.
COMMAND_MODULES = {f"bridge_jax.{m}" for m in ("train", "evaluate", "predict", "export", "convert", "demo")}
COMPOSING_COMMANDS = {"bridge_jax.demo"}


def _modules(root: str = PACKAGE_DIR) -> dict[str, str]:
    """{dotted module name: file} of every .py file under `root`."""
    out = {}
    base = os.path.dirname(root)
    for folder, _, names in os.walk(root):
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                mod = os.path.relpath(path, base)[:-3].replace(os.sep, ".")
                out[mod[:-len(".__init__")] if mod.endswith(".__init__") else mod] = path
    return out


def _packages_above(module: str, mods: dict[str, str]) -> set[str]:
    """The packages whose `__init__` runs when `module` is imported: "a.b.c" -> {"a", "a.b"} (those in `mods`)."""
    parts = module.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))} & set(mods)


def import_graph(root: str = PACKAGE_DIR) -> dict[str, set[str]]:
    """{module: the package modules it imports}, from every import statement (top level and inside functions);
    `from pkg import name` counts as importing `pkg.name` when that is a module, else `pkg`; importing `pkg.sub`
    counts as importing `pkg` (its `__init__`) too, unless the importer is inside `pkg`."""
    mods = _modules(root)

    def owner(name: str):
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for mod, path in mods.items():
        with open(path) as f:
            tree = ast.parse(f.read(), path)
        package = mod if path.endswith("__init__.py") else mod.rpartition(".")[0]
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                deps.update(owner(a.name) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative import
                    parts = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                    base = ".".join(parts + ([base] if base else []))
                deps.update(owner(f"{base}.{a.name}") if f"{base}.{a.name}" in mods else owner(base)
                            for a in node.names)
        deps = {d for d in deps if d}
        own = _packages_above(mod, mods) | ({mod} if path.endswith("__init__.py") else set())
        deps |= {p for d in deps for p in _packages_above(d, mods)} - own
        graph[mod] = {d for d in deps if d != mod}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_package_has_no_import_cycle():
    assert cycles(import_graph()) == []


def test_no_library_module_imports_a_command_line_module():
    graph = import_graph()
    assert COMMAND_MODULES <= set(graph)
    bad = {m: sorted(deps & COMMAND_MODULES) for m, deps in graph.items()
           if deps & COMMAND_MODULES and m not in COMPOSING_COMMANDS}
    assert bad == {}


def test_zoo_does_not_reach_bench_and_setup_and_configs_are_apart():
    graph = import_graph()

    def reach(start):
        seen, todo = set(), [start]
        while todo:
            for d in graph.get(todo.pop(), ()):
                if d not in seen:
                    seen.add(d)
                    todo.append(d)
        return seen

    assert not {m for m in reach("bridge_jax.zoo") if m.startswith("bridge_jax.bench")}
    assert not {m for m in reach("bridge_jax.setup") if m.startswith("bridge_jax.configs")}


def test_a_submodule_import_counts_its_package_init(tmp_path):
    """`pkg/__init__.py` importing `pkg.b`, which imports `a`, while `a` imports `pkg.c`: a cycle at run time
    (importing pkg.c runs pkg's __init__, which imports pkg.b, which imports a)."""
    pkg = tmp_path / "bridge_jax"
    (pkg / "pkg").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from bridge_jax.pkg import c\n")
    (pkg / "pkg" / "__init__.py").write_text("from bridge_jax.pkg.b import x\n")
    (pkg / "pkg" / "b.py").write_text("from bridge_jax import a\nfrom bridge_jax.pkg import c\n")
    (pkg / "pkg" / "c.py").write_text("")
    assert cycles(import_graph(str(pkg))) == [["bridge_jax.a", "bridge_jax.pkg", "bridge_jax.pkg.b"]]


@pytest.mark.parametrize("source, expected", [
    ("def f():\n    from bridge_jax import b\n", [["bridge_jax.a", "bridge_jax.b"]]),  # deferred imports count
    ("import bridge_jax.b\n", [["bridge_jax.a", "bridge_jax.b"]]),
    ("from . import c\n", []),
])
def test_the_checks_see_function_level_and_relative_imports(tmp_path, source, expected):
    pkg = tmp_path / "bridge_jax"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(source)
    (pkg / "b.py").write_text("from bridge_jax.a import x\n")
    (pkg / "c.py").write_text("")
    assert cycles(import_graph(str(pkg))) == expected
