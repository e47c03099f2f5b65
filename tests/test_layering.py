"""The package's import layering (docs/architecture.md): each unit imports only units on lines above it.

Imports under ``if TYPE_CHECKING:`` (annotations only) are not counted; function-local imports are.
"""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "src" / "meshsplat"

LAYERS = [
    ("errors",),
    ("_checks", "_mkl", "_typing", "_device", "_numba", "paths", "plausible"),
    ("io", "metrics"),
    ("camera", "drivers"),
    ("mesh",),
    ("embedding",),
    ("render",),
    ("gaussians",),
    ("data",),
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


def _imports(tree: ast.AST):
    """Imported meshsplat modules, skipping ``if TYPE_CHECKING:`` blocks."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING":
            continue
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("meshsplat.") and not node.level:
            yield node.module, node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("meshsplat."):
                    yield a.name, node.lineno
        else:
            yield from _imports(node)


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
            other = _unit(module)
            if other != me and other in RANK and RANK[other] >= RANK[me]:
                upward.append(f"{path.relative_to(PKG)}:{line} ({me}) imports {module} ({other})")
    assert not upward, "imports against the layering:\n" + "\n".join(upward)


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
