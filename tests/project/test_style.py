"""House rules a machine checks: ruff's linter and formatter (settings in pyproject.toml) are clean."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _ruff(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")
    if exe is None:
        pytest.fail("ruff is not installed: it comes with the [dev] extra (make test installs it)")
    return subprocess.run([exe, *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_ruff_lint_is_clean():
    res = _ruff("check", "--no-cache", "src", "tests", "bench")
    assert res.returncode == 0, res.stdout[-5000:] + res.stderr[-2000:]


def test_ruff_format_is_clean():
    res = _ruff("format", "--no-cache", "--check", "src", "tests", "bench")
    assert res.returncode == 0, res.stdout[-5000:] + res.stderr[-2000:]
