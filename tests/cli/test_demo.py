"""End to end: the demo pipeline in its tiny preset (synth -> train -> eval -> render -> export)."""

from __future__ import annotations

import json

import pytest

from meshsplat.cli.main import main


@pytest.mark.slow
def test_tiny_demo_runs_end_to_end_and_learns(tmp_path, assets, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--preset", "tiny", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 60
    # held-out frames and novel views were evaluated, and the avatar is far better than a blank image
    assert {"test_frames", "test_views"} <= set(summary["metrics"])
    for m in summary["metrics"].values():
        assert m["psnr"] > 15.0 and 0.0 < m["ssim"] <= 1.0
    log = (out / "run" / "log.csv").read_text().splitlines()
    header = log[0].split(",")
    psnr = [float(r.split(",")[header.index("psnr")]) for r in log[1:]]
    assert max(psnr[-3:]) > psnr[0] + 1.0, "training did not improve PSNR"
    for rel in (
        "data/contact_sheet.png",
        "run/eval/report.html",
        "run/eval/metrics.json",
        "export/avatar.ply",
        "export/embedding.json",
        "export/canonical_mesh.obj",
    ):
        assert (out / rel).is_file(), rel
    assert any((out / "animation").rglob("*.png")) or (out / "animation" / "avatar_orbit.mp4").is_file()
    assert "PSNR" in capsys.readouterr().out
