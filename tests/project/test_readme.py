"""The README's Python example runs as written (in a temporary folder) and makes what its comments say."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"


def python_example() -> str:
    """The first ```python block of the README's "## Python" section."""
    section = README.read_text().split("\n## Python\n", 1)[1].split("\n## ", 1)[0]
    found = re.search(r"```python\n(.*?)```", section, re.S)
    assert found, "README.md: the Python section has no ```python block"
    return found.group(1)


def test_the_example_uses_only_the_front_door():
    code = python_example()
    assert code.startswith("import meshsplat as ms\n")
    assert "from meshsplat" not in code and code.count("import ") == 1
    import meshsplat as ms

    used = set(re.findall(r"\bms\.(\w+)", code))
    assert used <= set(ms.__all__), used - set(ms.__all__)
    assert {
        "synthesize",
        "open_capture",
        "train_avatar",
        "load_avatar",
        "orbit_cameras",
        "AnimationSource",
        "load_animation",
        "render_animation",
        "evaluate",
        "export_avatar",
        "write_viewer",
    } <= used


@pytest.mark.slow
def test_the_example_runs_as_written(assets, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(python_example(), str(README), "exec"), scope)
    out = tmp_path / "out"
    assert scope["image"].shape == (64, 64, 3) and float(scope["image"].max()) > 0
    assert sorted(p.name for p in (out / "run" / "checkpoints").iterdir())[-1] == "ckpt_00000030.pt"
    assert len(list((out / "turntable" / "frames").glob("*.png"))) == len(scope["anim"].frames) >= 2
    assert set(scope["metrics"]["splits"]) >= {"test_frames", "test_views"}
    assert (out / "run" / "eval" / "metrics.json").is_file() and (out / "run" / "eval" / "report.html").is_file()
    assert {"avatar.ply", "embedding.json", "canonical_mesh.obj"} <= {p.name for p in (out / "export").iterdir()}
    assert (out / "viewer" / "index.html").is_file()
