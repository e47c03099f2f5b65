"""``meshsplat batch``: every job of a jobs file on Ray, an embedded local Ray by default or a cluster.

Each job is one Ray task (one CPU, ``runner.run_job``) that Ray retries when its worker process dies
(``max_retries``); the retry resumes from the job's newest checkpoint, bit for bit. A job with bad input
returns a ``failed`` row and the others go on; a job whose ``result.json`` says ``ok`` is skipped, so
running the same command again finishes only what is left. The driver shows one progress bar for the
fleet (jobs done, running, failed) and writes the results table (``report.write_results``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError
from meshsplat.fleet.jobs import Job, read_jobs
from meshsplat.fleet.report import summary_line, write_results
from meshsplat.fleet.runner import failed_result, finished_result, run_job

__all__ = ["run_batch"]


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
    rows: dict[str, dict[str, Any]] = {}
    todo: list[Job] = []
    for job in jobs:
        done = finished_result(out, job.name)
        if done is not None:
            rows[job.name] = done
        elif job.problem:
            rows[job.name] = failed_result(job, job.problem)
        else:
            todo.append(job)
    skipped = sum(r.get("status") == "ok" for r in rows.values())
    started_here = not ray.is_initialized()
    if todo and started_here:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        if todo:
            _run_on_ray(ray, todo, out, retries, progress, rows, skipped, len(jobs))
    finally:
        if todo and started_here:
            ray.shutdown()
    ordered = [rows[j.name] for j in jobs if j.name in rows]
    write_results(out, ordered)
    return ordered


def _run_on_ray(ray, todo, out, retries, progress, rows, skipped, total) -> None:
    task = ray.remote(num_cpus=1, max_retries=retries, retry_exceptions=False)(run_job)
    pending = {task.remote(job, str(out)): job for job in todo}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=skipped, desc="batch", unit="job", dynamic_ncols=True)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                job = pending.pop(ref)
                try:
                    rows[job.name] = ray.get(ref)
                except ray.exceptions.RayError as exc:  # the worker died more than `retries` times
                    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                    rows[job.name] = failed_result(job, f"worker lost {retries + 1} time(s): {msg}")
                if bar is not None:
                    bar.update(1)
            if bar is not None:
                failed = sum(r.get("status") == "failed" for r in rows.values())
                bar.set_postfix_str(
                    f"{len(pending)} running or queued, {failed} failed, {skipped} skipped (done before)"
                )
    finally:
        if bar is not None:
            bar.close()
    if progress:
        print(summary_line(list(rows.values())))
