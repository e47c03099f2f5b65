"""meshsplat eval: metrics on test splits, background compositing, report files, CLI."""

from __future__ import annotations

import json

import pytest

from _eval_kit import make_avatar, make_dataset, make_run
from meshsplat.errors import MeshsplatError
from meshsplat.eval import evaluate_avatar, evaluate_run
from meshsplat.metrics import lpips_available
from meshsplat.run_folder import load_run


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    av = make_avatar()
    ds = make_dataset(av, root / "ds")
    run = make_run(av, root / "run", ds, iteration=7)
    return av, ds, run


def test_evaluate_run_scores_the_true_avatar_and_writes_report(setup):
    av, _ds, run = setup
    m = evaluate_run(run, device="cpu")
    assert set(m["splits"]) == {"test_frames", "test_views"}  # every split but train
    assert m["iteration"] == 7 and m["n_gaussians"] == av.num_gaussians
    for name, n in (("test_frames", 2), ("test_views", 1)):
        s = m["splits"][name]
        assert s["n_frames"] == n and len(s["frames"]) == n
        # ground truth is this avatar's render, stored as 8-bit PNG: only quantisation error remains
        assert s["psnr"] > 40 and s["ssim"] > 0.99
        assert all(f["render_ms"] > 0 for f in s["frames"])
        if lpips_available():
            assert s["lpips"] < 0.01
    on_disk = json.loads((run / "eval" / "metrics.json").read_text())
    assert on_disk["splits"]["test_views"]["frames"][0]["index"] == 4
    assert on_disk["background"] == "white"
    for f in ("report.html", "samples_test_frames.png", "samples_test_views.png", "curves.png"):
        assert (run / "eval" / f).stat().st_size > 1000, f
    html = (run / "eval" / "report.html").read_text()
    assert "data:image/png;base64," in html and "test_views" in html


def test_metrics_drop_for_a_wrong_avatar_and_background_is_consistent(setup):
    av, ds, _ = setup
    from meshsplat.data import open_dataset

    d = open_dataset(ds)
    for bg in ("white", "black", "0.2,0.5,0.9"):
        good, _ = evaluate_avatar(av, d, ["test_views"], background=bg, lpips_net=None, samples_per_split=0)
        assert good["splits"]["test_views"]["psnr"] > 40, bg  # gt composited on the same colour
    bad = make_avatar(seed=1)  # other colours and embedding
    worse, _ = evaluate_avatar(bad, d, ["test_views"], lpips_net=None, samples_per_split=0)
    assert worse["splits"]["test_views"]["psnr"] < 30


def test_evaluate_errors(setup, tmp_path):
    av, ds, _run = setup
    from meshsplat.data import open_dataset

    d = open_dataset(ds)
    with pytest.raises(MeshsplatError, match="nope"):
        evaluate_avatar(av, d, ["nope"])
    other = make_avatar(n=50)
    other.mesh = type(av.mesh)(av.mesh.vertices[:-1], av.mesh.faces[(av.mesh.faces < 41).all(1)])
    with pytest.raises(MeshsplatError, match="vertices"):
        evaluate_avatar(other, d)
    with pytest.raises(MeshsplatError, match="run not found"):
        load_run(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MeshsplatError, match="no checkpoint in"):
        load_run(tmp_path / "empty")
    (tmp_path / "corrupt" / "checkpoints").mkdir(parents=True)
    (tmp_path / "corrupt" / "checkpoints" / "ckpt_00000010.pt").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(MeshsplatError, match=r"all 1 checkpoint\(s\) .* unreadable; newest: .*ckpt_00000010.pt"):
        load_run(tmp_path / "corrupt")
    no_data = make_run(av, tmp_path / "nodata", None)
    with pytest.raises(MeshsplatError, match="--dataset"):
        evaluate_run(no_data, report=False)


def test_cli_eval(setup, tmp_path, capsys):
    from meshsplat.cli.main import main

    _, _ds, run = setup
    out = tmp_path / "ev"
    rc = main(
        [
            "eval",
            str(run),
            "--out",
            str(out),
            "--splits",
            "test_views",
            "--max-frames",
            "1",
            "--no-progress",
            "--no-lpips",
            "--background",
            "black",
        ]
    )
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    assert list(m["splits"]) == ["test_views"] and m["background"] == "black"
    assert (out / "report.html").is_file()
    assert "test_views" in capsys.readouterr().out
    assert main(["eval", str(tmp_path / "no_such_run")]) == 2
    assert "run not found" in capsys.readouterr().err
