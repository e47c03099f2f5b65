"""MKL's vector math is set up on the importing thread before meshsplat computes anything."""

from __future__ import annotations

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
