"""Static types: mypy (a dev dependency) over the package, with the settings in pyproject.toml ([tool.mypy])."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_mypy_is_clean():
    proc = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]


def _incomplete_public_signatures() -> list[str]:
    """Public functions and methods (outside ``_private`` modules) missing a parameter or return annotation."""
    import ast

    found = []
    pkg = ROOT / "src" / "meshsplat"
    for path in sorted(pkg.rglob("*.py")):
        rel = path.relative_to(pkg)
        if any(part.startswith("_") and part != "__init__.py" for part in rel.parts):
            continue

        def visit(body: list, cls: str | None = None, rel: Path = rel) -> None:
            for node in body:
                if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                    visit(node.body, node.name, rel)
                elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    if node.name.startswith("_") and node.name != "__init__":
                        continue
                    a = node.args
                    params = a.posonlyargs + a.args + a.kwonlyargs + [x for x in (a.vararg, a.kwarg) if x]
                    if cls and params and params[0].arg in ("self", "cls"):
                        params = params[1:]
                    if any(p.annotation is None for p in params) or node.returns is None:
                        found.append(f"{rel}:{node.lineno} {cls + '.' if cls else ''}{node.name}")

        visit(ast.parse(path.read_text()).body)
    return found


def test_public_signatures_are_annotated():
    missing = _incomplete_public_signatures()
    assert not missing, "public functions with incomplete annotations:\n" + "\n".join(missing)
