"""`meshsplat` command line: one module per subcommand under meshsplat.cli.

Each subcommand module defines ``add_arguments(parser)`` and ``run(args) -> int``
and a docstring whose first paragraph is its help. A command whose module fails to import is listed
with its error and, when run, says why in one line (``--debug``, before or after the command: the
traceback), never vanishes. User errors (MeshsplatError,
missing files) print one clear line and exit 2, never a traceback. meshsplat's own warnings
(``MeshsplatWarning``) print as one ``note:`` line each, once per command, without the file and line
they were raised at; other packages' warnings print as Python prints them.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

from meshsplat import __version__
from meshsplat.errors import MeshsplatError, MeshsplatWarning, os_error_text

# name -> module under meshsplat.cli (imported only when that command runs, or for --help)
COMMANDS = {
    "track": "track_cmd",
    "synth": "synth_cmd",
    "import": "import_cmd",
    "train": "train_cmd",
    "eval": "eval_cmd",
    "render": "render_cmd",
    "export": "export_cmd",
    "demo": "demo_cmd",
    "view": "view_cmd",
    "batch": "batch_cmd",
    "completion": "completion_cmd",
    "docs": "docs_cmd",
}
DEBUG_HELP = "show full tracebacks (before or after the command)"


def _load(name: str):
    return importlib.import_module(f"meshsplat.cli.{COMMANDS[name]}")


def _summary(doc: str | None) -> str | None:
    """A command's one-line help: the first paragraph of its module docstring, on one line."""
    first = (doc or "").strip().split("\n\n")[0]
    return " ".join(first.split()) or None


def _import_error(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="meshsplat",
        description="Mesh-embedded Gaussian avatars. The manual: `meshsplat docs` (the docs/*.md pages help texts name).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"meshsplat {__version__}")
    parser.add_argument("--debug", action="store_true", help=DEBUG_HELP)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        if only is not None and name != only:
            sub.add_parser(name)
            continue
        try:
            mod = _load(name)
        except Exception as exc:  # noqa: BLE001 - listed with its error; running it reports the error
            sub.add_parser(name, help=f"(cannot load: {_import_error(exc)})")
            continue
        p = sub.add_parser(
            name,
            help=_summary(mod.__doc__),
            description=(mod.__doc__ or "").strip(),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        # after the subcommand too; SUPPRESS keeps the value given before it
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=DEBUG_HELP)
        mod.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if a in COMMANDS), None)
    if command is not None:
        try:
            _load(command)
        except Exception as exc:
            if "--debug" in argv:
                raise
            print(
                f"meshsplat {command}: error: the command could not be loaded ({_import_error(exc)}); "
                "reinstall meshsplat with the extras this command needs (--debug shows the traceback)",
                file=sys.stderr,
            )
            return 2
    parser = build_parser(only=command if command and "-h" not in argv and "--help" not in argv else None)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 1
    try:
        with _notes():
            return int(_load(args.command).run(args) or 0)
    except (MeshsplatError, OSError, MemoryError) as exc:
        if args.debug:
            raise
        print(f"meshsplat {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"meshsplat {args.command}: interrupted" + (f": {exc}" if str(exc) else ""), file=sys.stderr)
        return 128 + int(getattr(exc, "signum", signal.SIGINT))


@contextmanager
def _notes() -> Iterator[None]:
    """While a command runs: each distinct ``MeshsplatWarning`` prints once to stderr as ``note: TEXT``
    (whitespace folded to one line, no file:line); other warnings go to Python's usual display."""
    seen: set[str] = set()
    with warnings.catch_warnings():
        shown = warnings.showwarning  # the display in force (Python's, or a test harness's)

        def show(
            message: Warning | str,
            category: type[Warning],
            filename: str,
            lineno: int,
            file: TextIO | None = None,
            line: str | None = None,
        ) -> None:
            if not issubclass(category, MeshsplatWarning):
                shown(message, category, filename, lineno, file, line)
                return
            text = " ".join(str(message).split())
            if text not in seen:
                seen.add(text)
                print(f"note: {text}", file=sys.stderr, flush=True)

        warnings.showwarning = show
        warnings.simplefilter("always", MeshsplatWarning)  # the set above keeps each one once
        yield


def _one_line(exc: BaseException) -> str:
    """The user-facing text of an error: OS errors (a full disk, a read-only or occupied output
    location) say what failed on which path and what to do; memory errors say what to reduce."""
    if isinstance(exc, MemoryError):
        return "out of memory; reduce the request (image size, frame count, Gaussians; see docs/limits.md)"
    if isinstance(exc, OSError) and not isinstance(exc, MeshsplatError):
        return os_error_text(exc)
    return str(exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
