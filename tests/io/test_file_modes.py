"""Files meshsplat writes take the user's umask, like any other program's: under umask 022 checkpoints,
exports, the player page and batch results are readable by others (0644), so a player folder copied to a
web server or a run shared with a group works; a private umask (077) keeps them private."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from _eval_kit import deform, make_avatar, make_run
from meshsplat.export import export_avatar
from meshsplat.fleet.report import write_results
from meshsplat.io.atomic import atomic_write, write_bytes_atomic, write_text_atomic, write_with
from meshsplat.viewer import write_viewer_bundle

pytestmark = pytest.mark.skipif(os.name != "posix", reason="file modes and umask are POSIX")


@pytest.fixture
def umask() -> Iterator[object]:
    old = os.umask(0o022)

    def set_umask(mask: int) -> None:
        os.umask(mask)

    try:
        yield set_umask
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
def test_atomic_writes_take_the_umask(tmp_path, umask, mask):
    umask(mask)
    write_bytes_atomic(tmp_path / "a.bin", b"x")
    write_text_atomic(tmp_path / "b.txt", "x")
    with atomic_write(tmp_path / "c.bin") as fh:
        fh.write(b"x")
    write_with(tmp_path / "d.txt", lambda p: p.write_text("x"))
    expected = 0o666 & ~mask
    assert {p.name: _mode(p) for p in _files(tmp_path)} == dict.fromkeys(["a.bin", "b.txt", "c.bin", "d.txt"], expected)
    plain = tmp_path / "plain.txt"  # what open() makes under the same umask
    plain.write_text("x")
    assert _mode(plain) == expected


def test_runs_exports_player_pages_and_batch_results_are_readable_by_others(tmp_path, umask):
    avatar = make_avatar(n=200)
    run = make_run(avatar, tmp_path / "run", None)
    export_avatar(avatar, tmp_path / "export", formats=("ply", "splat", "spz", "gltf"))
    write_viewer_bundle(avatar, [deform(avatar.mesh.vertices, t) for t in (0.0, 0.5)], tmp_path / "player")
    write_results(tmp_path / "batch", [{"name": "a", "status": "ok"}])
    written = {
        "checkpoint": _files(run / "checkpoints"),
        "export": _files(tmp_path / "export"),
        "player": _files(tmp_path / "player"),
        "batch": _files(tmp_path / "batch"),
    }
    for what, files in written.items():
        assert files, what
        wrong = {str(p.relative_to(tmp_path)): oct(_mode(p)) for p in files if _mode(p) != 0o644}
        assert not wrong, f"{what}: not 0644 under umask 022: {wrong}"
    assert not [p for p in tmp_path.rglob("*.tmp")]  # no temporary file left behind
