"""``meshsplat batch``: every job of a jobs file on Ray, an embedded local Ray by default or a cluster.

Each job is one Ray task (one CPU, ``runner.run_job``) that Ray retries when its worker process dies
(``max_retries``); the retry resumes from the job's newest checkpoint, bit for bit. A job with bad input
returns a ``failed`` row and the others go on; a job whose ``result.json`` says ``ok`` is skipped, so
running the same command again finishes only what is left (a job edited since is run again: results are
kept per job spec, ``runner.finished_result``). The driver shows one progress bar for the fleet (jobs done,
running, failed) and writes the results table (``report.write_results``). Ctrl-C cancels the running jobs
(each stops at its next iteration, its checkpoints intact), writes the table with them marked interrupted,
and ends; the same command then resumes them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError
from meshsplat.fleet.jobs import Job, read_jobs
from meshsplat.fleet.report import summary_line, write_results
from meshsplat.fleet.runner import RESULT_KEYS, failed_result, finished_result, run_job

__all__ = ["run_batch", "INTERRUPTED"]

INTERRUPTED = "interrupted (Ctrl-C): run the same command again to resume from the job's last checkpoint"
STOP_GRACE_S = 20.0  # after Ctrl-C, how long cancelled jobs get to stop before the driver leaves


def _ray():
    try:
        import ray
    except ImportError:
        raise MeshsplatError("meshsplat batch needs Ray: pip install 'meshsplat[ray]'") from None
    return ray


def run_batch(
    jobs_file: str | Path,
    out: str | Path,
    address: str | None = None,
    workers: int | None = None,
    retries: int = 3,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Run every job of ``jobs_file`` into ``out/NAME/``; returns the result rows (also written as
    ``out/results.{json,csv,html}``). ``address``: an existing Ray cluster (``ray://HOST:10001`` or
    ``auto``); default an embedded local Ray with ``workers`` CPUs (default all). Uses an already
    started Ray session when there is one."""
    ray = _ray()
    jobs = read_jobs(jobs_file)
    out = Path(out).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict[str, Any]] = {}  # by position: a repeated name is a failed job of its own
    todo: list[tuple[int, Job]] = []
    for i, job in enumerate(jobs):
        if job.problem:
            rows[i] = failed_result(job, job.problem)
        elif (done := finished_result(out, job)) is not None:
            rows[i] = done
        else:
            todo.append((i, job))
    skipped = sum(r.get("status") == "ok" for r in rows.values())
    started_here = not ray.is_initialized()
    try:
        if todo and started_here:
            _init(ray, address, workers)
        try:
            if todo:
                _run_on_ray(ray, todo, out, retries, progress, rows, skipped, len(jobs))
        finally:
            if todo and started_here:
                ray.shutdown()
    except BaseException as exc:  # Ctrl-C or no Ray: the table still says what finished and what did not
        why = INTERRUPTED if isinstance(exc, KeyboardInterrupt) else f"not run: {exc}"
        for i, job in todo:
            rows.setdefault(i, failed_result(job, why))
        write_results(out, [rows[i] for i in range(len(jobs)) if i in rows])
        raise
    ordered = [{k: rows[i].get(k) for k in RESULT_KEYS} for i in range(len(jobs)) if i in rows]  # as the table
    write_results(out, ordered)
    return ordered


def _init(ray, address: str | None, workers: int | None) -> None:
    """Start the embedded Ray or connect to ``address``; a failure is one line."""
    try:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - Ray raises many kinds (ConnectionError, ImportError, RuntimeError)
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        hint = (
            "; a ray:// address needs the Ray client (pip install 'ray[client]') and the head node's client port"
            if address and address.startswith("ray://")
            else "; check the address (or leave --address out for a local Ray)"
            if address
            else ""
        )
        raise MeshsplatError(f"cannot start or reach {where}: {type(exc).__name__}: {first}{hint}") from None


def _run_on_ray(ray, todo, out, retries, progress, rows, skipped, total) -> None:
    task = ray.remote(num_cpus=1, max_retries=retries, retry_exceptions=False)(run_job)
    pending = {task.remote(job, str(out)): (i, job) for i, job in todo}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=skipped, desc="batch", unit="job", dynamic_ncols=True)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                i, job = pending.pop(ref)
                try:
                    rows[i] = ray.get(ref)
                except ray.exceptions.RayError as exc:  # the worker died more than `retries` times
                    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                    rows[i] = failed_result(job, f"worker lost {retries + 1} time(s): {msg}")
                if bar is not None:
                    bar.update(1)
            if bar is not None:
                failed = sum(r.get("status") == "failed" for r in rows.values())
                bar.set_postfix_str(
                    f"{len(pending)} running or queued, {failed} failed, {skipped} skipped (done before)"
                )
    except KeyboardInterrupt:
        for ref in pending:  # a KeyboardInterrupt in each job: it checkpoints at its next iteration and stops
            ray.cancel(ref)
        ray.wait(list(pending), num_returns=len(pending), timeout=STOP_GRACE_S)
        raise
    finally:
        if bar is not None:
            bar.close()
    if progress:
        print(summary_line(list(rows.values())))
