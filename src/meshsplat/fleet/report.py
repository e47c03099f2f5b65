"""The results table of ``meshsplat batch``: one row per job (``runner.RESULT_KEYS``), written as
``results.json``, ``results.csv`` and ``results.html`` (a page that opens from the disk)."""

from __future__ import annotations

import csv
import html
import io
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from meshsplat.fleet.runner import RESULT_KEYS
from meshsplat.io.atomic import write_text_atomic

__all__ = ["write_results", "summary_line"]


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def summary_line(rows: Sequence[dict[str, Any]]) -> str:
    ok = sum(r.get("status") == "ok" for r in rows)
    return f"{ok} of {len(rows)} job(s) finished" + (f", {len(rows) - ok} failed" if ok < len(rows) else "")


def write_results(out: str | Path, rows: Sequence[dict[str, Any]], title: str = "meshsplat batch") -> dict[str, Path]:
    """Write the table in three forms under ``out``; returns their paths."""
    out = Path(out)
    rows = [{k: r.get(k) for k in RESULT_KEYS} for r in rows]
    paths = {"json": out / "results.json", "csv": out / "results.csv", "html": out / "results.html"}
    write_text_atomic(paths["json"], json.dumps(rows, indent=1) + "\n")
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=RESULT_KEYS)
    wr.writeheader()
    wr.writerows({k: _cell(r[k]) for k in RESULT_KEYS} for r in rows)
    write_text_atomic(paths["csv"], buf.getvalue())
    head = "".join(f"<th>{html.escape(k)}</th>" for k in RESULT_KEYS)
    body = "".join(
        f'<tr class="{html.escape(str(r["status"]))}">'
        + "".join(f"<td>{html.escape(_cell(r[k]))}</td>" for k in RESULT_KEYS)
        + "</tr>\n"
        for r in rows
    )
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font:14px sans-serif;margin:2em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:left}}tr.failed{{background:#fdd}}</style></head>
<body><h1>{html.escape(title)}</h1><p>{html.escape(summary_line(rows))}</p>
<table><tr>{head}</tr>
{body}</table></body></html>
"""
    write_text_atomic(paths["html"], page)
    return paths
