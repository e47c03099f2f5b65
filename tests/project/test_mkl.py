"""MKL's vector math is set up on the importing thread before meshsplat computes anything."""

from __future__ import annotations

import ast
import ctypes
import subprocess
import sys
from pathlib import Path

import pytest
import torch

_LIB = Path(torch.__file__).parent / "lib" / "libtorch_cpu.so"


def _has_vml() -> bool:
    try:
        return hasattr(ctypes.CDLL(str(_LIB)), "vmlGetMode")
    except OSError:
        return False


def _vml_mode_after(code: str) -> int:
    """VML's mode on the main thread of a fresh process after ``code`` (it changes on VML's first call)."""
    probe = f"import ctypes; {code}; print(ctypes.CDLL({str(_LIB)!r}).vmlGetMode())"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(not _has_vml(), reason="this torch build does not use Intel MKL's vector math")
def test_importing_the_checks_sets_up_vector_math_on_this_thread():
    untouched = _vml_mode_after("import torch")
    after_math = _vml_mode_after("import torch; torch.ones(1).sqrt()")
    assert after_math != untouched, "VML's mode no longer tells whether it was set up: revisit this test"
    assert _vml_mode_after("import meshsplat._checks") == after_math
    assert _vml_mode_after("import meshsplat.mesh.geometry") == after_math


PKG = Path(__file__).resolve().parents[2] / "src" / "meshsplat"
EXEMPT = {"meshsplat._mkl", "meshsplat._checks", "meshsplat._device", "meshsplat._typing"}  # no tensor maths


def _module_level(body: list[ast.stmt]):
    """Statements that run at import: the body, and the bodies of module-level if/try blocks."""
    for node in body:
        yield node
        if isinstance(node, ast.If | ast.Try):
            for block in (
                node.body,
                node.orelse,
                getattr(node, "finalbody", []),
                *[h.body for h in getattr(node, "handlers", [])],
            ):
                yield from _module_level(block)


def _graph() -> tuple[dict[str, set[str]], set[str]]:
    """Each package module -> the package modules it imports when imported; the modules importing torch."""
    files = {".".join(p.relative_to(PKG.parent).with_suffix("").parts).removesuffix(".__init__"): p
             for p in PKG.rglob("*.py")}  # fmt: skip
    edges: dict[str, set[str]] = {}
    uses_torch: set[str] = set()
    for name, path in files.items():
        parents = {".".join(name.split(".")[:k]) for k in range(1, name.count(".") + 1)}
        out = set(parents)
        for node in _module_level(ast.parse(path.read_text()).body):
            if isinstance(node, ast.Import):
                out |= {a.name for a in node.names if a.name.startswith("meshsplat")}
                if any(a.name == "torch" for a in node.names):
                    uses_torch.add(name)
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("meshsplat") and not node.level:
                out.add(node.module)
                out |= {f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in files}
        edges[name] = {m for m in out if m in files and m != name}
    return edges, uses_torch


def test_every_module_that_imports_torch_imports_the_set_up():
    edges, uses_torch = _graph()
    missing = []
    for name in sorted(uses_torch - EXEMPT):
        seen, todo = set(), [name]
        while todo:
            m = todo.pop()
            if m not in seen:
                seen.add(m)
                todo.extend(edges.get(m, ()))
        if "meshsplat._mkl" not in seen:
            missing.append(name)
    assert len(uses_torch) > 50
    assert not missing, f"import meshsplat._checks (or _mkl) in: {missing}"
