"""The README and docs: no links leave the repository, every relative link (and its #anchor) resolves, and
every ``meshsplat[extra]`` they tell a user to install exists."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#+\s+(.*)$", re.M)


def _anchors(md: Path) -> set[str]:
    """The #anchors of a markdown file's headings, as GitHub derives them (lower case, punctuation dropped)."""
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in HEADING.findall(md.read_text())}


# The one address the README may name: PyTorch's index of CPU wheels, in the install command (pip takes
# no other spelling of "the CPU build"). It is an argument to pip, not a link.
README_URLS = {"https://download.pytorch.org/whl/cpu"}


def test_readme_does_not_link_outside_the_repository():
    text = (ROOT / "README.md").read_text()
    urls = set(re.findall(r"https?://[^\s)`'\"]+", text))
    assert urls <= README_URLS, f"the README must not link (or point) outside the repository: {urls - README_URLS}"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc):
    broken = []
    for target in LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        path = (doc.parent / target.split("#")[0]).resolve()
        if not path.exists():
            broken.append(target)
    assert not broken, f"{doc.relative_to(ROOT)}: broken links {broken}"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_anchors_name_a_heading(doc):
    broken = []
    for target in LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target) or "#" not in target:
            continue
        file, anchor = target.split("#", 1)
        path = (doc.parent / file).resolve() if file else doc
        if path.suffix == ".md" and path.exists() and anchor not in _anchors(path):
            broken.append(target)
    assert not broken, f"{doc.relative_to(ROOT)}: links to headings that do not exist {broken}"


def _extras() -> set[str]:
    """The optional-dependency names of pyproject.toml (read without tomllib, which Python 3.10 lacks)."""
    section = (ROOT / "pyproject.toml").read_text().split("[project.optional-dependencies]", 1)[1]
    section = re.split(r"^\[", section, flags=re.M)[0]
    return set(re.findall(r"^([A-Za-z][\w-]*)\s*=", section, re.M))


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_install_commands_name_extras_that_exist(doc):
    # pip only warns about an unknown extra and installs without it: the user finds out at run time
    extras = _extras()
    assert {"track", "video", "cuda"} <= extras, extras
    named = {e.strip() for group in re.findall(r"meshsplat\[([^\]]+)\]", doc.read_text()) for e in group.split(",")}
    assert named <= extras, f"{doc.relative_to(ROOT)}: extras that pyproject.toml does not declare {named - extras}"
