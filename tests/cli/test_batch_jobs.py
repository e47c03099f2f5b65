"""The jobs file of ``meshsplat batch``: three spellings of the same jobs, per-job problems that fail
only their job, and files that cannot be read at all."""

from __future__ import annotations

import json

import pytest

from _train_kit import make_tiny_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.fleet.jobs import job_config, read_jobs
from meshsplat.fleet.report import write_results
from meshsplat.fleet.runner import RESULT_KEYS, failed_result, run_job


def test_yaml_json_and_text_say_the_same(tmp_path):
    pytest.importorskip("yaml")
    (tmp_path / "y.yaml").write_text(
        "defaults:\n  iterations: 50\n  set: [model.n_init=300]\n"
        "jobs:\n  - data: caps/a\n  - {data: caps/b, name: bee, set: [seed=3], recipe: paper}\n"
    )
    doc = {"defaults": {"iterations": 50, "set": ["model.n_init=300"]}}
    doc["jobs"] = [{"data": "caps/a"}, {"data": "caps/b", "name": "bee", "set": ["seed=3"], "recipe": "paper"}]
    (tmp_path / "j.json").write_text(json.dumps(doc))
    y, j = read_jobs(tmp_path / "y.yaml"), read_jobs(tmp_path / "j.json")
    assert [x.to_dict() for x in y] == [x.to_dict() for x in j]
    a, b = y
    assert (a.name, a.data, a.iterations, a.set) == ("a", str(tmp_path / "caps/a"), 50, ["model.n_init=300"])
    assert (b.name, b.recipe, b.set) == ("bee", "paper", ["model.n_init=300", "seed=3"])
    cfg = job_config(b, tmp_path / "run")
    assert (cfg.seed, cfg.model.n_init, cfg.iterations, cfg.shading.enabled) == (3, 300, 50, False)  # paper recipe
    (tmp_path / "t.txt").write_text("# captures\ncaps/a model.n_init=300\n\ncaps/b seed=3  # the second\n")
    t = read_jobs(tmp_path / "t.txt")
    assert [(x.name, x.set) for x in t] == [("a", ["model.n_init=300"]), ("b", ["seed=3"])]


def test_a_bad_job_fails_alone_and_a_bad_file_is_refused(tmp_path):
    jobs = [
        {"data": "a"},
        {"data": "b", "colour": "red"},
        {"data": "c", "set": ["no_such.key=1"]},
        {"data": "d", "export": ["obj"]},
        {"name": "a", "data": "e"},
        {"data": "f", "iterations": "many"},
        {"nodata": 1},
    ]
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    got = read_jobs(tmp_path / "jobs.json")
    assert got[0].problem == ""
    assert "unknown key(s) colour" in got[1].problem
    assert "no_such" in got[2].problem
    assert "obj" in got[3].problem
    assert "used by an earlier job" in got[4].problem
    assert "bad value" in got[5].problem
    assert "'data'" in got[6].problem
    for bad, match in [
        ("[]", "non-empty list"),
        ("{", "not valid JSON"),
        ('{"defaults": 3, "jobs": ["a"]}', "defaults"),
    ]:
        (tmp_path / "bad.json").write_text(bad)
        with pytest.raises(MeshsplatError, match=match):
            read_jobs(tmp_path / "bad.json")
    with pytest.raises(MeshsplatError, match="not found"):
        read_jobs(tmp_path / "none.json")
    (tmp_path / "jobs.toml").write_text("")
    with pytest.raises(MeshsplatError, match=r"\.yaml, \.yml, \.json or \.txt"):
        read_jobs(tmp_path / "jobs.toml")


def test_results_table_in_three_forms(tmp_path):
    (job,) = read_jobs(_one(tmp_path))
    row = failed_result(job, "first line <b>\nsecond line")
    paths = write_results(tmp_path, [row])
    assert json.loads(paths["json"].read_text())[0]["reason"] == "first line <b>"
    assert paths["csv"].read_text().splitlines()[0] == ",".join(RESULT_KEYS)
    page = paths["html"].read_text()
    assert "first line &lt;b&gt;" in page and "0 of 1 job(s) finished, 1 failed" in page


def _one(tmp_path):
    (tmp_path / "one.json").write_text(json.dumps(["cap"]))
    return tmp_path / "one.json"


def test_one_job_without_ray_and_a_capture_without_test_split(tmp_path):
    data = make_tiny_dataset(tmp_path / "cap")  # a 'train' split only
    (tmp_path / "jobs.json").write_text(
        json.dumps([{"data": "cap", "iterations": 3, "device": "cpu", "set": ["model.n_init=100", "backend=torch"]}])
    )
    (job,) = read_jobs(tmp_path / "jobs.json")
    assert job.data == str(data)
    row = run_job(job, tmp_path / "out")
    assert row["status"] == "ok" and row["iterations"] == 3 and row["psnr"] is None, row
    assert row["reason"] == "not evaluated: the capture has no test split"
    assert (tmp_path / "out" / "cap" / "export" / "avatar.ply").is_file()
    assert run_job(job, tmp_path / "out") == json.loads((tmp_path / "out" / "cap" / "result.json").read_text())
