"""The command line on any OS and as users expect of such tools: it starts and runs a command without the
Unix-only `resource` module and without /proc (as on Windows and macOS); a command that cannot be
imported says why instead of vanishing; --version, --debug before or after the command, help text on
every option, each command's summary whole, and a shell completion script that completes."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from meshsplat import __version__
from meshsplat.cli import main as cli_main
from meshsplat.cli.main import COMMANDS, build_parser, main
from meshsplat.errors import MeshsplatError

# A sitecustomize that makes this Linux look like a system without `resource` and /proc.
NO_RESOURCE_NO_PROC = """
import builtins, io, sys

class _NoResource:
    def find_spec(self, name, path=None, target=None):
        if name == "resource":
            raise ModuleNotFoundError("No module named 'resource' (hidden by the test)")
        return None

sys.modules.pop("resource", None)
sys.meta_path.insert(0, _NoResource())
_open = builtins.open

def _open_without_proc(file, *args, **kwargs):
    if str(file).startswith("/proc"):
        raise FileNotFoundError(2, "No such file or directory (hidden by the test)", str(file))
    return _open(file, *args, **kwargs)

builtins.open = io.open = _open_without_proc
"""


def _run(tmp_path: Path, site: str, *argv: str) -> subprocess.CompletedProcess:
    """``meshsplat ARGV`` in a fresh interpreter whose sitecustomize is ``site``."""
    site_dir = tmp_path / "site"
    site_dir.mkdir(exist_ok=True)
    (site_dir / "sitecustomize.py").write_text(textwrap.dedent(site))
    path = os.pathsep.join([str(site_dir), *(p for p in sys.path if p)])
    env = {**os.environ, "PYTHONPATH": path, "MESHSPLAT_THREADS": "1"}
    cmd = [sys.executable, "-m", "meshsplat.cli.main", *argv]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)


def test_the_cli_starts_and_runs_a_command_without_resource_and_proc(tmp_path):
    res = _run(tmp_path, NO_RESOURCE_NO_PROC, "--help")
    assert res.returncode == 0, res.stderr
    for name in COMMANDS:  # every command loads (none dropped for want of `resource`)
        assert name in res.stdout
    assert "cannot load" not in res.stdout
    res = _run(tmp_path, NO_RESOURCE_NO_PROC, "--version")
    assert res.returncode == 0 and res.stdout.strip() == f"meshsplat {__version__}", res.stderr
    # synth checks its memory estimate: with /proc hidden it falls back to the installed memory
    probe = "try:\n import resource\nexcept ImportError:\n print('no resource')\n"
    probe += "try:\n open('/proc/meminfo')\nexcept OSError:\n print('no proc')\n"
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site")}
    hidden = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=60)
    assert hidden.stdout.splitlines() == ["no resource", "no proc"], hidden.stderr  # the test hides both
    # synth checks its memory estimate: with /proc hidden it falls back to the installed memory
    argv = ["synth", "cesiumman", "--out", str(tmp_path / "cap"), "--resolution", "32", "--frames", "2"]
    argv += ["--views", "1", "--rig", "orbit", "--test-frames", "0", "--test-views", "0", "--threads", "1"]
    res = _run(tmp_path, NO_RESOURCE_NO_PROC, *argv)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "cap" / "manifest.json").is_file()
    assert "Traceback" not in res.stderr and "could not read" not in res.stderr


def test_memory_that_cannot_be_read_is_said_not_silently_skipped(tmp_path):
    # no /proc, no resource and no sysconf: nothing says how much memory there is
    site = NO_RESOURCE_NO_PROC + "\nimport os\ndel os.sysconf\n"
    argv = ["synth", "cesiumman", "--out", str(tmp_path / "cap"), "--resolution", "32", "--frames", "2"]
    argv += ["--views", "1", "--rig", "orbit", "--test-frames", "0", "--test-views", "0", "--threads", "1"]
    res = _run(tmp_path, site, *argv)
    assert res.returncode == 0, res.stderr
    notes = [line for line in res.stderr.splitlines() if "could not read how much memory" in line]
    assert len(notes) == 1 and notes[0].startswith("note: "), res.stderr


def test_the_memory_refusal_still_works_where_memory_is_known():
    from meshsplat.cli._guards import check_memory, render_bytes
    from meshsplat.cli._memory import available_memory

    avail = available_memory()
    assert avail is not None and avail > 0
    with pytest.raises(MeshsplatError, match=r"needs about .* but only"):
        check_memory("rendering", render_bytes(200_000, 200_000), "lower --size")


BLOCK_BATCH = """
import sys

