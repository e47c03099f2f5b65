"""Jobs files taken as written (issue 52): values never coerced, sizes bounded before anything is built,
finished jobs keyed by their whole spec (an edited job runs again), a repeated name a failed job of its own,
and a Ray that cannot be reached one line."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from _train_kit import make_tiny_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.fleet.jobs import MAX_DEPTH, MAX_FILE_BYTES, read_jobs
from meshsplat.fleet.runner import finished_result, run_job


def _jobs(tmp_path, entries, name="jobs.json"):
    (tmp_path / name).write_text(json.dumps(entries))
    return read_jobs(tmp_path / name)


@pytest.mark.parametrize(
    "entry, problem",
    [
        ({"eval": "false"}, "eval: expected true or false (unquoted), got 'false'"),
        ({"eval": 0}, "eval: expected true or false"),
        ({"iterations": 2.9}, "iterations: expected a whole number, got 2.9"),
        ({"iterations": "30"}, "iterations: expected a whole number, got '30'"),
        ({"iterations": True}, "iterations: expected a whole number, got True"),
        ({"threads": 1.5}, "threads: expected a whole number"),
        ({"set": "seed=3"}, "set: expected a list of KEY=VALUE items"),
        ({"set": ["seed=3", 4]}, "set: expected a list of text items"),
        ({"export": "ply"}, "export: expected a list of text items, got 'ply'"),
        ({"recipe": ["paper"]}, "recipe: expected text"),
        ({"name": 7}, "name: expected text, got 7"),
        ({"data": 5}, "data: expected a capture path, got 5"),
    ],
)
def test_values_are_taken_as_written_never_coerced(tmp_path, entry, problem):
    (job,) = _jobs(tmp_path, [{"data": "cap", **entry}])
    assert problem in job.problem


def test_well_typed_values_pass(tmp_path):
    (job,) = _jobs(tmp_path, [{"data": "cap", "eval": False, "iterations": 30, "threads": 2, "export": []}])
    assert job.problem == "" and (job.eval, job.iterations, job.threads, job.export) == (False, 30, 2, [])


def test_yaml_alias_bomb_is_refused_before_it_expands(tmp_path):
    pytest.importorskip("yaml")
    lines = ['a: &a ["x","x","x","x","x","x","x","x","x","x"]']
    for i in range(1, 9):  # 10**9 leaves
        prev = chr(ord("a") + i - 1)
        lines.append(f"{chr(ord('a') + i)}: &{chr(ord('a') + i)} [{', '.join(['*' + prev] * 10)}]")
    lines.append("jobs: [*i]")
    (tmp_path / "bomb.yaml").write_text("\n".join(lines) + "\n")
    t0 = time.perf_counter()
    with pytest.raises(MeshsplatError, match=r"more than 1,000,000 values once its YAML aliases"):
        read_jobs(tmp_path / "bomb.yaml")
    assert time.perf_counter() - t0 < 30


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 200_000])
def test_deep_nesting_is_refused(tmp_path, depth):
    (tmp_path / "deep.json").write_text("[" * depth + "]" * depth)
    with pytest.raises(MeshsplatError, match="nested"):
        read_jobs(tmp_path / "deep.json")
    pytest.importorskip("yaml")
    (tmp_path / "deep.yaml").write_text("[" * depth + "]" * depth)
    with pytest.raises(MeshsplatError, match=r"nested|not valid YAML"):
        read_jobs(tmp_path / "deep.yaml")


def test_an_unclosed_quote_names_its_line(tmp_path):
    (tmp_path / "jobs.txt").write_text("caps/a seed=1\ncaps/b 'seed=2\n")
    with pytest.raises(MeshsplatError, match=r"jobs.txt:2: No closing quotation in \"caps/b 'seed=2\""):
        read_jobs(tmp_path / "jobs.txt")


def test_a_huge_file_is_refused_unread(tmp_path):
    path = tmp_path / "jobs.json"
    with open(path, "wb") as fh:
        fh.truncate(MAX_FILE_BYTES + 1)  # sparse: nothing to read
    with pytest.raises(MeshsplatError, match="is not a jobs file"):
        read_jobs(path)


def test_finished_jobs_are_keyed_by_their_spec(tmp_path):
    make_tiny_dataset(tmp_path / "cap")
    base = {"data": "cap", "iterations": 2, "device": "cpu", "eval": False, "export": []}
    base["set"] = ["model.n_init=100", "backend=torch"]
    (job,) = _jobs(tmp_path, [base])
    out = tmp_path / "out"
    first = run_job(job, out)
    assert first["status"] == "ok" and first["iterations"] == 2, first
    assert finished_result(out, job) == json.loads((out / "cap" / "result.json").read_text())

    (longer,) = _jobs(tmp_path, [{**base, "iterations": 3}])  # edited: more iterations
    assert longer.spec() != job.spec() and finished_result(out, longer) is None
    again = run_job(longer, out)
    assert again["status"] == "ok" and again["iterations"] == 3, again  # resumed, not reported as before

    (changed,) = _jobs(tmp_path, [{**base, "iterations": 3, "set": ["model.n_init=150", "backend=torch"]}])
    row = run_job(changed, out)
    assert row["status"] == "failed"
    assert "the job was edited since its run was trained" in row["reason"] and "model.n_init" in row["reason"]
    assert json.loads((out / "cap" / "result.json").read_text())["spec"] == changed.spec()
    assert finished_result(out, longer) is None  # the failed attempt is on record; the run is untouched
    assert (out / "cap" / "run" / "checkpoints" / "ckpt_00000003.pt").is_file()


def test_a_repeated_name_is_a_failed_job_even_when_the_first_finished(tmp_path):
    make_tiny_dataset(tmp_path / "cap")
    entry = {"data": "cap", "iterations": 2, "device": "cpu", "eval": False, "export": []}
    entry["set"] = ["model.n_init=100", "backend=torch"]
    first, second = _jobs(tmp_path, [entry, {**entry, "iterations": 5}])
    assert run_job(first, tmp_path / "out")["status"] == "ok"
    row = run_job(second, tmp_path / "out")
    assert row["status"] == "failed" and "used by an earlier job" in row["reason"]


HIDE_RAY_CLIENT = """
import sys
class _NoClient:
    def find_spec(self, name, path=None, target=None):
        if name == "grpc" or name.startswith("grpc."):
            raise ModuleNotFoundError("No module named 'grpc' (hidden by the test)")
        return None
