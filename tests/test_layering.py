"""The package's imports, read from the source with ``ast`` (nothing is imported):

- every import, deferred (in a function) or only for type checking included, points down
  the stage packages' layer order that docs/architecture.md states ("Layers, bottom to
  top"), or stays within its own layer;
- no module uses another module's private (``_name``) function, class or constant;
- ``solver/``: no import cycle among its modules (deferred, function-level imports
  included), no module imports the ``perfros_bag.solver`` package itself (its
  ``__init__`` only re-exports them).

Each check is tried on a small made-up graph first, so that it is known to fail when it
should.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "perfros_bag"


@dataclass(frozen=True)
class Import:
    src: str  # the importing module
    dst: str  # the imported module (own modules only, resolved to a file of the package)
    line: int
    deferred: bool  # inside a function
    typing: bool  # under ``if TYPE_CHECKING:`` (never runs)
    names: tuple[str, ...]  # ``from dst import names`` (empty for ``import dst``)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


Where = tuple[ast.Import | ast.ImportFrom, bool, bool]


def _import_nodes(tree: ast.AST) -> Iterator[Where]:
    """Each import statement, with whether it sits inside a function and whether under
    ``if TYPE_CHECKING:``."""
    def walk(node: ast.AST, in_function: bool, typing: bool) -> Iterator[Where]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import | ast.ImportFrom):
                yield child, in_function, typing
            elif isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for stmt in child.body:
                    yield from walk(stmt, in_function, True)
                for stmt in child.orelse:
                    yield from walk(stmt, in_function, typing)
            elif isinstance(child, ast.stmt):  # expressions hold no import statement
                inner = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
                yield from walk(child, inner, typing)
    return walk(tree, False, False)


@functools.cache
def _parse(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), str(path))


def module_imports(name: str, path: Path, known: Mapping[str, Path]) -> Iterator[Import]:
    """Every import of an own module by ``name``."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node, deferred, typing in _import_nodes(_parse(path)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in known:
                    yield Import(name, alias.name, node.lineno, deferred, typing, ())
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
            if base not in known:
                continue
            plain = tuple(a.name for a in node.names if f"{base}.{a.name}" not in known)
            for alias in node.names:  # ``from pkg import submodule``
                if f"{base}.{alias.name}" in known:
                    yield Import(name, f"{base}.{alias.name}", node.lineno, deferred, typing, ())
            if plain:
                yield Import(name, base, node.lineno, deferred, typing, plain)


def imports(known: Mapping[str, Path], *, typing: bool = False) -> Iterator[Import]:
    """Every run-time import of an own module by every module of ``known`` (with
    ``typing``, those under ``if TYPE_CHECKING:`` too)."""
    for name, path in known.items():
        yield from (i for i in module_imports(name, path, known) if typing or not i.typing)


#: the layers, bottom to top (docs/architecture.md states the same line)
LAYERS = ("shared", "system", "cpu", "ingest", "characterisation", "fitting", "solver", "validation", "rosrun",
          "sweep", "export", "casestudy", "tune", "watch", "report", "cli")
#: the package root's own modules: the shared helpers, and the entry points with the public API
ROOT_LAYERS = {"errors": "shared", "limits": "shared", "fileio": "shared", "doccheck": "shared",
               "entry": "cli", "__main__": "cli", "": "cli"}


