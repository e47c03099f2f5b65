"""Read the manual: list its pages, or print one (the docs/*.md files that help texts and errors name).

Examples:
  meshsplat docs                      # the pages, with their titles, and the folder they are in
  meshsplat docs own-video            # print docs/own-video.md (also: docs/own-video.md, own-video.md)
  meshsplat docs config --path        # where the file is, to open in an editor or a Markdown viewer
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from meshsplat.errors import MeshsplatError

__all__ = ["add_arguments", "run", "docs_folder", "topics", "topic_name"]

_PACKAGE = Path(__file__).resolve().parents[1]


def docs_folder() -> Path | None:
    """The manual's folder: ``meshsplat/docs`` in an installed package (the wheel ships it), else the
    ``docs`` folder of the checkout an editable install runs from; None when neither exists."""
    shipped = _PACKAGE / "docs"
    if (shipped / "quality.md").is_file():
        return shipped
    checkout = _PACKAGE.parents[1]  # src/meshsplat -> the repository
    if (checkout / "pyproject.toml").is_file() and (checkout / "docs" / "quality.md").is_file():
        return checkout / "docs"
    return None


def _name(rel: Path) -> str:
    """A page's topic: its path below docs without ``.md``; a folder's README is the folder."""
    parts = rel.with_suffix("").parts
    return "/".join(parts[:-1]) if len(parts) > 1 and parts[-1] == "README" else "/".join(parts)


def topics() -> dict[str, Path]:
    """Topic name -> file, sorted by name (empty when no manual is found)."""
    folder = docs_folder()
    if folder is None:
        return {}
    found = {_name(p.relative_to(folder)): p for p in folder.rglob("*.md")}
    return dict(sorted(found.items()))


def topic_name(text: str) -> str:
    """The topic a user typed, as help texts spell pages: ``quality``, ``quality.md``, ``docs/quality.md``,
    ``docs/quality.md#a-heading`` all name ``quality``."""
    name = text.strip().split("#", 1)[0].replace("\\", "/").strip("/").lower()
    name = name.removeprefix("docs/")
    name = name.removesuffix(".md")
    return name.removesuffix("/readme")


def _title(path: Path) -> str:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    return ""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    names = list(topics())
    parser.add_argument(
        "topic",
        nargs="?",
        type=topic_name,
        choices=names or None,
        metavar="TOPIC",
        help="the page to print (as help texts name it: quality, docs/quality.md, ...); none: list the pages",
    )
    parser.add_argument("--path", action="store_true", help="print the file's path instead of its text")


def run(args: argparse.Namespace) -> int:
    pages = topics()
    if not pages:
        raise MeshsplatError(
            f"the manual is not installed next to the package ({_PACKAGE / 'docs'}); reinstall meshsplat"
        )
    if args.topic is None:
        folder = docs_folder()
        if args.path:
            print(folder)
            return 0
        width = max(len(n) for n in pages)
        for name, path in pages.items():
            print(f"{name:<{width}}  {_title(path)}")
        print(f"\n{len(pages)} pages in {folder}; `meshsplat docs TOPIC` prints one")
        return 0
    if args.topic not in pages:  # no choices were known when the parser was built
        raise MeshsplatError(f"no page {args.topic!r} in the manual; `meshsplat docs` lists them")
    path = pages[args.topic]
    text = f"{path}\n" if args.path else path.read_text(encoding="utf-8")
    encoding = sys.stdout.encoding or "utf-8"  # a console that cannot show a character gets "?", not an error
    print(text.encode(encoding, "replace").decode(encoding), end="")
    return 0
