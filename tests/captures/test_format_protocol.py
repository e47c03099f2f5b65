"""Every registered capture format is a CaptureFormat: the attributes and signatures the registry, the
command line and ``synth --format`` rely on (data/formats/protocol.py)."""

from __future__ import annotations

import types

import pytest

from meshsplat.data.formats import FORMAT_NAMES, format_module
from meshsplat.data.formats.protocol import CaptureFormat, format_problems
from meshsplat.synth.generate import RIGS


@pytest.mark.parametrize("name", FORMAT_NAMES)
def test_every_registered_format_fits_the_protocol(name):
    module = format_module(name)
    assert format_problems(module, name) == []
    assert isinstance(module, CaptureFormat)
    assert set(getattr(module, "WRITE_RIGS", ())) <= set(RIGS)


def test_the_check_sees_what_is_missing_or_misnamed():
    fake = types.ModuleType("fake")
    fake.NAME, fake.DESCRIPTION = "other", "a layout"
    fake.detect = lambda root, extra: True
    fake.read = lambda root: None
    fake.write = lambda dataset, out, overwrite=True: None
    assert any("SIGNATURE" in p for p in format_problems(fake, "fake"))
    fake.SIGNATURE = "x.json"
    problems = format_problems(fake, "fake")
    assert any("registered as 'fake'" in p for p in problems)
    fake.NAME = "fake"
    problems = format_problems(fake, "fake")
    assert any(p.startswith("detect(root)") for p in problems)
    assert any(p.startswith("read(root, model_dir=None") for p in problems)
    assert any("overwrite must default to False" in p for p in problems)
