"""No import circle among the package's modules: the graph of every ``import`` in ``dpc_jax``, read from
the source (at module level and inside functions alike, since a lazy import ties two modules as much as an
eager one), has no strongly connected component of more than one module."""

from __future__ import annotations

import ast
from pathlib import Path

import dpc_jax

PACKAGE = Path(dpc_jax.__file__).resolve().parent


def module_files(package: Path) -> dict[str, Path]:
    """Dotted module name → its file, for every ``.py`` under ``package`` (a package is its ``__init__``)."""
    files = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return files


def _known(name: str, modules: dict[str, Path]) -> str | None:
    """The deepest module of ``modules`` that ``name`` (a dotted module or attribute path) lies in."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_graph(package: Path) -> dict[str, set[str]]:
    """Module → the modules of the package it imports anywhere in its source. ``import a.b`` imports ``a.b``;
    ``from a import b`` imports ``a.b`` when that is a module, else ``a``; relative imports are resolved."""
    modules = module_files(package)
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                # ``from .. import x``: ``node.level`` dots, the first of which is the module's own package.
                parent = here[:len(here) - node.level + 1] if node.level else []
                base = ".".join([*parent, *([node.module] if node.module else [])])
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                           for alias in node.names]
            else:
                continue
            graph[name] |= {known for target in targets if (known := _known(target, modules)) is not None}
        graph[name].discard(name)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = stack[stack.index(node):]
            del stack[stack.index(node):]
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def test_the_graph_sees_every_form_of_import(tmp_path: Path) -> None:
    """A made-up package whose circles close through each form: a lazy ``import``, ``from . import``, a
    relative ``from .m import name`` and ``from pkg import module``; and a chain that is no circle."""
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    sources = {
        "__init__.py": "", "sub/__init__.py": "",
        "a.py": "def f():\n    import pkg.b\n",
        "b.py": "from . import c\n",
        "c.py": "from .a import f\n",
        "sub/d.py": "from pkg import sub\nfrom pkg.sub import e\n",
        "sub/e.py": "from ..sub import d\n",
        "f.py": "import pkg.a\nfrom pkg.sub.e import name\n",
    }
    for file, text in sources.items():
        (package / file).write_text(text)
    graph = import_graph(package)
    assert graph["pkg.sub.d"] == {"pkg.sub", "pkg.sub.e"} and graph["pkg.f"] == {"pkg.a", "pkg.sub.e"}
    assert cycles(graph) == [["pkg.a", "pkg.b", "pkg.c"], ["pkg.sub.d", "pkg.sub.e"]]


def test_no_module_of_the_package_imports_one_that_imports_it_back() -> None:
    found = cycles(import_graph(PACKAGE))
    assert not found, ("import circles (each: modules that import one another, directly or through the "
                       "others):\n" + "\n".join(", ".join(component) for component in found))
