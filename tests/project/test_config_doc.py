"""docs/config.md lists every TrainConfig key with the code's type and default (it cannot go stale)."""

from __future__ import annotations

import json
import re
import typing
from pathlib import Path

from meshsplat.train.config import TrainConfig

DOC = Path(__file__).resolve().parents[2] / "docs" / "config.md"


def _code_keys() -> dict[str, tuple[str, object]]:
    """``section.key`` -> (type name, default) of every TrainConfig field."""
    out = {}

    def walk(cls, obj, prefix):
        for name, tp in typing.get_type_hints(cls).items():
            value = getattr(obj, name)
            if hasattr(tp, "__dataclass_fields__"):
                walk(tp, value, f"{prefix}{name}.")
            else:
                args = [a for a in typing.get_args(tp) if a is not type(None)]
                # Optional[X] (X | None) reads "X or null" in the doc
                out[prefix + name] = (f"{args[0].__name__} or null" if args else tp.__name__, value)

    walk(TrainConfig, TrainConfig(), "")
    return out


def _doc_rows() -> dict[str, tuple[str, object]]:
    rows = {}
    for line in DOC.read_text().splitlines():
        m = re.match(r"^\| `([A-Za-z_0-9.]+)` \| (\w+(?: or null)?) \| `(.*?)` \|", line)
        if m:
            assert m.group(1) not in rows, f"docs/config.md lists {m.group(1)} twice"
            rows[m.group(1)] = (m.group(2), json.loads(m.group(3)))
    return rows


def test_every_config_key_is_documented_with_its_type_and_default():
    code, doc = _code_keys(), _doc_rows()
    assert len(code) > 50
    missing = sorted(set(code) - set(doc))
    assert not missing, f"docs/config.md misses {missing}"
    stale = sorted(set(doc) - set(code))
    assert not stale, f"docs/config.md lists keys TrainConfig no longer has: {stale}"
    wrong = {k: (doc[k], code[k]) for k in code if doc[k] != code[k]}
    assert not wrong, f"docs/config.md type/default differ from the code (doc, code): {wrong}"


def test_strategy_rows_name_their_gsplat_counterpart():
    for line in DOC.read_text().splitlines():
        if line.startswith("| `strategy."):
            gsplat = line.split("|")[5].strip()
            assert gsplat.startswith("`") or gsplat.startswith("ours"), line