class _NoFleet:
    def find_spec(self, name, path=None, target=None):
        if name == "meshsplat.fleet.batch":
            raise ImportError("fleet is broken (by the test)")
        return None

sys.meta_path.insert(0, _NoFleet())
"""


def test_a_command_that_cannot_be_imported_says_why(tmp_path):
    res = _run(tmp_path, BLOCK_BATCH, "batch", "jobs.txt", "--out", "x")
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("meshsplat batch: error: the command could not be loaded")
    assert "ImportError: fleet is broken (by the test)" in lines[0] and "--debug" in lines[0]
    assert "invalid choice" not in res.stderr
    res = _run(tmp_path, BLOCK_BATCH, "batch", "jobs.txt", "--debug")
    assert res.returncode != 0 and "Traceback" in res.stderr and "fleet is broken" in res.stderr
    res = _run(tmp_path, BLOCK_BATCH, "--help")  # listed, with its error; the others still load
    assert res.returncode == 0
    batch_line = next(line for line in res.stdout.splitlines() if line.strip().startswith("batch"))
    assert "cannot load" in batch_line + res.stdout and "train" in res.stdout


def test_debug_is_accepted_before_or_after_the_command(tmp_path, capsys):
    missing = str(tmp_path / "no_such_run")
    assert main(["export", missing]) == 2
    assert "error:" in capsys.readouterr().err
    for argv in (["--debug", "export", missing], ["export", missing, "--debug"]):
        with pytest.raises((MeshsplatError, OSError)):
            main(argv)


def _actions(parser: argparse.ArgumentParser, path: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _actions(sub, f"{path} {name}")
        else:
            yield path, action


def test_every_option_and_argument_has_help_text():
    missing = [
        f"{path} {'/'.join(a.option_strings) or a.dest}"
        for path, a in _actions(build_parser(), "meshsplat")
        if a.help != argparse.SUPPRESS and not (a.help or "").strip()
    ]
    assert not missing, f"no help text: {missing}"


def test_each_command_summary_is_whole():
    for name in COMMANDS:
        summary = cli_main._summary(cli_main._load(name).__doc__)
        assert summary and summary.endswith("."), (name, summary)
        assert "\n" not in summary
    export = cli_main._summary(cli_main._load("export").__doc__)
    assert export is not None and export.endswith("canonical mesh OBJ, README.")


def _complete(script: str, *words: str) -> list[str]:
    code = (
        f"{script}\nCOMP_WORDS=({' '.join(repr(w) for w in words)}); COMP_CWORD={len(words) - 1}\n"
        '_meshsplat; printf "%s\\n" "${COMPREPLY[@]}"'
    )
    res = subprocess.run(["bash", "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return res.stdout.split()


@pytest.mark.skipif(not Path("/bin/bash").exists() and not Path("/usr/bin/bash").exists(), reason="needs bash")
def test_bash_completion_completes_commands_options_and_choices(capsys):
    assert main(["completion", "bash"]) == 0
    script = capsys.readouterr().out
    assert "complete -o default -F _meshsplat meshsplat" in script
    assert _complete(script, "meshsplat", "exp") == ["export"]
    assert _complete(script, "meshsplat", "--ver") == ["--version"]
    assert _complete(script, "meshsplat", "train", "--rec") == ["--recipe"]
    assert sorted(_complete(script, "meshsplat", "--debug", "train", "--recipe", "")) == ["paper", "quality"]
    assert _complete(script, "meshsplat", "completion", "") == ["bash", "zsh"]
    assert _complete(script, "meshsplat", "train", "data/") == []  # arguments: the shell's file names
    assert main(["completion", "zsh"]) == 0
    zsh = capsys.readouterr().out
    assert zsh.startswith("autoload -U +X bashcompinit && bashcompinit\n") and script in zsh
