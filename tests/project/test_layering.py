"""The package's import layering (docs/architecture.md): each unit imports only units on lines above it,
and no module imports itself through others (no import circles).

Every import counts: those under ``if TYPE_CHECKING:`` (annotations only) and function-local ones too.
"""

import ast
from collections.abc import Iterator
from pathlib import Path

PKG = Path(__file__).resolve().parents[2] / "src" / "meshsplat"

LAYERS = [
    ("errors", "_mkl"),
    ("_checks", "_typing", "_device", "_numba", "paths", "plausible"),
    ("_numba_ahead",),
    ("io", "metrics"),
    ("camera", "drivers"),
    ("mesh",),
    ("embedding",),
    ("render",),
    ("gaussians",),
    ("data",),
    ("animation",),
    ("run_folder",),
    ("train",),
    ("synth", "eval", "export", "animate"),
    ("demo", "viewer", "track"),
    ("pipeline", "fleet"),
    ("cli",),
]
RANK = {unit: i for i, units in enumerate(LAYERS) for unit in units}


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "meshsplat"


def _imports(tree: ast.AST) -> Iterator[tuple[str, int]]:
    """``(module, line)`` of every import of a meshsplat module, wherever it stands (``if TYPE_CHECKING:``
    blocks and function bodies included); ``from meshsplat.x import y`` names ``meshsplat.x.y`` when
    ``y`` is a module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "meshsplat" and not node.level:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                yield (sub if sub in MODULES else node.module), node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "meshsplat":
                    yield a.name, node.lineno


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PKG.rglob("*.py")}


def test_every_unit_has_a_layer():
    units = {_unit(".".join(p.relative_to(PKG.parent).with_suffix("").parts)) for p in PKG.rglob("*.py")}
    units -= {"meshsplat", "__init__", "__main__"}
    assert units <= set(RANK), f"add {sorted(units - set(RANK))} to LAYERS and docs/architecture.md"


def test_imports_flow_one_way():
    upward = []
    for path in sorted(PKG.rglob("*.py")):
        me = _unit(".".join(path.relative_to(PKG.parent).with_suffix("").parts))
        if me not in RANK:
            continue
        for module, line in _imports(ast.parse(path.read_text())):
            if module == "meshsplat":
                continue  # the front door (``from meshsplat import __version__``) sits outside the lines
            other = _unit(module)
            if other != me and other in RANK and RANK[other] >= RANK[me]:
                upward.append(f"{path.relative_to(PKG)}:{line} ({me}) imports {module} ({other})")
    assert not upward, "imports against the layering:\n" + "\n".join(upward)


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other, directly or through others (the strongly connected
    components of more than one module, Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles = []

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
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1 or v in graph.get(v, ()):
                circles.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def test_import_circles_are_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert sorted(import_circles(graph)) == [["a", "b", "c"], ["e"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    graph = {
        me: {m for m, _ in _imports(ast.parse(path.read_text())) if m in MODULES and m != me}
        for me, path in MODULES.items()
    }
    circles = import_circles(graph)
    assert not circles, "modules importing each other:\n" + "\n".join(" <-> ".join(c) for c in circles)


# Function-local imports of the package's own modules hide the import graph and leave nothing a cycle needs:
# import them at the top. Lazy imports stay for optional heavy dependencies (gsplat, smplx, matplotlib, ...).
LOCAL_IMPORT_ALLOWED: set[str] = set()


def test_own_modules_are_imported_at_the_top():
    local = []
    for path in sorted(PKG.rglob("*.py")):
        for fn in ast.walk(ast.parse(path.read_text())):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                names = (
                    [node.module or ""]
                    if isinstance(node, ast.ImportFrom)
                    else [a.name for a in node.names]
                    if isinstance(node, ast.Import)
                    else []
                )
                if any(n.startswith("meshsplat") for n in names):
                    where = f"{path.relative_to(PKG)}:{node.lineno}"
                    if str(path.relative_to(PKG)) not in LOCAL_IMPORT_ALLOWED:
                        local.append(where)
    assert not local, "function-local imports of meshsplat modules (move them to the top):\n" + "\n".join(local)
