"""cli/_options.py: the run and render options are declared once and mean the same in every command."""

from __future__ import annotations

import argparse

import pytest

from meshsplat.cli._options import add_render_options, add_run_argument, parse_size, render_options
from meshsplat.cli.main import build_parser
from meshsplat.errors import MeshsplatError

SHARED = ("--dataset", "--size", "--background", "--device", "--backend", "--no-progress")


def _actions(command: str) -> dict[str, argparse.Action]:
    sub = next(a for a in build_parser(only=command)._actions if isinstance(a, argparse._SubParsersAction))
    return {s: a for a in sub.choices[command]._actions for s in a.option_strings}


def test_shared_flags_read_the_same_everywhere():
    seen: dict[str, tuple] = {}
    for cmd in ("eval", "render", "view", "train"):
        for flag, a in _actions(cmd).items():
            if flag in SHARED and not (cmd == "view" and flag == "--background"):  # the page: white or black
                key = (a.help, a.choices) if flag != "--device" else (a.help,)  # train leaves it to the config
                assert seen.setdefault(flag, key) == key, (cmd, flag)
    assert set(seen) == set(SHARED)
    assert _actions("train")["--device"].default is None and _actions("eval")["--device"].default == "auto"
    assert _actions("view")["--background"].choices == ("white", "black")
    assert "--backend" not in _actions("view") and "--background" not in _actions("train")


def test_render_options_parse_once():
    p = argparse.ArgumentParser()
    add_run_argument(p)
    add_render_options(p, size=True)
    o = render_options(p.parse_args(["RUN", "--size", "64x32", "--background", "0,0.5,1", "--no-progress"]))
    assert (o.size, o.background, o.device, o.backend, o.progress) == ((64, 32), "0,0.5,1", "auto", "auto", False)
    o = render_options(p.parse_args(["RUN"]))
    assert o.size is None and o.background == "white" and o.progress
    q = argparse.ArgumentParser()
    add_render_options(q, device=False, backend=False, background=False, progress=False)
    o = render_options(q.parse_args([]))
    assert (o.device, o.backend, o.background, o.size, o.progress) == (None, "auto", None, None, True)


@pytest.mark.parametrize("text, match", [("64", "expected WxH"), ("0x64", "pixels per side"), ("axb", "expected WxH")])
def test_bad_size_is_one_line(text, match):
    with pytest.raises(MeshsplatError, match=match) as e:
        parse_size(text)
    assert "\n" not in str(e.value)
