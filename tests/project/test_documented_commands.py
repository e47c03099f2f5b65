"""Every ``meshsplat ...`` command written in README.md and docs/**/*.md parses with the real CLI, and the
README's command-line chain (synth -> train -> eval -> render -> export -> view) runs at tiny sizes.

Commands are taken from fenced code blocks (one per line; ``\\`` continues a line, ``# comments`` and a
``$ `` prompt are dropped) and from inline code spans. Shell placeholders in capitals (``DATA``, ``RUN``,
``N``) stand for a value: as the value of an option with choices or a type they become a valid one. A
usage synopsis (``[--rig a|b|c]``, ``...``) is checked once per alternative. An inline span that names
no positional argument (``meshsplat train --set section.key=value``, ``meshsplat export --format``) is a
reference to a command or flag: its subcommand and flags must exist and given choices be valid.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import itertools
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

from meshsplat.animation import ANIMATION_KINDS
from meshsplat.cli.main import COMMANDS, build_parser, main
from meshsplat.train import DEFAULT_RECIPE, apply_overrides, recipe_config

ROOT = Path(__file__).resolve().parents[2]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*$")


@dataclass(frozen=True)
class DocCommand:
    where: str  # "README.md:56"
    text: str  # as written, continuation lines joined, comment and prompt dropped
    inline: bool  # from an inline code span (else a fenced code block)


def fenced_commands(text: str, name: str) -> list[DocCommand]:
    """``meshsplat`` command lines of the fenced code blocks of a markdown text."""
    out, fence, pending, start = [], None, "", 0
    for n, line in enumerate(text.splitlines(), 1):
        marker = re.match(r"^\s*(```|~~~)", line)
        if marker and (fence is None or marker.group(1) == fence):
            fence = marker.group(1) if fence is None else None
            pending = ""
            continue
        if fence is None:
            continue
        if not pending:
            start = n
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        logical = (pending + line).strip()
        pending = ""
        logical = re.sub(r"^\$\s+", "", logical)
        if logical.startswith("meshsplat "):
            words = shlex.split(logical, comments=True)
            out.append(DocCommand(f"{name}:{start}", " ".join(shlex.quote(w) for w in words), False))
    return out


def inline_commands(text: str, name: str) -> list[DocCommand]:
    """``meshsplat`` commands of the inline code spans (outside fenced blocks) of a markdown text."""
    blanked, fence = [], None
    for line in text.splitlines():
        marker = re.match(r"^\s*(```|~~~)", line)
        if marker and (fence is None or marker.group(1) == fence):
            fence = marker.group(1) if fence is None else None
            blanked.append("")
            continue
        blanked.append("" if fence else line)
    prose = "\n".join(blanked)
    out = []
    for m in re.finditer(r"`([^`]+)`", prose):
        span = " ".join(m.group(1).split())
        if span.startswith("meshsplat ") and "\n\n" not in m.group(1):
            out.append(DocCommand(f"{name}:{prose.count(chr(10), 0, m.start()) + 1}", span, True))
    return out


def documented_commands() -> list[DocCommand]:
    cmds = []
    for path in DOC_FILES:
        text, name = path.read_text(), str(path.relative_to(ROOT))
        cmds += fenced_commands(text, name) + inline_commands(text, name)
    return cmds


COMMANDS_IN_DOCS = documented_commands()


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _variants(words: list[str]) -> list[list[str]]:
    """A usage synopsis as commands: brackets and ``...`` dropped, one command per ``a|b`` alternative."""
    words = [w.strip("[]") for w in words]
    words = [w for w in words if w and w != "..."]
    base = [w.split("|")[0] for w in words]
    out = [base]
    for i, w in enumerate(words):
        out += [base[:i] + [alt] + base[i + 1 :] for alt in w.split("|")[1:]]
    return out


def _value_for(action: argparse.Action, word: str) -> str:
    """``word``, or for a placeholder a value the option accepts (its first choice, or one its type takes)."""
    if not PLACEHOLDER.match(word):
        return word
    if action.choices:
        return str(next(iter(action.choices)))
    for candidate in ("1", "0.5", "auto", word):
        try:
            if action.type is None or action.type(candidate) is not None:
                return candidate
        except (TypeError, ValueError, argparse.ArgumentTypeError):
            continue
    return word


def _fill_placeholders(sub: argparse.ArgumentParser, args: list[str]) -> tuple[list[str], int]:
    """``args`` with option-value placeholders replaced, and the number of positional words."""
    out, positionals, i = [], 0, 0
    while i < len(args):
        word = args[i]
        action = sub._option_string_actions.get(word.split("=", 1)[0]) if word.startswith("-") else None
        out.append(word)
        i += 1
        if action is None:
            positionals += not word.startswith("-")
            continue
        if action.nargs == 0 or "=" in word:
            continue
        many = action.nargs in ("+", "*") or (isinstance(action.nargs, int) and action.nargs > 1)
        limit = action.nargs if isinstance(action.nargs, int) else (len(args) if many else 1)
        taken = 0
        while i < len(args) and taken < limit and not args[i].startswith("-"):
            out.append(_value_for(action, args[i]))
            i += 1
            taken += 1
    return out, positionals


def _parse_error(parser: argparse.ArgumentParser, argv: list[str]) -> tuple[argparse.Namespace | None, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            return parser.parse_args(argv), ""
        except SystemExit:
            return None, err.getvalue().strip().splitlines()[-1]


def check_command(cmd: DocCommand) -> list[str]:
    """Problems of one documented command (empty: it parses, and its --set values apply)."""
    words = shlex.split(cmd.text)
    if len(words) < 2 or words[0] != "meshsplat":
        return [f"not a meshsplat command: {cmd.text!r}"]
    names = words[1].split("/")
    unknown = [n for n in names if n not in COMMANDS]
    if unknown:
        return [f"unknown subcommand(s) {unknown}"]
    problems = []
    for name in names:
        parser = build_parser(only=name)
        sub = _subparser(parser, name)
        for variant in _variants(words[2:]):
            args, positionals = _fill_placeholders(sub, variant)
            if cmd.inline and positionals == 0:  # a reference to the command or its flags
                problems += [
                    f"{name}: unknown option {w}"
                    for w in args
                    if w.startswith("-") and w.split("=")[0] not in sub._option_string_actions
                ]
                for flag, value in itertools.pairwise(args):
                    action = sub._option_string_actions.get(flag)
                    if (
                        action is not None
                        and action.choices
                        and not value.startswith("-")
                        and value not in action.choices
                    ):
                        problems.append(f"{name} {flag}: invalid choice {value!r}")
                continue
            ns, error = _parse_error(parser, [name, *args])
            if ns is None:
                problems.append(f"meshsplat {name} {' '.join(args)}: {error}")
                continue
            if name == "train":
                try:
                    apply_overrides(recipe_config(ns.recipe or DEFAULT_RECIPE), ns.set).validate()
                except ValueError as exc:
                    problems.append(f"train --set {ns.set}: {exc}")
            if name in ("render", "view") and ns.animation and ns.animation[0] not in ANIMATION_KINDS:
                problems.append(f"{name} --animation: unknown kind {ns.animation[0]!r}")
    return problems


def test_extraction_finds_the_documented_commands():
    texts = {c.text for c in COMMANDS_IN_DOCS}
    assert len(COMMANDS_IN_DOCS) >= 50, len(COMMANDS_IN_DOCS)
    assert "meshsplat eval runs/cesium" in texts  # README block, comment dropped
    assert any(
        c.inline and c.text.startswith("meshsplat render RUN --animation motion") for c in COMMANDS_IN_DOCS
    )  # 2 lines
    md = "x `meshsplat eval A\nB` y\n```bash\n$ meshsplat train D \\\n  --out R   # note\n# meshsplat no\n```\n"
    assert [c.text for c in fenced_commands(md, "m")] == ["meshsplat train D --out R"]
    assert [(c.where, c.text) for c in inline_commands(md, "m")] == [("m:1", "meshsplat eval A B")]


def test_checker_catches_what_fails():
    bad = {
        "meshsplat train DATA --set model.shading=sh2 model.init_color_frames=8": "required: --out",
        "meshsplat train D --out R --set model.nope=1": "unknown key",
        "meshsplat trian D": "unknown subcommand",
        "meshsplat synth CesiumMan --out d --rig spiral": "invalid choice",
        "meshsplat view RUN --out o --animation gtlf f.glb": "unknown kind",
    }
    for text, expected in bad.items():
        problems = check_command(DocCommand("x", text, False))
        assert problems and expected in problems[0], (text, problems)
    assert check_command(DocCommand("x", "meshsplat export --frmat", True)) == ["export: unknown option --frmat"]
    assert check_command(DocCommand("x", "meshsplat synth --format NAME", True)) == []
    assert check_command(
        DocCommand("x", "meshsplat synth A --out D [--rig monocular-turn|orbit|nope]", True)
    ) and not check_command(
        DocCommand("x", "meshsplat synth A --out D [--rig orbit|multiview] [--threads N|auto]", True)
    )


@pytest.mark.parametrize("cmd", COMMANDS_IN_DOCS, ids=[c.where for c in COMMANDS_IN_DOCS])
def test_documented_command_parses(cmd):
    assert check_command(cmd) == [], f"{cmd.where}: {cmd.text}"


def test_commands_name_no_checkout_paths():
    """A user has the package, not this checkout: no command names a file outside the repository."""
    outside = [f"{c.where}: {c.text}" for c in COMMANDS_IN_DOCS if "../" in c.text]
    assert not outside


# The README's command-line chain, run as written except for this table: (README text, what runs instead).
# Only sizes, thread counts and progress output change (tiny, 1 thread), nothing else. Every entry must
# match its README command, so the table cannot silently go stale.
README_SUBSTITUTIONS: dict[str, list[tuple[str, str]]] = {
    "synth": [("--frames 100 --resolution 512", "--frames 8 --resolution 32 --threads 1")],
    "train": [("--minutes 10", "--iters 4 --threads 1 --no-progress --set model.n_init=300")],
    "eval": [("runs/cesium", "runs/cesium --threads 1 --no-progress")],
    "render": [("--out renders/", "--out renders/ --seconds 0.2 --threads 1 --no-progress")],
    "export": [],
    "view": [],
}
README_OUTPUTS = {
    "synth": "data/cesium/manifest.json",
    "train": "runs/cesium/checkpoints/ckpt_00000004.pt",
    "eval": "runs/cesium/eval/metrics.json",
    "render": "renders/frames",
    "export": "runs/cesium/export/avatar.ply",
    "view": "viewer/index.html",
}


def readme_chain() -> list[str]:
    """The fenced ``meshsplat`` commands of the README's "Command line" section, the chain, in order, with
    ``README_SUBSTITUTIONS`` applied."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("\n## Command line\n", 1)[1].split("\n## ", 1)[0]
    cmds = [c.text for c in fenced_commands(section, "README.md")]
    chain = []
    for name, subs in README_SUBSTITUTIONS.items():
        found = [c for c in cmds if shlex.split(c)[1] == name]
        assert len(found) == 1, f"README.md: expected one fenced `meshsplat {name}` command, found {found}"
        text = found[0]
        for old, new in subs:
            assert old in text, f"README_SUBSTITUTIONS[{name!r}]: {old!r} is no longer in {text!r}"
            text = text.replace(old, new)
        chain.append(text)
    return chain


@pytest.mark.slow
def test_readme_command_line_runs(tmp_path, monkeypatch, assets, capsys):
    monkeypatch.chdir(tmp_path)
    for text, (_name, output) in zip(readme_chain(), README_OUTPUTS.items(), strict=True):
        rc = main(shlex.split(text)[1:])
        err = capsys.readouterr().err
        assert rc == 0, f"{text}: exit {rc}: {err.strip().splitlines()[-1:] if err.strip() else ''}"
        assert (tmp_path / output).exists(), f"{text}: {output} missing"