sys.meta_path.insert(0, _NoClient())
"""


def test_a_ray_client_address_without_the_client_is_one_line(tmp_path):
    pytest.importorskip("ray")
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(textwrap.dedent(HIDE_RAY_CLIENT))
    (tmp_path / "jobs.json").write_text(json.dumps(["cap"]))
    make_tiny_dataset(tmp_path / "cap")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), *(p for p in sys.path if p)])}
    cmd = [sys.executable, "-m", "meshsplat.cli.main", "batch", str(tmp_path / "jobs.json"), "--out"]
    cmd += [str(tmp_path / "out"), "--address", "ray://127.0.0.1:1", "--no-progress"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert "cannot start or reach the Ray cluster at ray://127.0.0.1:1" in last and "ray[client]" in last
    table = json.loads((tmp_path / "out" / "results.json").read_text())
    assert [r["status"] for r in table] == ["failed"] and table[0]["reason"].startswith(
        "not run: cannot start or reach"
    )


@pytest.mark.slow
def test_ctrl_c_stops_batch_promptly_and_the_same_command_resumes(tmp_path):
    pytest.importorskip("ray")
    from meshsplat.io import load_checkpoint
    from meshsplat.run_folder import RunFolder

    make_tiny_dataset(tmp_path / "cap")
    job = {"data": "cap", "iterations": 100_000, "device": "cpu", "eval": False, "export": []}
    job["set"] = ["model.n_init=100", "backend=torch", "checkpoint_every=2", "loss.lambda_lpips=0"]
    (tmp_path / "jobs.json").write_text(json.dumps([job]))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[2] / "src"), env.get("PYTHONPATH", "")])
    cmd = [sys.executable, "-m", "meshsplat.cli.main", "batch", str(tmp_path / "jobs.json"), "--out"]
    cmd += [str(tmp_path / "out"), "--workers", "1", "--no-progress"]
    # Ctrl-C as a terminal gives it: the test's own process may ignore SIGINT (an xdist worker after some
    # tests), and a child keeps an ignored SIGINT; the whole suite hung here without this
    restore_sigint = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    driver = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=restore_sigint
    )
    run = RunFolder(tmp_path / "out" / "cap" / "run")
    try:
        deadline = time.monotonic() + 240
        while not run.checkpoints() and time.monotonic() < deadline and driver.poll() is None:
            time.sleep(0.1)
        assert run.checkpoints(), "the job should be training"
        t0 = time.monotonic()
        driver.send_signal(signal.SIGINT)
        _, err = driver.communicate(timeout=120)
        assert time.monotonic() - t0 < 60  # not after the job's 100,000 iterations
    finally:
        if driver.poll() is None:
            driver.kill()
    assert driver.returncode != 0 and "Traceback" not in err, err
    (row,) = json.loads((tmp_path / "out" / "results.json").read_text())
    assert row["status"] == "failed" and row["reason"].startswith("interrupted (Ctrl-C)")
    stopped_at = load_checkpoint(run.checkpoints()[-1][1])["iteration"]  # intact
    assert 0 < stopped_at < 100_000
    job["iterations"] = stopped_at + 2  # edited: the same run goes on to the new end
    (tmp_path / "jobs.json").write_text(json.dumps([job]))
    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    (row,) = json.loads((tmp_path / "out" / "results.json").read_text())
    assert row["status"] == "ok" and row["iterations"] == stopped_at + 2