def layer_of(module: str) -> str:
    """``perfros_bag.solver.exact`` -> ``solver``; a root module by :data:`ROOT_LAYERS`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else ROOT_LAYERS[parts[1] if len(parts) > 1 else ""]


def upward(found: Iterator[Import] | list[Import], order: tuple[str, ...] = LAYERS) -> list[str]:
    """``src:line -> dst (layer -> higher layer)`` for each import that points up ``order``."""
    rank = {name: i for i, name in enumerate(order)}
    out = []
    for imp in found:
        a, b = layer_of(imp.src), layer_of(imp.dst)
        if rank[b] > rank[a]:
            out.append(f"{imp.src}:{imp.line} -> {imp.dst} ({a} -> {b})")
    return sorted(out)


def cycles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
    return sorted(found)


def _is_submodule(path: Path, name: str) -> bool:
    """Is ``name`` a module of the package at ``path`` (a compiled extension such as
    ``ingest/_sqlitecells``)?"""
    return path.name == "__init__.py" and any(path.parent.glob(f"{name}.*"))


def private_uses(known: Mapping[str, Path]) -> list[str]:
    """``module:line name`` for every use of another own module's private name: ``from m
    import _x`` or ``m._x`` where ``m`` names an own module. A leading underscore on a
    module (``_lazy``, ``_app``) is the package's business: importing from it is allowed."""
    out = []
    for imp in imports(known):
        for n in imp.names:
            if n.startswith("_") and not n.startswith("__") and imp.dst != imp.src \
                    and not _is_submodule(known[imp.dst], n):
                out.append(f"{imp.src}:{imp.line} {imp.dst}.{n}")
    for name, path in known.items():
        aliases: dict[str, str] = {}  # a local name -> the own module it stands for
        whole = [imp for imp in module_imports(name, path, known) if not imp.names]
        for node in ast.walk(_parse(path)):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in known:
                        aliases[alias.asname or alias.name] = alias.name
            elif isinstance(node, ast.ImportFrom):
                for imp in whole:
                    if imp.line == node.lineno:
                        local = next((a.asname or a.name for a in node.names
                                      if imp.dst.endswith(f".{a.name}")), imp.dst.rsplit(".", 1)[-1])
                        aliases[local] = imp.dst
        for node in ast.walk(_parse(path)):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                    and aliases.get(node.value.id, name) != name \
                    and node.attr.startswith("_") and not node.attr.startswith("__"):
                out.append(f"{name}:{node.lineno} {aliases[node.value.id]}.{node.attr}")
    return sorted(out)


# ---- the checks, tried on made-up cases first ---------------------------------------------

def test_cycles_finds_a_cycle_through_a_deferred_import_and_none_in_a_chain() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_private_uses_and_imports_on_a_made_up_package(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "low.py").write_text("def _hidden():\n    return 1\n\ndef shown():\n    return _hidden()\n")
    (pkg / "high.py").write_text("from pkg import low as lo\n\n\ndef f():\n    from pkg.low import _hidden\n"
                                 "    return lo._hidden() + _hidden() + lo.shown()\n")
    known = {"pkg": pkg / "__init__.py", "pkg.low": pkg / "low.py", "pkg.high": pkg / "high.py"}
    got = sorted(imports(known), key=lambda i: (i.line, i.names))
    assert [(i.src, i.dst, i.deferred) for i in got] == [("pkg.high", "pkg.low", False), ("pkg.high", "pkg.low", True)]
    assert private_uses(known) == ["pkg.high:5 pkg.low._hidden", "pkg.high:6 pkg.low._hidden"]


def test_upward_finds_an_import_of_a_higher_layer_and_passes_a_lower_one() -> None:
    down = Import("perfros_bag.tune.loop", "perfros_bag.sweep.deploy", 3, True, False, ("deploy",))
    up = Import("perfros_bag.tune.loop", "perfros_bag.report.tune_plots", 9, True, False, ("plot_tune",))
    root = Import("perfros_bag.system.types", "perfros_bag.fileio", 1, False, False, ("read_json",))
    assert upward([down, root]) == []
    assert upward([down, up]) == ["perfros_bag.tune.loop:9 -> perfros_bag.report.tune_plots (tune -> report)"]


# ---- the package ---------------------------------------------------------------------------

def test_solver_has_no_import_cycle() -> None:
    known = modules()
    graph: dict[str, set[str]] = {}
    for imp in imports(known):
        if imp.src.startswith("perfros_bag.solver") and imp.dst.startswith("perfros_bag.solver") \
                and imp.src != imp.dst:
            graph.setdefault(imp.src, set()).add(imp.dst)
    assert cycles(graph) == []


def test_no_solver_module_imports_the_solver_package() -> None:
    """``perfros_bag.solver`` (its ``__init__``) re-exports the modules: one of them importing
    it back would be a cycle waiting for a name to move."""
    back = [f"{i.src}:{i.line}" for i in imports(modules())
            if i.dst == "perfros_bag.solver" and i.src.startswith("perfros_bag.solver.")]
    assert back == []


def test_no_module_uses_another_modules_private_names() -> None:
    assert private_uses(modules()) == []


def test_every_package_has_a_layer_and_docs_state_the_same_order() -> None:
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert packages <= set(LAYERS), f"a new stage package needs its place in LAYERS: {packages - set(LAYERS)}"
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    stated = [line for line in text.splitlines() if line.startswith("Layers, bottom to top:")]
    assert len(stated) == 1, "docs/architecture.md states the layers on one line 'Layers, bottom to top: ...'"
    names = [w.strip(" `.") for w in stated[0].split(":", 1)[1].split("<")]
    assert tuple(names) == LAYERS


def test_no_import_points_up_the_layers() -> None:
    assert upward(imports(modules(), typing=True)) == []
