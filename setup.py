"""The wheel carries the manual: docs/**/*.md copied into meshsplat/docs at build time, so `meshsplat docs`
(and the docs/*.md pages that help texts and errors name) work from an installed package. Everything
else about the build is in pyproject.toml."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

DOCS = Path(__file__).resolve().parent / "docs"


class BuildPyWithDocs(build_py):
    def run(self):
        super().run()
        if not DOCS.is_dir():  # building from an sdist made without them
            return
        target = Path(self.build_lib) / "meshsplat" / "docs"
        for page in sorted(DOCS.rglob("*.md")):
            out = target / page.relative_to(DOCS)
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(page, out)


setup(cmdclass={"build_py": BuildPyWithDocs})
