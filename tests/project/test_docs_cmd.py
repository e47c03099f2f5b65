"""`meshsplat docs`: the manual's pages from the package, under the names help texts and errors give them."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from meshsplat.cli import docs_cmd
from meshsplat.cli.main import main

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src" / "meshsplat"


def test_every_page_the_code_names_is_a_topic():
    named = {m for p in SRC.rglob("*.py") for m in re.findall(r"docs/[\w/-]+\.md", p.read_text())}
    assert len(named) >= 5, named
    pages = docs_cmd.topics()
    missing = sorted(n for n in named if docs_cmd.topic_name(n) not in pages)
    assert not missing, f"help texts name pages `meshsplat docs` cannot show: {missing}"


def test_topic_names_as_users_type_them():
    for typed in ("quality", "quality.md", "docs/quality.md", "docs/quality.md#watching-training", "Quality"):
        assert docs_cmd.topic_name(typed) == "quality"
    assert docs_cmd.topic_name("docs/formats/README.md") == "formats"
    assert docs_cmd.topic_name("formats/meshseq") == "formats/meshseq"


def test_list_print_and_path(capsys):
    assert main(["docs"]) == 0
    listing = capsys.readouterr().out
    assert re.search(r"^own-video +From your own video$", listing, re.M), listing
    assert "formats/meshseq" in listing and "pages in" in listing
    assert main(["docs", "docs/quality.md"]) == 0
    assert capsys.readouterr().out == (ROOT / "docs" / "quality.md").read_text()
    assert main(["docs", "config", "--path"]) == 0
    assert Path(capsys.readouterr().out.strip()) == ROOT / "docs" / "config.md"


def test_unknown_page_is_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["docs", "nope"])
    assert exc.value.code == 2 and "invalid choice: 'nope'" in capsys.readouterr().err


def test_the_shipped_manual_comes_first(tmp_path, monkeypatch):
    package = tmp_path / "site-packages" / "meshsplat"
    (package / "docs" / "formats").mkdir(parents=True)
    (package / "docs" / "quality.md").write_text("# Shipped\n")
    (package / "docs" / "formats" / "README.md").write_text("# Formats\n")
    monkeypatch.setattr(docs_cmd, "_PACKAGE", package)
    assert docs_cmd.docs_folder() == package / "docs"
    assert docs_cmd.topics() == {"formats": package / "docs/formats/README.md", "quality": package / "docs/quality.md"}
    (package / "docs" / "quality.md").unlink()
    (package / "docs" / "formats" / "README.md").unlink()
    assert docs_cmd.docs_folder() is None and docs_cmd.topics() == {}
